"""The sim_camera node: the simulated world's vision systems as ROS camera drivers (images,
CameraInfo, tf), rendered with PyBullet from world_sim's poses.

Simulation glue (it imports pybullet). Parameters, topics, tf frames and timing are in
docs/nodes/sim_camera.md.
"""

from __future__ import annotations

import sys
import threading
import time

import cv2
import numpy as np
import rospy
import tf2_ros
from geometry_msgs.msg import TransformStamped
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header

from drvs.common.settings import ParamError
from drvs.ros.node import NodeScaffold
from drvs.ros.tf_frames import camera_transform, optical_frame
from drvs.ros.world_poses import LatestPoses
from drvs.sim.lens import Lens
from drvs.sim.params import SimCameraParams
from drvs.sim.scene import TINY_RENDERER_SAMPLE, Scene
from drvs.sim.simulation import mount_position
from drvs.sim.world import Camera
from drvs.sim.world_file import load_world
from drvs.vision.camera import PinholeCamera
from drvs.vision.frame import Frame
from drvs.vision.optics import intrinsics_of

SLOW_LOG_PERIOD = 10.0
"""Seconds between debug lines saying that rendering falls behind ``~rate``."""


def selected_cameras(world, names: tuple[str, ...]) -> tuple[Camera, ...]:
    """The world's vision systems named in ``~cameras`` (all of them for none).

    :raises ParamError: naming the unknown camera and the known ones.
    """
    if not names:
        return tuple(world.vision_systems)
    known = [camera.name for camera in world.vision_systems]
    for name in names:
        if name not in known:
            raise ParamError(
                'cameras', f'no vision system named {name!r} in {world.path} (known: {", ".join(known)})'
            )
    return tuple(world.camera(name) for name in dict.fromkeys(names))


# -- messages ----------------------------------------------------------------------------------
def image_message(array: np.ndarray, encoding: str, header: Header) -> Image:
    """A sensor_msgs/Image of an rgb8 (H, W, 3) uint8 or 32FC1 (H, W) float32 array."""
    array = np.ascontiguousarray(array)
    height, width = array.shape[:2]
    return Image(
        header=header,
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=int(sys.byteorder == 'big'),
        step=array.strides[0],
        data=array.tobytes(),
    )


def compressed_message(
    rgb: np.ndarray, header: Header, compression: str, jpeg_quality: int
) -> CompressedImage:
    """An rgb8 image compressed as image_transport's ``compressed`` plugin does (BGR inside)."""
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    if compression == 'jpeg':
        ok, data = cv2.imencode('.jpg', bgr, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
    else:
        ok, data = cv2.imencode('.png', bgr)
    if not ok:
        raise RuntimeError(f'cv2.imencode failed to write {compression} of a {rgb.shape} image')
    return CompressedImage(header=header, format=f'rgb8; {compression} compressed bgr8', data=data.tobytes())


def camera_info_message(K: np.ndarray, D, width: int, height: int, header: Header) -> CameraInfo:
    """CameraInfo of a camera whose images need no rectifying rotation: R = I, P = [K | 0]."""
    K = np.asarray(K, float)
    return CameraInfo(
        header=header,
        width=width,
        height=height,
        distortion_model='plumb_bob',
        D=[float(d) for d in D],
        K=K.flatten().tolist(),
        R=np.eye(3).flatten().tolist(),
        P=np.hstack([K, np.zeros((3, 1))]).flatten().tolist(),
    )


# -- the node ----------------------------------------------------------------------------------
class Feed:
    """One camera: its optics (ideal, or a lens over a padded canvas), publishers and last stamp."""

    def __init__(self, config: Camera):
        self.config = config
        self.camera = PinholeCamera.from_config(config)
        self.frame_id = optical_frame(config.name)
        if config.distortion:
            self.lens: Lens | None = Lens(self.camera, tuple(config.distortion), TINY_RENDERER_SAMPLE)
            self.canvas = self.lens.canvas
            self.K = np.asarray(self.lens.model.K, float)
            self.D = tuple(float(d) for d in self.lens.model.D)
        else:
            self.lens = None
            self.canvas = self.camera
            self.K = intrinsics_of(self.camera, TINY_RENDERER_SAMPLE)
            self.D = (0.0,) * 5
        self.noise = config.depth_noise
        self.rng = self.noise.generator(config.name) if self.noise is not None else None
        self.last_stamp: float | None = None
        self.image_pub = self.info_pub = self.depth_pub = self.compressed_pub = None

    def advertise(self, depth: bool) -> None:
        name = self.config.name
        self.image_pub = rospy.Publisher(f'{name}/image_raw', Image, queue_size=2)
        self.info_pub = rospy.Publisher(f'{name}/camera_info', CameraInfo, queue_size=2)
        self.compressed_pub = rospy.Publisher(f'{name}/image_raw/compressed', CompressedImage, queue_size=2)
        if depth:
            self.depth_pub = rospy.Publisher(f'{name}/depth/image_raw', Image, queue_size=2)

    def unadvertise(self) -> None:
        for publisher in (self.image_pub, self.info_pub, self.depth_pub, self.compressed_pub):
            if publisher is not None:
                publisher.unregister()

    def subscribed(self) -> bool:
        """Whether anyone subscribes to the colour, depth or compressed image."""
        return any(
            publisher is not None and publisher.get_num_connections() > 0
            for publisher in (self.image_pub, self.depth_pub, self.compressed_pub)
        )

    def camera_at(self, elapsed: float, camera: PinholeCamera) -> PinholeCamera:
        """``camera`` moved with the mount to where it is ``elapsed`` s after the start."""
        if not self.config.moving:
            return camera
        return camera.moved_to(*mount_position(self.config, elapsed))


class SimCameraNode:
    """Renders and publishes the cameras; :meth:`start` does the work, :meth:`stop` undoes it."""

    def __init__(self, params: SimCameraParams):
        self.params = params
        self.world = load_world(params.world)
        self.feeds = []
        for config in selected_cameras(self.world, params.camera_names):
            try:
                self.feeds.append(Feed(config))
            except ValueError as error:  # a lens that cannot be simulated (drvs.sim.lens)
                raise ValueError(f'{self.world.path}: vision_systems {config.name}: {error}') from None
        self.scene: Scene | None = None
        self._scene_lock = threading.Lock()  # PyBullet is not thread-safe; stop() closes the scene
        self.poses = LatestPoses(params.poses_topic)
        self.node = NodeScaffold(None)  # no /diagnostics: a simulation node is not part of DRVS
        self._start_time = 0.0

    # -- lifecycle -----------------------------------------------------------------------------
    def start(self) -> None:
        self.scene = Scene(self.world)
        self._start_time = rospy.get_time()
        for feed in self.feeds:
            feed.advertise(self.params.depth)
        self.tf_broadcaster = tf2_ros.TransformBroadcaster()
        self.static_broadcaster = tf2_ros.StaticTransformBroadcaster()
        now = rospy.Time.from_sec(self._start_time)
        fixed = [self._transform(feed, feed.camera, now) for feed in self.feeds if not feed.config.moving]
        if fixed:
            self.static_broadcaster.sendTransform(fixed)
        self.poses.start()
        self.node.spawn(self._render_loop, 'render')
        rospy.on_shutdown(self.stop)
        for feed in self.feeds:
            rospy.loginfo(
                '%s: camera %s: %dx%d, fov %.0f deg, %s, %s; frame %s',
                rospy.get_name(),
                feed.config.name,
                feed.camera.width,
                feed.camera.height,
                feed.camera.fov_deg,
                f'lens D={list(feed.D)}' if feed.lens else 'ideal lens',
                'moving mount' if feed.config.moving else 'fixed',
                feed.frame_id,
            )
        rospy.loginfo(
            '%s: %d camera(s) at up to %g Hz while subscribed; poses from %s',
            rospy.get_name(),
            len(self.feeds),
            self.params.rate,
            self.params.poses_topic,
        )

    def stop(self) -> None:
        """Stop the loop, withdraw the topics, release the scene (also after the loop failed)."""
        self.node.stop(join=5.0)
        with self._scene_lock:
            if self.scene is None:  # stopped already
                return
            self.scene.close()
            self.scene = None
        for feed in self.feeds:
            feed.unadvertise()

    # -- rendering -----------------------------------------------------------------------------
    def _render_loop(self) -> None:
        period = 1.0 / self.params.rate
        next_cycle = time.monotonic()
        while not self.node.stopped:
            started = time.monotonic()
            published = 0
            for feed in self.feeds:
                if self.node.stopped:
                    return
                if feed.subscribed():
                    published += self._publish(feed)
            next_cycle += period
            delay = next_cycle - time.monotonic()
            if delay < 0:  # fell behind: go on at once, without a burst to catch up
                if published:
                    rospy.logdebug_throttle(
                        SLOW_LOG_PERIOD,
                        '%s: %d frame(s) took %.3f s, more than the %.3f s of ~rate: publishing as fast as '
                        'rendering allows',
                        rospy.get_name(),
                        published,
                        time.monotonic() - started,
                        period,
                    )
                next_cycle, delay = time.monotonic(), 0.0
            self.node.wait(delay)

    def render(self, feed: Feed) -> Frame | None:
        """The camera's view of the latest poses, distorted by its lens; None if it shows nothing new."""
        stamp, poses = self.poses.latest()
        if stamp is None:
            stamp = rospy.get_time()  # no poses yet: the world file's, now
        if stamp == feed.last_stamp:  # it would only repeat the last (and tf warn of a repeat)
            return None
        with self._scene_lock:
            if self.scene is None:  # stopped
                return None
            if poses:
                self.scene.apply_poses(poses)
            camera = feed.camera_at(stamp - self._start_time, feed.canvas)
            frame = self.scene.render(camera, stamp, feed.noise, feed.rng)
        return feed.lens.apply(frame) if feed.lens is not None else frame

    def _publish(self, feed: Feed) -> int:
        """Render and publish one frame of ``feed`` (tf first); the number of frames published."""
        frame = self.render(feed)
        if frame is None:
            return 0
        stamp = rospy.Time.from_sec(frame.stamp)
        if feed.config.moving:
            camera = feed.camera_at(frame.stamp - self._start_time, feed.camera)
            self.tf_broadcaster.sendTransform(self._transform(feed, camera, stamp))
        height, width = frame.rgb.shape[:2]
        if feed.image_pub.get_num_connections() > 0:
            feed.image_pub.publish(image_message(frame.rgb, 'rgb8', self._header(feed, stamp)))
        if feed.depth_pub is not None and feed.depth_pub.get_num_connections() > 0:
            depth = np.asarray(frame.depth, np.float32)
            feed.depth_pub.publish(image_message(depth, '32FC1', self._header(feed, stamp)))
        if feed.compressed_pub.get_num_connections() > 0:
            feed.compressed_pub.publish(
                compressed_message(
                    frame.rgb, self._header(feed, stamp), self.params.compression, self.params.jpeg_quality
                )
            )
        feed.info_pub.publish(camera_info_message(feed.K, feed.D, width, height, self._header(feed, stamp)))
        feed.last_stamp = frame.stamp
        return 1

    @staticmethod
    def _header(feed: Feed, stamp: rospy.Time) -> Header:
        return Header(stamp=stamp, frame_id=feed.frame_id)  # one each: a publisher sets its own seq

    @staticmethod
    def _transform(feed: Feed, camera: PinholeCamera, stamp: rospy.Time) -> TransformStamped:
        return camera_transform(camera, feed.frame_id, stamp)
