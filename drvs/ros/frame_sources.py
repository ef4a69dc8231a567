"""A vision system's frames from a ROS camera (``~source:=topic``): :class:`TopicSource`.

It reads the image (raw or compressed), CameraInfo, an optional aligned depth image and the
camera's pose on tf, and imports no pybullet. :mod:`drvs.ros.render_source`, the simulation's
source, answers the same questions: a frame for a request (``frame``), the floor area to register
(``footprint``: None while unknown, [] to unregister), why requests cannot be served now
(``unavailable``). Described in docs/nodes/vision_system.md.
"""

from __future__ import annotations

import math
import threading

import numpy as np
import rospy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from drvs.common.transforms import matrix_from_quaternion
from drvs.vision.frame import Frame
from drvs.vision.frame_feed import FrameFeed, FrameTimeout
from drvs.vision.optics import CameraModel

SUPPORTED_DISTORTION = ('plumb_bob', 'rational_polynomial', '')
"""CameraInfo distortion models OpenCV's pinhole functions read (an empty D means none)."""

IMAGE_BUFFER = 1 << 25
"""Bytes of socket buffer per image subscription: room for one 4096 x 2048 rgb8 frame, so
rospy's latest-only queue drops old frames instead of reading a backlog."""


FRAMES_BEFORE_INFO = 10
"""Frames that may arrive before the first CameraInfo without a warning (they race at start)."""


class FrameUnavailable(RuntimeError):
    """No frame can be had for a request; the message says why and what to check."""


class _Received:
    """One frame as it arrived (messages), decoded into a :class:`Frame` once, when first used."""

    def __init__(self, image, depth, info: CameraInfo):
        self.image = image
        self.depth = depth
        self.info = info
        self.stamp = image.header.stamp.to_sec()
        self.decoded: Frame | None = None
        self.lock = threading.Lock()


class TopicSource:
    """Frames from a camera topic, its CameraInfo and tf (``~source:=topic``)."""

    name = 'topic'
    moving = False  # the camera's driver puts its pose on tf

    def __init__(self, params, count):
        from cv_bridge import CvBridge

        self.params = params
        self._count = count
        self.bridge = CvBridge()
        self.feed = FrameFeed(
            params.max_frame_age, params.frame_timeout, params.stale_after, clock=rospy.get_time
        )
        self._info: CameraInfo | None = None
        self._intrinsics: CameraModel | None = None  # at the identity pose
        self._info_problem: str | None = None
        self._info_lock = threading.Lock()
        self._frames_without_info = 0
        self._info_version = 0  # counts CameraInfo changes: the footprint is computed again
        self._footprint_key = None
        self._footprint: list = []
        self.tf_buffer = None
        self.image_topic = ''
        self.pose_problem: str | None = None  # why the camera's pose is not known now (no tf), else None
        self.depth_problem: str | None = None  # why the newest depth image was left out, else None

    def start(self) -> None:
        import message_filters
        import tf2_ros

        self.tf_buffer = tf2_ros.Buffer(cache_time=rospy.Duration(30.0))
        self._tf_listener = tf2_ros.TransformListener(self.tf_buffer)
        # As image_transport does: the remapped base topic, then its transport's subtopic.
        image_type, image_name = Image, rospy.resolve_name('image')
        if self.params.compressed:
            image_type, image_name = CompressedImage, image_name + '/compressed'
        self.image_topic = image_name
        rospy.Subscriber('camera_info', CameraInfo, self._on_info, queue_size=1)
        if self.params.depth:
            self.depth_topic = rospy.resolve_name('depth')
            subscribers = [
                message_filters.Subscriber(image_name, image_type, queue_size=2, buff_size=IMAGE_BUFFER),
                message_filters.Subscriber('depth', Image, queue_size=2, buff_size=IMAGE_BUFFER),
            ]
            self._sync = message_filters.TimeSynchronizer(subscribers, queue_size=4)
            self._sync.registerCallback(self._on_frame)
        else:
            rospy.Subscriber(image_name, image_type, self._on_frame, queue_size=1, buff_size=IMAGE_BUFFER)

    @property
    def depth(self) -> bool:
        """Whether frames come with a depth image (``~depth``): algorithms that need one run."""
        return bool(self.params.depth)

    def tag_heights(self) -> dict:
        """None known: a request (``h=H``) or ``~tag_height`` says how high a tag lies."""
        return {}

    def describe(self) -> str:
        depth = f' with depth {self.depth_topic}' if self.params.depth else ''
        return f'camera topic {self.image_topic}{depth}, {rospy.resolve_name("camera_info")}, tf'

    # -- subscriptions ---------------------------------------------------------------------------
    def _on_info(self, info: CameraInfo) -> None:
        with self._info_lock:
            if self._info is not None and _same_info(self._info, info):
                return
            self._info = info
            self._info_version += 1
            try:
                self._intrinsics = camera_model_of(info)
                self._info_problem = None
            except ValueError as error:
                self._intrinsics = None
                self._info_problem = str(error)
        if self._info_problem:
            rospy.logerr('%s: %s', rospy.get_name(), self._info_problem)

    def _on_frame(self, image, depth=None) -> None:
        with self._info_lock:
            info = self._info
        if info is None:
            self._frames_without_info += 1
            if self._frames_without_info > FRAMES_BEFORE_INFO:  # not just the first frame's race
                rospy.logwarn_throttle(
                    10.0,
                    '%s: %d frames arrived on %s but no CameraInfo on %s: is the driver calibrated?',
                    rospy.get_name(),
                    self._frames_without_info,
                    self.image_topic,
                    rospy.resolve_name('camera_info'),
                )
            return
        self.feed.put(_Received(image, depth, info))

    # -- frames ----------------------------------------------------------------------------------
    def frame(self, arrival: float) -> tuple[Frame, bool]:
        try:
            received = self.feed.get()
        except FrameTimeout as error:
            raise FrameUnavailable(f'{self.image_topic}: {error}') from None
        return self._decode(received), False

    def newest(self) -> Frame | None:
        received = self.feed.newest()
        return None if received is None else self._decode(received)

    def latest(self) -> Frame | None:
        """The newest frame if it can be decoded now (for a look at it before a request), else None."""
        try:
            return self.newest()
        except FrameUnavailable:
            return None

    def _decode(self, received: _Received) -> Frame:
        with received.lock:
            if received.decoded is None:
                received.decoded = self._frame_of(received)
                self._count(renders=1)
            return received.decoded

    def _frame_of(self, received: _Received) -> Frame:
        with self._info_lock:
            model, problem = self._intrinsics, self._info_problem
        if model is None:
            raise FrameUnavailable(problem or 'no usable CameraInfo')
        image = received.image
        if isinstance(image, CompressedImage):
            rgb = self.bridge.compressed_imgmsg_to_cv2(image, 'rgb8')
        else:
            rgb = self.bridge.imgmsg_to_cv2(image, 'rgb8')
        height, width = rgb.shape[:2]
        if (width, height) != (model.width, model.height):
            raise FrameUnavailable(
                f'{self.image_topic}: image is {width}x{height} but CameraInfo says '
                f'{model.width}x{model.height}'
            )
        depth = None
        if received.depth is not None:
            try:
                depth = self.depth_metres(received.depth)
                if depth.shape != (height, width):
                    raise FrameUnavailable(
                        f'{self.depth_topic}: depth image is {depth.shape[1]}x{depth.shape[0]}, '
                        f'not registered to the {width}x{height} colour image'
                    )
            except FrameUnavailable as error:  # the colour image still serves colour algorithms
                depth, self.depth_problem = None, str(error)
                rospy.logwarn_throttle(10.0, '%s: depth left out: %s', rospy.get_name(), error)
            else:
                self.depth_problem = None
        rotation, translation = self.pose(image.header.frame_id, image.header.stamp)
        return Frame(
            rgb=np.ascontiguousarray(rgb),
            depth=depth,
            camera=model.with_pose(rotation, translation),
            stamp=received.stamp,
        )

    def depth_metres(self, message: Image) -> np.ndarray:
        """A depth image in metres (float32; 0 or NaN where it has no value)."""
        if message.encoding == '32FC1':
            return np.asarray(self.bridge.imgmsg_to_cv2(message, '32FC1'), np.float32)
        if message.encoding == '16UC1':
            return self.bridge.imgmsg_to_cv2(message, '16UC1').astype(np.float32) / 1000.0
        raise FrameUnavailable(
            f'{self.depth_topic}: depth encoding {message.encoding!r}; expected 32FC1 (metres) '
            'or 16UC1 (millimetres)'
        )

    def pose(self, frame_id: str, stamp) -> tuple[np.ndarray, np.ndarray]:
        """(rotation, translation) of ``frame_id`` in the map frame at ``stamp`` (latest: Time(0))."""
        import tf2_ros

        if not frame_id:
            raise FrameUnavailable(f'{self.image_topic}: the image has no header.frame_id')
        try:
            transform = self.tf_buffer.lookup_transform(
                self.params.map_frame, frame_id, stamp, rospy.Duration(self.params.tf_timeout)
            ).transform
        except tf2_ros.TransformException as error:
            raise FrameUnavailable(
                f'no transform {self.params.map_frame} <- {frame_id} at {stamp.to_sec():.3f}: {error}'
                ' (publish the camera pose on tf, e.g. with static_transform_publisher)'
            ) from None
        q, t = transform.rotation, transform.translation
        return matrix_from_quaternion((q.x, q.y, q.z, q.w)), np.array([t.x, t.y, t.z])

    # -- registration ----------------------------------------------------------------------------
    def footprint(self) -> list | None:
        """The floor the camera sees now; [] while the feed is stale; None while not yet known."""
        if self.feed.stale():
            return []
        with self._info_lock:
            model, info, version = self._intrinsics, self._info, self._info_version
        if model is None:
            return None
        try:
            rotation, translation = self.pose(info.header.frame_id or self._frame_id(), rospy.Time(0))
        except FrameUnavailable as error:
            self.pose_problem = f'no calibrated pose: {error}'
            rospy.logwarn_throttle(10.0, '%s: not registering yet: %s', rospy.get_name(), error)
            return None
        self.pose_problem = None
        key = (version, rotation.round(6).tobytes(), translation.round(6).tobytes())
        if key != self._footprint_key:
            self._footprint = model.with_pose(rotation, translation).floor_footprint(self.params.max_range)
            self._footprint_key = key
            if not self._footprint:
                rospy.logwarn_throttle(
                    10.0,
                    '%s: the camera at %s sees no floor within ~max_range %.1f m: not registering',
                    rospy.get_name(),
                    np.round(translation, 3).tolist(),
                    self.params.max_range,
                )
        return self._footprint

    def _frame_id(self) -> str:
        received = self.feed.newest()
        return received.image.header.frame_id if received is not None else ''

    def frame_age(self) -> float | None:
        """Seconds since the newest frame arrived; None before the first."""
        age = self.feed.age()
        return age if math.isfinite(age) else None

    def unavailable(self) -> str | None:
        """Why requests cannot be served now (a stale feed, no pose on tf), or None."""
        if self.feed.stale():
            age = self.feed.age()
            since = 'no frame yet' if age == float('inf') else f'no frame for {age:.1f} s'
            return f'{self.image_topic}: {since}'
        return self.pose_problem

    def close(self) -> None:
        pass


def camera_model_of(info: CameraInfo) -> CameraModel:
    """The intrinsics of a CameraInfo (at the identity pose), or ValueError saying what is wrong."""
    from image_geometry import PinholeCameraModel

    if info.distortion_model not in SUPPORTED_DISTORTION:
        raise ValueError(
            f'CameraInfo distortion_model {info.distortion_model!r} is not supported; '
            f'use one of {", ".join(repr(m) for m in SUPPORTED_DISTORTION)}'
        )
    if info.binning_x > 1 or info.binning_y > 1 or info.roi.width or info.roi.height:
        raise ValueError(
            'CameraInfo with binning or a region of interest is not supported; publish full frames'
        )
    if not info.width or not info.height or not info.K[0] or not info.K[4]:
        raise ValueError(
            f'CameraInfo is uncalibrated (width {info.width}, height {info.height}, K {list(info.K)})'
        )
    model = PinholeCameraModel()
    model.fromCameraInfo(info)
    coefficients = tuple(float(c) for c in np.ravel(model.distortionCoeffs()))
    return CameraModel(
        K=np.asarray(model.intrinsicMatrix(), float),
        D=coefficients if any(coefficients) else (),
        width=int(info.width),
        height=int(info.height),
        rotation=np.eye(3),
        translation=np.zeros(3),
    )


def _same_info(a: CameraInfo, b: CameraInfo) -> bool:
    return (
        a.header.frame_id == b.header.frame_id
        and (a.width, a.height, a.distortion_model) == (b.width, b.height, b.distortion_model)
        and tuple(a.K) == tuple(b.K)
        and tuple(a.D) == tuple(b.D)
    )
