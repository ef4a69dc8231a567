"""A world file built in PyBullet (DIRECT): boxes on a floor, kinematic poses, overhead rendering.

Shared by world_sim (which moves bodies and asks PyBullet for contacts) and by
each vision system (which keeps its own copy in step and renders its view).
Every body is a flat-coloured box; the light is ambient only and shadows are
off, so a pixel shows exactly its body's colour: the floor can never take a
shade that a colour model matches by accident. A body with a ``tag`` carries it
on top: a textured quad (:mod:`drvs.algorithms.tag_images`) :data:`TAG_LIFT` above the box,
centred on it and turned with it; it has no collision shape, so contacts are the
box's alone. The textures live in a temporary directory the scene removes on
:meth:`Scene.close`.

One :class:`Scene` owns one PyBullet client; PyBullet is not thread-safe, so
callers serialise access (the nodes hold a lock around each call).
"""

from __future__ import annotations

import logging
import math
import shutil
import tempfile
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import pybullet

from drvs.algorithms.tag_images import quad_side, write_quad, write_tag_image
from drvs.sim.depth_noise import DepthNoise
from drvs.sim.world import Body, World
from drvs.vision.camera import PinholeCamera
from drvs.vision.frame import Frame

log = logging.getLogger('rosout.' + __name__)

FLOOR_THICKNESS = 0.02
FLOOR_MARGIN = 100.0
"""The floor's visual plate reaches this far beyond ``floor.size`` so no view shows the background."""
TAG_LIFT = 0.001
"""A tag lies this far (metres) above its body's top, so the two never fight for the depth buffer."""


TINY_RENDERER_SAMPLE = (-0.5, 0.5)
"""Where TinyRenderer samples the scene for array pixel (row r, column c), relative to that
pixel's centre (c + 0.5, r + 0.5) in :mod:`drvs.vision.camera`'s convention: at (c, r + 1). Measured
(test_vision checks it): a flat plate's mask covers exactly the columns c with u_left <= c <= u_right
and the rows r with v_top <= r + 1 <= v_bottom of its projected corners."""


def render_view(
    client: int, camera: PinholeCamera, segmentation: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(RGB (H, W, 3) uint8, depth buffer (H, W) in [0, 1], and with ``segmentation`` the body
    id each pixel shows (-1: none), else None) of ``camera``'s view in PyBullet ``client``, with
    TinyRenderer: ambient light only, no shadows."""
    view = pybullet.computeViewMatrix(camera.eye, camera.target, camera.up, physicsClientId=client)
    projection = pybullet.computeProjectionMatrixFOV(
        camera.fov_deg, camera.aspect, camera.near, camera.far, physicsClientId=client
    )
    width, height, rgba, depth, bodies = pybullet.getCameraImage(
        camera.width,
        camera.height,
        view,
        projection,
        shadow=0,
        lightAmbientCoeff=1.0,
        lightDiffuseCoeff=0.0,
        lightSpecularCoeff=0.0,
        renderer=pybullet.ER_TINY_RENDERER,
        flags=0 if segmentation else pybullet.ER_NO_SEGMENTATION_MASK,
        physicsClientId=client,
    )
    rgb = np.ascontiguousarray(np.reshape(np.asarray(rgba, np.uint8), (height, width, 4))[..., :3])
    shown = np.reshape(np.asarray(bodies, np.int32), (height, width)) if segmentation else None
    return rgb, np.reshape(np.asarray(depth, np.float32), (height, width)), shown


def _rgba(colour: tuple[int, int, int]) -> list[float]:
    return [c / 255.0 for c in colour] + [1.0]


def _quaternion(yaw: float) -> list[float]:
    return [0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)]


class Scene:
    """The bodies of a world in a private PyBullet DIRECT client, addressed by name.

    Names: each robot's and station's (``robot``, ``station`` in the single form) and each
    object's ``name``.
    """

    def __init__(self, world: World):
        self.world = world
        self.client = pybullet.connect(pybullet.DIRECT)
        self.bodies: dict[str, int] = {}
        self.sizes: dict[str, tuple[float, float, float]] = {}
        self.bottoms: dict[str, float] = {}
        """How high above the floor each body's underside is (0 for all but a hanging object)."""
        self.tags: dict[str, int] = {}
        """The tag quad on top of each body that carries one, by body name."""
        self.shiny: list[int] = []
        """The PyBullet ids of the shiny bodies (a depth sensor sees holes on them)."""
        self._poses: dict[str, tuple[float, float, float]] = {}
        self.texture_folder: Path | None = None
        """The temporary directory of the tag textures (None without tags); removed by :meth:`close`."""
        width, depth = world.floor_size
        floor = pybullet.createVisualShape(
            pybullet.GEOM_BOX,
            halfExtents=[width / 2 + FLOOR_MARGIN, depth / 2 + FLOOR_MARGIN, FLOOR_THICKNESS / 2],
            rgbaColor=_rgba(world.floor_colour),
            physicsClientId=self.client,
        )
        self.floor = pybullet.createMultiBody(
            0, -1, floor, [width / 2, depth / 2, -FLOOR_THICKNESS / 2], physicsClientId=self.client
        )
        try:
            for body in (*(b for robot in world.robots for b in (robot.body, robot.station)), *world.objects):
                self._add(body)
        except BaseException:
            self.close()
            raise

    def _add(self, body: Body) -> None:
        half = [s / 2.0 for s in body.size]
        visual = pybullet.createVisualShape(
            pybullet.GEOM_BOX, halfExtents=half, rgbaColor=_rgba(body.colour), physicsClientId=self.client
        )
        collision = pybullet.createCollisionShape(
            pybullet.GEOM_BOX, halfExtents=half, physicsClientId=self.client
        )
        self.bodies[body.name] = pybullet.createMultiBody(
            0, collision, visual, [0, 0, half[2]], physicsClientId=self.client
        )
        self.sizes[body.name] = body.size
        self.bottoms[body.name] = body.bottom
        if body.shiny:
            self.shiny.append(self.bodies[body.name])
        if body.tag is not None:
            self.tags[body.name] = self._add_tag(body)
        self.set_pose(body.name, body.position[0], body.position[1], body.yaw)

    def _add_tag(self, body: Body) -> int:
        """A visual-only textured quad showing ``body.tag``; placed by :meth:`set_pose`."""
        tag = body.tag
        assert tag is not None  # _add calls it for a tagged body
        if self.texture_folder is None:
            self.texture_folder = Path(tempfile.mkdtemp(prefix='drvs_scene_tags_'))
        quad = write_quad(self.texture_folder)
        texture = write_tag_image(self.texture_folder, tag.family, tag.id)
        side = quad_side(tag.family, tag.size)
        shape = pybullet.createVisualShape(
            pybullet.GEOM_MESH, fileName=str(quad), meshScale=[side, side, 1.0], physicsClientId=self.client
        )
        quad_body = pybullet.createMultiBody(0, -1, shape, [0, 0, 0], physicsClientId=self.client)
        texture_id = pybullet.loadTexture(str(texture), physicsClientId=self.client)
        pybullet.changeVisualShape(
            quad_body, -1, textureUniqueId=texture_id, rgbaColor=[1, 1, 1, 1], physicsClientId=self.client
        )
        return quad_body

    # -- poses ---------------------------------------------------------------------------------
    def set_pose(self, name: str, x: float, y: float, yaw: float) -> None:
        """Place body ``name`` with its footprint centred at (x, y), turned by ``yaw`` radians (at
        its own height: on the floor, or ``bottom`` above it)."""
        if self._poses.get(name) == (x, y, yaw):
            return
        pybullet.resetBasePositionAndOrientation(
            self.bodies[name],
            [x, y, self.bottoms[name] + self.sizes[name][2] / 2.0],
            _quaternion(yaw),
            physicsClientId=self.client,
        )
        if name in self.tags:
            pybullet.resetBasePositionAndOrientation(
                self.tags[name],
                [x, y, self.sizes[name][2] + TAG_LIFT],
                _quaternion(yaw),
                physicsClientId=self.client,
            )
        self._poses[name] = (x, y, yaw)

    def pose(self, name: str) -> tuple[float, float, float]:
        return self._poses[name]

    def poses(self) -> dict[str, tuple[float, float, float]]:
        return dict(self._poses)

    def apply_poses(self, poses: dict) -> None:
        """Set every known body's pose from {name: (x, y, yaw)}; unknown names are skipped."""
        for name, (x, y, yaw) in poses.items():
            if name in self.bodies:
                self.set_pose(name, float(x), float(y), float(yaw))

    # -- contacts ------------------------------------------------------------------------------
    def distances(self, name: str, others: Iterable[str], within: float) -> dict[str, float]:
        """Signed distance (negative = penetration) from ``name`` to each of ``others`` closer
        than ``within`` metres."""
        found = {}
        body = self.bodies[name]
        for other in others:
            points = pybullet.getClosestPoints(body, self.bodies[other], within, physicsClientId=self.client)
            if points:
                found[other] = min(point[8] for point in points)
        return found

    # -- rendering -----------------------------------------------------------------------------
    def render(
        self,
        camera: PinholeCamera,
        stamp: float = 0.0,
        noise: DepthNoise | None = None,
        rng: np.random.Generator | None = None,
    ) -> Frame:
        """Render ``camera``'s view with TinyRenderer: flat colours, no shadows; depth perfect, or
        spoilt by ``noise`` with ``rng`` (:mod:`drvs.sim.depth_noise`)."""
        rgb, depth, shown = render_view(
            self.client, camera, segmentation=noise is not None and bool(self.shiny)
        )
        metric = camera.metric_depth(depth)
        if noise is not None:
            shiny = np.isin(shown, self.shiny) if shown is not None else None
            metric = noise.apply(metric, rgb, rng if rng is not None else np.random.default_rng(), shiny)
        return Frame(
            rgb=rgb,
            depth=metric.astype(np.float32),
            camera=camera,
            stamp=stamp,
            sample_offset=TINY_RENDERER_SAMPLE,
        )

    def close(self) -> None:
        if self.client is not None:
            pybullet.disconnect(physicsClientId=self.client)
            self.client = None
        if self.texture_folder is not None:
            shutil.rmtree(self.texture_folder, ignore_errors=True)
            self.texture_folder = None

    def __enter__(self) -> Scene:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
