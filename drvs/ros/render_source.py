"""A vision system's frames rendered from its own copy of the simulated world (``~source:=render``).

The simulation's shortcut, and the only frame source that imports pybullet: the vision system
imports this module only when ``~source`` is ``render``. It answers what
:class:`drvs.ros.frame_sources.TopicSource` answers, and puts its camera on tf as sim_camera
does. Described in docs/nodes/vision_system.md.
"""

from __future__ import annotations

import threading
from dataclasses import replace

import rospy

from drvs.ros.frame_sources import FrameUnavailable
from drvs.ros.tf_frames import camera_transform, optical_frame
from drvs.ros.world_poses import LatestPoses
from drvs.sim.scene import Scene
from drvs.sim.simulation import mount_position
from drvs.sim.world_file import load_world
from drvs.vision.camera import PinholeCamera
from drvs.vision.frame import Frame
from drvs.vision.pipeline import FrameCache

__all__ = ['RenderSource']


class RenderSource:
    """Frames rendered on demand from a private copy of the world, kept in step with world_sim's
    poses (``~poses_topic``).

    :param count: the node's counter (``renders``, ``cache_hits``).
    """

    name = 'render'
    depth = True  # the renderer's depth buffer comes with every frame
    pose_problem = None  # the world file gives the pose
    depth_problem = None  # the renderer's depth always fits

    def __init__(self, params, count):
        self.world = load_world(params.world)
        self.config = self.world.camera(params.camera)
        self.params = params
        self.base_camera = PinholeCamera.from_config(self.config)
        self._count = count
        self.scene: Scene | None = None
        self._scene_lock = threading.Lock()  # PyBullet is not thread-safe
        self.poses = LatestPoses(params.poses_topic)
        self._start_time = 0.0
        self.cache = FrameCache(self._capture, params.max_frame_age, clock=rospy.get_time)
        self.frame_id = optical_frame(self.config.name)
        self._broadcaster = None  # tf, made by start(): static for a fixed camera
        self._fixed_footprint: list | None = None
        self.noise = self.config.depth_noise  # the depth sensor's imperfections (None: perfect depth)
        self._rng = self.noise.generator(self.config.name) if self.noise is not None else None

    @property
    def moving(self) -> bool:
        """Whether the camera is on a moving mount (its pose must be broadcast as it goes)."""
        return bool(self.config.moving)

    def tag_heights(self) -> dict:
        """The heights of the world's AprilTags, for the apriltag algorithm."""
        return self.world.tag_heights()

    def start(self) -> None:
        import tf2_ros

        self.scene = Scene(self.world)
        self._start_time = rospy.get_time()
        self.poses.start()
        if self.moving:
            self._broadcaster = tf2_ros.TransformBroadcaster()
            self.broadcast_pose()
        else:
            self._broadcaster = tf2_ros.StaticTransformBroadcaster()
            stamp = rospy.Time.from_sec(self._start_time)
            self._broadcaster.sendTransform(camera_transform(self.base_camera, self.frame_id, stamp))

    def broadcast_pose(self) -> None:
        """A moving camera's pose now, on ``/tf`` (a fixed one is on ``/tf_static`` from the start)."""
        now = rospy.get_time()
        transform = camera_transform(self.camera_at(now), self.frame_id, rospy.Time.from_sec(now))
        self._broadcaster.sendTransform(transform)

    def frame_age(self) -> float | None:
        """None: frames are rendered on demand, so they cannot go stale."""
        return None

    def describe(self) -> str:
        camera = self.base_camera
        return (
            f'camera {self.config.name} at {camera.eye} looking at {camera.target}, '
            f'{camera.width}x{camera.height}, fov {camera.fov_deg:.0f} deg (rendered)'
        )

    def camera_at(self, stamp: float) -> PinholeCamera:
        """The camera model at time ``stamp`` (its mount may move along its waypoints)."""
        if not self.config.moving:
            return self.base_camera
        return self.base_camera.moved_to(*mount_position(self.config, stamp - self._start_time))

    def _capture(self, stamp: float) -> Frame:
        _, poses = self.poses.latest()
        with self._scene_lock:
            if self.scene is None:
                raise FrameUnavailable('the vision system is shutting down')
            if poses:
                self.scene.apply_poses(poses)
            frame = self.scene.render(self.camera_at(stamp), stamp, self.noise, self._rng)
        self._count(renders=1)
        return frame

    def frame(self, arrival: float) -> tuple[Frame, bool]:
        """(frame, whether it was reused from a capture shared with earlier requests)."""
        frame, reused = self.cache.get(arrival)
        if reused:
            self._count(cache_hits=1)
        return frame, reused

    def newest(self) -> Frame:
        return self.cache.get(rospy.get_time())[0]

    def latest(self) -> Frame | None:
        """The last frame rendered, if any (no new render for a look before a request)."""
        return self.cache.last

    def empty_floor(self):
        """The camera's view of the world without a body in it, (H, W, 3) RGB: ``foreground``'s reference."""
        empty = replace(self.world, robots=(), objects=())
        with self._scene_lock, Scene(empty) as scene:
            return scene.render(self.base_camera).rgb

    def footprint(self) -> list | None:
        if not self.config.moving:  # asked 20 times a second: a fixed camera's never changes
            if self._fixed_footprint is None:
                self._fixed_footprint = self.base_camera.floor_footprint(self.world.floor_size)
            return self._fixed_footprint
        return self.camera_at(rospy.get_time()).floor_footprint(self.world.floor_size)

    def unavailable(self) -> str | None:
        return None

    def close(self) -> None:
        with self._scene_lock:
            if self.scene is not None:
                self.scene.close()
                self.scene = None
