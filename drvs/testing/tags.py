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

:data:`TAGS` and :data:`CAMERAS` are the scene drvs_calibrate's tests calibrate from
(test/unit/vision/test_calibration.py, and test/live/test_drvs_calibrate.py from a topic),
with the helpers both use to give the command its arguments and to judge its pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pybullet
import yaml

from drvs.algorithms.tag_images import quad_side, write_quad, write_tag_image
from drvs.sim.scene import render_view
from drvs.vision.camera import PinholeCamera
from drvs.vision.optics import optical_pose_of

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
        rgb, _, _ = render_view(client, camera)
    finally:
        pybullet.disconnect(physicsClientId=client)
    return rgb


TAGS = [
    FloorTag(0, (1.0, 1.0), yaw=0.3),
    FloorTag(1, (2.5, 1.2), yaw=1.0),
    FloorTag(2, (1.2, 2.6), yaw=-0.5),
    FloorTag(3, (2.8, 2.8), yaw=2.0),
    FloorTag(4, (2.0, 2.0), yaw=0.0),
    FloorTag(5, (0.5, 2.0), yaw=0.8),
]
"""Six tags on a 3 m floor."""
CAMERAS = {
    'from_the_south': PinholeCamera(
        eye=(1.8, -0.6, 3.0), target=(1.9, 1.7, 0.0), fov_deg=60, width=800, height=600
    ),
    'from_the_north_east': PinholeCamera(
        eye=(4.0, 3.6, 2.8), target=(2.0, 1.9, 0.0), fov_deg=60, width=800, height=600
    ),
    'from_the_west_turned': PinholeCamera(
        eye=(-0.5, 1.0, 3.2), target=(1.5, 1.9, 0.0), fov_deg=60, width=800, height=600, up=(1.0, 0.0, 0.0)
    ),
}
"""Three cameras that see all of :data:`TAGS`."""
POSITION_TOLERANCE = 0.01  # metres
ANGLE_TOLERANCE = 0.5  # degrees
"""How close a pose calibrated from a rendered view of :data:`TAGS` must come to the camera's."""


def tag_args(tags: list[FloorTag]) -> list[str]:
    """drvs_calibrate's ``--tag ID:X,Y`` arguments for ``tags``."""
    return [arg for tag in tags for arg in ('--tag', f'{tag.id}:{tag.position[0]},{tag.position[1]}')]


def pose_errors(camera: PinholeCamera, rotation, translation) -> tuple[float, float]:
    """(metres, degrees) between a recovered optical-frame pose and the camera's."""
    true_rotation, true_translation = optical_pose_of(camera)
    cosine = (np.trace(np.asarray(rotation).T @ true_rotation) - 1.0) / 2.0
    angle = math.degrees(math.acos(min(1.0, max(-1.0, cosine))))
    return float(np.linalg.norm(np.asarray(translation) - true_translation)), angle


def write_camera_info(path: Path, K, size=(800, 600), distortion=(0.0, 0.0, 0.0, 0.0, 0.0)) -> Path:
    """A camera_calibration_parsers YAML file, as a ROS camera driver saves it."""
    path.write_text(
        yaml.safe_dump(
            {
                'image_width': int(size[0]),
                'image_height': int(size[1]),
                'camera_name': 'cam1',
                'camera_matrix': {'rows': 3, 'cols': 3, 'data': [float(v) for v in np.ravel(K)]},
                'distortion_model': 'plumb_bob',
                'distortion_coefficients': {'rows': 1, 'cols': 5, 'data': [float(d) for d in distortion]},
                'rectification_matrix': {'rows': 3, 'cols': 3, 'data': [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]},
                'projection_matrix': {
                    'rows': 3,
                    'cols': 4,
                    'data': [
                        float(K[0, 0]),
                        0,
                        float(K[0, 2]),
                        0,
                        0,
                        float(K[1, 1]),
                        float(K[1, 2]),
                        0,
                        0,
                        0,
                        1.0,
                        0,
                    ],
                },
            },
            sort_keys=False,
        )
    )
    return path
