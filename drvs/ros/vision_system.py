"""The vision_system node: one overhead camera of the simulated world, serving DetectObjectBoundary.

It keeps its own PyBullet copy of the world (:class:`drvs.scene.Scene`), in step
with world_sim's ``/world_sim/poses`` (static at the world file's poses while
world_sim is absent), and registers the floor area its camera sees with the DRVS
server. A request is validated and acknowledged at once; a worker then takes a
frame (rendered, or reused from the frame cache), runs the algorithm, puts the
outlines on the floor in ``map`` (:mod:`drvs.vision`) and, only if it found at
least one object, calls the robot back.

Registration: at start (retrying every ``~retry_period`` while the server is not
up), renewed every half lease, at once when the camera's field of view changes
(a camera on a moving mount: ``waypoints`` and ``speed`` in its world entry),
and removed (empty field of view) on a clean shutdown.

Parameters (private):

``~world`` (str, required)
    The world file.
``~camera`` (str, default: the node's name)
    Which ``vision_systems`` entry of the world this node is.
``~min_area`` (float, default 20)
    Smallest object, in pixels.
``~epsilon`` (float, default 1.0)
    Outline simplification tolerance, in pixels (Douglas-Peucker).
``~max_frame_age`` (float, default 0.1)
    Requests arriving within this many seconds of the last capture reuse it.
``~callback_timeout`` (float, default 2.0)
    Seconds a callback to a robot may take; a failed or hung one is logged and dropped.
``~workers`` (int, default 2)
    Threads processing requests.
``~queue_size`` (int, default 32)
    Requests waiting for a worker; beyond it requests are refused (accepted=false).
``~register_service`` (str, default ``/drvs/register_vision_service``)
    The DRVS server's RegisterVisionService.
``~register_timeout`` (float, default 2.0)
    Seconds a registration call may take.
``~lease`` (float, default: the server's ``lease`` parameter, e.g. ``/drvs/lease``, else 10)
    The server's lease; registrations are renewed every half lease.
``~retry_period`` (float, default 1.0)
    Seconds between registration attempts while the server is unreachable or refuses.
``~move_threshold`` (float, default 0.01)
    Metres a field-of-view vertex must move before the new field of view is registered.
``~poses_topic`` (str, default ``/world_sim/poses``)
    world_sim's pose topic.
``~debug_rate`` (float, default 1.0)
    Views per second rendered for ``~debug_image`` while someone subscribes (0: only
    after requests).

Topics and services:

``~detect_object_boundary`` (drvs/DetectObjectBoundary)
    e.g. ``/vs1/detect_object_boundary``.
``~stats`` (std_msgs/String JSON, latched)
    ``requests``, ``refused``, ``callbacks``, ``callback_failures``, ``callback_bytes``
    (serialized size of the callbacks sent), ``renders``, ``cache_hits``,
    ``registrations``, ``objects``, and ``requests_by_algorithm`` (accepted requests per
    algorithm string, at most ``MAX_ALGORITHMS_COUNTED`` distinct ones, the rest under
    ``other``); republished when they change.
``~debug_image`` (sensor_msgs/Image, rgb8)
    The view with the detections drawn; rendered only while subscribed.
"""

from __future__ import annotations

import io
import json
import queue
import threading
import time
import traceback
from dataclasses import dataclass

import numpy as np
import rospy
from sensor_msgs.msg import Image
from std_msgs.msg import String

from drvs.algorithms import AlgorithmError
from drvs.camera import PinholeCamera
from drvs.ros.conversions import msg_to_box, points_to_detected_object, points_to_polygon
from drvs.ros.params import read_params
from drvs.ros.service_client import ServiceCallError, ServiceClient
from drvs.scene import Frame, Scene
from drvs.simulation import mount_position
from drvs.srv import (
    CallbackCoordinates,
    CallbackCoordinatesRequest,
    DetectObjectBoundary,
    DetectObjectBoundaryResponse,
    RegisterVisionService,
    RegisterVisionServiceRequest,
)
from drvs.validation import ValidationError, request_fields
from drvs.vision import FrameCache, draw_detections, locate_objects
from drvs.world import load_world

MAX_ALGORITHMS_COUNTED = 64
"""Distinct algorithm strings counted in ``~stats``; callers choose them, so the count is capped."""


@dataclass(frozen=True)
class VisionSystemParams:
    world: str
    camera: str
    min_area: float = 20.0
    epsilon: float = 1.0
    max_frame_age: float = 0.1
    callback_timeout: float = 2.0
    workers: int = 2
    queue_size: int = 32
    register_service: str = '/drvs/register_vision_service'
    register_timeout: float = 2.0
    lease: float = 10.0
    retry_period: float = 1.0
    move_threshold: float = 0.01
    poses_topic: str = '/world_sim/poses'
    debug_rate: float = 1.0

    def __post_init__(self):
        for name in ('callback_timeout', 'register_timeout', 'lease', 'retry_period'):
            if not getattr(self, name) > 0:
                raise ValueError(f'~{name}: must be positive, got {getattr(self, name)}')
        for name in ('min_area', 'epsilon', 'max_frame_age', 'move_threshold', 'debug_rate'):
            if not getattr(self, name) >= 0:
                raise ValueError(f'~{name}: must be zero or positive, got {getattr(self, name)}')
        if self.workers < 1 or self.queue_size < 1:
            raise ValueError(
                f'~workers and ~queue_size: must be at least 1, got {self.workers}, {self.queue_size}'
            )

    @classmethod
    def from_rosparam(cls) -> VisionSystemParams:
        """Every field from ``~name``; the camera defaults to the node's name, the lease to the server's."""
        register_service = rospy.get_param('~register_service', cls.register_service)
        server = register_service.rsplit('/', 1)[0].rstrip('/')
        defaults = {
            'camera': rospy.get_name().rsplit('/', 1)[-1],
            'lease': float(rospy.get_param(server + '/lease', cls.lease)),
        }
        return read_params(cls, defaults)


@dataclass(frozen=True)
class Job:
    algorithm: object
    algorithm_text: str
    region: tuple[float, float, float, float]
    callback_service: str
    request_id: str
    arrival: float


class VisionSystemNode:
    """One camera serving DetectObjectBoundary; :meth:`start` does the work, :meth:`stop` undoes it."""

    def __init__(self, params: VisionSystemParams):
        self.params = params
        self.world = load_world(params.world)
        self.config = self.world.camera(params.camera)
        self.base_camera = PinholeCamera.from_config(self.config)
        self.scene: Scene | None = None
        self.service_name = ''
        self.stats = dict.fromkeys(
            (
                'requests',
                'refused',
                'callbacks',
                'callback_failures',
                'callback_bytes',
                'renders',
                'cache_hits',
                'registrations',
                'objects',
            ),
            0,
        )
        self._stats_lock = threading.Lock()  # guards stats and requests_by_algorithm
        self.requests_by_algorithm: dict[str, int] = {}
        self._scene_lock = threading.Lock()  # PyBullet is not thread-safe
        self._poses_lock = threading.Lock()
        self._poses: dict | None = None
        self._clients_lock = threading.Lock()
        self._callback_clients: dict[str, ServiceClient] = {}
        self._jobs: queue.Queue = queue.Queue(maxsize=params.queue_size)
        self._stopping = threading.Event()
        self._threads: list[threading.Thread] = []
        self._registered: list | None = None
        self._start_time = 0.0
        self.cache = FrameCache(self._capture, params.max_frame_age, clock=rospy.get_time)

    # -- lifecycle -----------------------------------------------------------------------------
    def start(self) -> None:
        self.scene = Scene(self.world)
        self._start_time = rospy.get_time()
        self.stats_pub = rospy.Publisher('~stats', String, queue_size=1, latch=True)
        self.debug_pub = rospy.Publisher('~debug_image', Image, queue_size=1)
        rospy.Subscriber(self.params.poses_topic, String, self._on_poses, queue_size=1)
        self._register_client = ServiceClient(
            self.params.register_service, RegisterVisionService, timeout=self.params.register_timeout
        )
        for index in range(self.params.workers):
            self._spawn(self._work, f'worker{index}')
        service = rospy.Service('~detect_object_boundary', DetectObjectBoundary, self._handle_detect)
        self.service_name = service.resolved_name
        self._spawn(self._registration_loop, 'registration')  # after the service is advertised
        if self.params.debug_rate > 0:
            self._spawn(self._debug_loop, 'debug')
        rospy.on_shutdown(self.stop)
        self._publish_stats()
        rospy.loginfo(
            '%s: camera %s at %s looking at %s, %dx%d, fov %.0f deg; serving %s',
            rospy.get_name(),
            self.config.name,
            self.base_camera.eye,
            self.base_camera.target,
            self.base_camera.width,
            self.base_camera.height,
            self.base_camera.fov_deg,
            self.service_name,
        )

    def _spawn(self, target, name: str) -> None:
        thread = threading.Thread(target=target, name=name, daemon=True)
        thread.start()
        self._threads.append(thread)

    def stop(self) -> None:
        """Stop the workers, unregister from the server, release the scene."""
        if self._stopping.is_set():
            return
        self._stopping.set()
        for _ in range(self.params.workers):
            try:
                self._jobs.put_nowait(None)
            except queue.Full:
                break
        for thread in self._threads:
            thread.join(timeout=self.params.callback_timeout + 1.0)
        if self._registered:
            self._call_register([], 'unregister')
        self._register_client.close()
        with self._clients_lock:
            for client in self._callback_clients.values():
                client.close()
            self._callback_clients.clear()
        with self._scene_lock:
            if self.scene is not None:
                self.scene.close()
                self.scene = None

    # -- camera and frames ---------------------------------------------------------------------
    def camera_at(self, stamp: float) -> PinholeCamera:
        """The camera model at time ``stamp`` (its mount may move along its waypoints)."""
        if not self.config.moving:
            return self.base_camera
        return self.base_camera.moved_to(*mount_position(self.config, stamp - self._start_time))

    def _on_poses(self, message: String) -> None:
        try:
            poses = json.loads(message.data)['poses']
        except (ValueError, KeyError, TypeError) as error:
            rospy.logwarn_throttle(10.0, '%s: unreadable poses message: %s', rospy.get_name(), error)
            return
        with self._poses_lock:
            self._poses = poses

    def _capture(self, stamp: float) -> Frame:
        with self._poses_lock:
            poses = self._poses
        with self._scene_lock:
            if self.scene is None:
                raise RuntimeError('the vision system is shutting down')
            if poses:
                self.scene.apply_poses(poses)
            frame = self.scene.render(self.camera_at(stamp), stamp)
        self._count(renders=1)
        return frame

    # -- requests ------------------------------------------------------------------------------
    def _handle_detect(self, request) -> DetectObjectBoundaryResponse:
        arrival = rospy.get_time()
        self._count(requests=1)
        try:
            algorithm, region = request_fields(
                request.algorithm, msg_to_box(request.region_of_interest), request.callback_service
            )
        except (AlgorithmError, ValidationError) as error:
            return self._refuse(request, str(error))
        self._count_algorithm(request.algorithm)
        job = Job(algorithm, request.algorithm, region, request.callback_service, request.request_id, arrival)
        try:
            self._jobs.put_nowait(job)
        except queue.Full:
            return self._refuse(
                request, f'busy: {self.params.queue_size} requests are waiting already; try again later'
            )
        rospy.logdebug(
            '%s: accepted request %r (%s)', rospy.get_name(), request.request_id, request.algorithm
        )
        return DetectObjectBoundaryResponse(accepted=True, message='', vision_systems=1)

    def _refuse(self, request, message: str) -> DetectObjectBoundaryResponse:
        self._count(refused=1)
        rospy.loginfo('%s: refused request %r: %s', rospy.get_name(), request.request_id, message)
        return DetectObjectBoundaryResponse(accepted=False, message=message, vision_systems=0)

    def _work(self) -> None:
        while not self._stopping.is_set():
            job = self._jobs.get()
            if job is None:
                return
            try:
                self._process(job)
            except Exception:  # one request that fails must not take its worker down with it
                rospy.logerr(
                    '%s: request %r failed:\n%s', rospy.get_name(), job.request_id, traceback.format_exc()
                )

    def _process(self, job: Job) -> None:
        frame, reused = self.cache.get(job.arrival)
        if reused:
            self._count(cache_hits=1)
        outlines = locate_objects(frame, job.algorithm, job.region, self.params.min_area, self.params.epsilon)
        if self.debug_pub.get_num_connections() > 0:
            self._publish_debug(frame, outlines)
        rospy.logdebug(
            '%s: request %r: %d object(s)%s',
            rospy.get_name(),
            job.request_id,
            len(outlines),
            ' (cached frame)' if reused else '',
        )
        if outlines:
            self._call_back(job, frame, outlines)

    def _call_back(self, job: Job, frame: Frame, outlines) -> None:
        request = CallbackCoordinatesRequest(
            algorithm=job.algorithm_text,
            request_id=job.request_id,
            vision_system=self.service_name,
            stamp=rospy.Time.from_sec(frame.stamp),
            objects=[points_to_detected_object(outline) for outline in outlines],
        )
        buffer = io.BytesIO()
        request.serialize(buffer)
        with self._clients_lock:
            client = self._callback_clients.get(job.callback_service)
            if client is None:
                client = ServiceClient(
                    job.callback_service, CallbackCoordinates, self.params.callback_timeout
                )
                self._callback_clients[job.callback_service] = client
        try:
            client.call(request)
        except ServiceCallError as error:
            self._count(callback_failures=1)
            rospy.logwarn('%s: callback for request %r dropped: %s', rospy.get_name(), job.request_id, error)
            return
        self._count(callbacks=1, callback_bytes=len(buffer.getvalue()), objects=len(outlines))

    # -- registration --------------------------------------------------------------------------
    def _registration_loop(self) -> None:
        renew = self.params.lease / 2.0
        last_ok = None
        retry_at = 0.0
        footprint = self.camera_at(rospy.get_time()).floor_footprint(self.world.floor_size)
        while not self._stopping.wait(0.05):
            if self.config.moving:
                footprint = self.camera_at(rospy.get_time()).floor_footprint(self.world.floor_size)
            now = time.monotonic()
            moved = self._registered is None or _moved(
                self._registered, footprint, self.params.move_threshold
            )
            due = moved or last_ok is None or now - last_ok >= renew
            if not due or now < retry_at:
                continue
            what = 'register' if self._registered is None else 'move' if moved else 'renew'
            if self._call_register(footprint, what):
                self._registered = footprint
                last_ok = now
            else:
                retry_at = now + self.params.retry_period

    def _call_register(self, footprint, what: str) -> bool:
        request = RegisterVisionServiceRequest(
            service_name=self.service_name, field_of_view=points_to_polygon(footprint)
        )
        try:
            response = self._register_client.call(request)
        except ServiceCallError as error:
            rospy.logwarn_throttle(10.0, '%s: waiting for the DRVS server (%s)', rospy.get_name(), error)
            return False
        if not response.accepted:
            rospy.logwarn('%s: %s refused: %s', rospy.get_name(), what, response.message)
            return False
        if what != 'renew':
            rospy.loginfo(
                '%s: %s %s with field of view %s',
                rospy.get_name(),
                what,
                self.service_name,
                [(round(x, 3), round(y, 3)) for x, y in footprint],
            )
        self._count(registrations=1)
        return True

    # -- introspection -------------------------------------------------------------------------
    def _count(self, **increments) -> None:
        with self._stats_lock:
            for key, value in increments.items():
                self.stats[key] += value
        self._publish_stats()

    def _count_algorithm(self, algorithm: str) -> None:
        with self._stats_lock:
            counts = self.requests_by_algorithm
            key = algorithm if algorithm in counts or len(counts) < MAX_ALGORITHMS_COUNTED else 'other'
            counts[key] = counts.get(key, 0) + 1

    def _publish_stats(self) -> None:
        with self._stats_lock:
            text = json.dumps(
                {**self.stats, 'requests_by_algorithm': self.requests_by_algorithm}, sort_keys=True
            )
        self.stats_pub.publish(String(text))

    def _debug_loop(self) -> None:
        period = 1.0 / self.params.debug_rate
        while not self._stopping.wait(period):
            if self.debug_pub.get_num_connections() > 0:
                try:
                    frame, _ = self.cache.get(rospy.get_time())
                except RuntimeError:
                    return
                self._publish_debug(frame, [])

    def _publish_debug(self, frame: Frame, outlines) -> None:
        image = draw_detections(frame, outlines)
        height, width = image.shape[:2]
        message = Image(height=height, width=width, encoding='rgb8', is_bigendian=0, step=width * 3)
        message.header.stamp = rospy.Time.from_sec(frame.stamp)
        message.header.frame_id = self.config.name
        message.data = np.ascontiguousarray(image).tobytes()
        self.debug_pub.publish(message)


def _moved(old, new, threshold: float) -> bool:
    """Whether a field of view changed by more than ``threshold`` metres at any vertex."""
    if len(old) != len(new):
        return True
    if not new:
        return False
    return float(np.max(np.abs(np.asarray(old) - np.asarray(new)))) > threshold
