"""AprilTags (tag36h11) lying on a floor, rendered with PyBullet's TinyRenderer: views for drvs_calibrate.

Each tag is a flat textured quad at z = 0 on a grey floor plate (a little below it,
so the two never fight for the depth buffer), with the image of
:func:`drvs.algorithms.tag_images.tag_image` (the marker in a white quiet zone one cell wide; a
tag of ``size`` is the black square). Seen from above, the printed top of a tag at
``yaw`` 0 points along +y of ``map`` and its left edge is towards -x; ``yaw`` turns
it counter-clockwise. The quad is an OBJ file written next to the textures.
The view is lit as :meth:`drvs.sim.scene.Scene.render` lights it (ambient only), so
the array's pixels follow :data:`drvs.sim.scene.TINY_RENDERER_SAMPLE` and
``drvs.vision.optics.intrinsics_of(camera, TINY_RENDERER_SAMPLE)`` is its ``K``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pybullet

from drvs.algorithms.tag_images import quad_side, write_quad, write_tag_image
from drvs.sim.scene import render_view
from drvs.vision.camera import PinholeCamera

FAMILY = 'tag36h11'
FLOOR_DEPTH = 0.01
"""The floor plate's top is this far below the tags."""


@dataclass(frozen=True)
class FloorTag:
    """Tag ``id`` with its centre at ``position`` on the floor, turned by ``yaw`` radians; ``size`` metres."""

    id: int
    position: tuple[float, float]
    yaw: float = 0.0
    size: float = 0.3

    def corners(self) -> np.ndarray:
        """The black square's corners in ``map`` (4 x 3), in aruco's order: the printed top-left
        first, then clockwise as seen from above."""
        half = self.size / 2.0
        local = np.array([[-half, half], [half, half], [half, -half], [-half, -half]])
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        turned = local @ np.array([[c, s], [-s, c]]) + np.asarray(self.position, float)
        return np.c_[turned, np.zeros(4)]


def render_floor_tags(
    camera: PinholeCamera,
    tags: list[FloorTag],
    folder: str | Path,
    floor_colour: tuple[int, int, int] = (150, 150, 150),
) -> np.ndarray:
    """The camera's view (RGB, height x width x 3, uint8) of ``tags`` on a floor; files go to ``folder``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    quad = write_quad(folder)
    client = pybullet.connect(pybullet.DIRECT)
    try:
        plate = pybullet.createVisualShape(
            pybullet.GEOM_BOX,
            halfExtents=[100.0, 100.0, 0.01],
            rgbaColor=[c / 255.0 for c in floor_colour] + [1.0],
            physicsClientId=client,
        )
        pybullet.createMultiBody(0, -1, plate, [0, 0, -FLOOR_DEPTH - 0.01], physicsClientId=client)
        for tag in tags:
            texture = write_tag_image(folder, FAMILY, tag.id)
            side = quad_side(FAMILY, tag.size)
            shape = pybullet.createVisualShape(
                pybullet.GEOM_MESH, fileName=str(quad), meshScale=[side, side, 1.0], physicsClientId=client
            )
            body = pybullet.createMultiBody(
                0,
                -1,
                shape,
                [*tag.position, 0.0],
                [0.0, 0.0, math.sin(tag.yaw / 2.0), math.cos(tag.yaw / 2.0)],
                physicsClientId=client,
            )
            texture_id = pybullet.loadTexture(str(texture), physicsClientId=client)
            pybullet.changeVisualShape(
                body, -1, textureUniqueId=texture_id, rgbaColor=[1, 1, 1, 1], physicsClientId=client
            )
        rgb, _ = render_view(client, camera)
    finally:
        pybullet.disconnect(physicsClientId=client)
    return rgb
