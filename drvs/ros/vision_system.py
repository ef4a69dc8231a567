"""The vision_system node: one camera serving DetectObjectBoundary.

Its frames come from one of two sources (:mod:`drvs.ros.frame_sources`):

- ``~source:=topic``: any ROS camera. It subscribes to ``image``
  (sensor_msgs/Image; rgb8, bgr8, mono8, bayer_* or anything else cv_bridge
  converts to rgb8) or, with ``~compressed``, ``image/compressed``
  (sensor_msgs/CompressedImage), and ``camera_info`` (sensor_msgs/CameraInfo);
  the camera's pose is the tf transform ``map`` <- the image's
  ``header.frame_id`` (its optical frame, REP-103: z forward, x right, y down) at
  the image's stamp. No world file needed::

      nodes/vision_system __name:=cam1 _source:=topic image:=/cam1/image_raw camera_info:=/cam1/camera_info

  Outlines are undistorted, lifted to rays and met with the floor plane z = 0
  (the ground-plane assumption: a tall object is reported where its outline
  falls on the floor seen from the camera, i.e. stretched away from it), or,
  with ``~depth``, lifted with the aligned depth image ``depth`` (32FC1 metres
  or 16UC1 millimetres, same stamp as the colour image) so a tall object is
  reported where it stands.
- ``~source:=render`` (the default when ``~world`` is given): the simulation
  shortcut. It keeps its own PyBullet copy of the world, in step with
  world_sim's ``/world_sim/poses`` (static at the world file's poses while
  world_sim is absent), and renders its view on demand.

A request is validated and acknowledged at once; a worker then takes a frame,
runs the algorithm, puts the outlines on the floor in ``map``
(:mod:`drvs.vision.pipeline`) and, only if it found at least one object, calls the
robot back with the frame's stamp (the moment it shows). Requests that share a
frame and an algorithm string run the algorithm once (:class:`FrameDetections`).

Watches (standing requests, ``~watch_object_boundary``): the same question asked
once for every ``period`` seconds during ``duration`` seconds, named by
(``callback_service``, ``request_id``); the same key again renews it (the region
may change), ``duration`` 0 cancels it. The period granted is at least
``~min_watch_period``, the duration at most ``~max_watch_duration``. One guarded
thread sleeps until a watch is due (ROS time), takes one frame for every watch due
then and none while nobody watches, runs each watch's algorithm on its region and
calls back as for a request: every period when something was found, or with
``changes_only`` only when the outlines moved beyond ``~change_tolerance``, plus
one callback with no objects when what it had reported is gone. The bookkeeping
and the rules are :mod:`drvs.vision.watch_runner`'s.

Frames from a topic: a request uses the newest frame if it is younger than
``~max_frame_age``, otherwise it waits for the next one up to
``~frame_timeout``. A feed without frames for ``~stale_after`` seconds
unregisters (robots are never routed to a dead camera), refuses requests with
``UNAVAILABLE``, and registers again when frames return.

Registration: the names of the algorithms it runs (the built-ins and every
plugin installed: :func:`drvs.algorithms.load_algorithms`; the server routes to it
only requests for those) and the floor area the camera sees (for a topic: the image's footprint
on the floor from CameraInfo and tf, distortion-aware, up to ``~max_range``), at
start (for a topic: once CameraInfo, tf and frames are known), renewed at half
the lease the server grants (its response's ``lease``), at once when the field
of view changes by more than ``~move_threshold`` (a camera on a moving mount:
``waypoints`` and ``speed`` in its world entry, or a moving tf frame), and
removed (empty field of view) on a clean shutdown. While the server is unreachable or
refuses with a temporary status (``BUSY``, ``RATE_LIMITED``, ``UNAVAILABLE``, e.g.
ejected after failed forwards) it retries after the response's ``retry_after``,
with jitter and growing backoff (:func:`drvs.common.retry.retry_delay`, at most
``~retry_period`` beyond ``retry_after``); after ``INVALID`` it logs the reason as
an error and retries every ``~retry_period``.

Background loops (registration, workers, watches, debug view) are guarded
(:class:`drvs.common.guard.LoopGuard`): an unexpected exception is logged with its
traceback and the loop restarts; one that keeps failing shuts the node down
(exit code 1).

Parameters: the fields of :class:`VisionSystemParams`, each declared with its default,
meaning and range; README.md's vision_system table is generated from them.

Topics and services:

``~detect_object_boundary`` (drvs/DetectObjectBoundary)
    e.g. ``/vs1/detect_object_boundary``.
``~watch_object_boundary`` (drvs/WatchObjectBoundary)
    Its sibling, e.g. ``/vs1/watch_object_boundary``: ``INVALID`` naming the field,
    ``UNAVAILABLE`` while the feed is stale, ``BUSY`` beyond ``~max_watches``; accepted
    with ``vision_systems`` 1 and the granted ``period`` and ``duration`` (a cancel: 0, 0, 0).
``~stats`` (drvs/VisionSystemStats, latched; at most every 0.5 s while the counts change)
    ``requests``, ``refused``, ``callbacks``, ``callback_failures``, ``callback_bytes``
    (serialized size of the callbacks sent), ``renders`` (frames rendered or decoded),
    ``no_frame`` (accepted requests dropped because no frame came), ``cache_hits``,
    ``registrations``, ``objects``, ``watch_calls`` (accepted watch calls: new, renewed,
    cancelled), ``watches`` (standing now), ``watch_evaluations`` (one watch on one frame),
    and accepted requests per algorithm string
    (``algorithms`` and ``algorithm_requests``, at most ``MAX_ALGORITHMS_COUNTED``
    distinct ones, the rest under ``other``); republished when they change.
``~debug_image`` (sensor_msgs/Image, rgb8)
    The view with the detections drawn; rendered only while subscribed.
``/drvs/markers`` (visualization_msgs/MarkerArray, frame ``map``)
    With every callback sent, its outlines for RViz (:func:`drvs.ros.markers.detection_markers`:
    namespace ``detections/<service>/<algorithm>``, coloured by algorithm NAME, fading after
    ``DETECTION_LIFETIME`` seconds); published only while someone subscribes. The topic is
    the server's, next to ``~register_service``, where it publishes the fields of view.
``/diagnostics`` (diagnostic_msgs/DiagnosticArray, 1 Hz)
    Status ``drvs: <node name>``, hardware_id the camera's name
    (:func:`drvs.common.health.vision_system_health`): ERROR for a stale topic feed (or no frame
    yet) and for a registration refused ``INVALID``; WARN when not registered (why: the
    server's refusal or the failed call), the request queue nearly full, or callbacks
    failed in the last second; OK otherwise. Values: registered, source, frame age,
    ``~stale_after``, queue length and size, watches, callbacks and failures in the last period,
    the last registration refusal and error.
``/tf_static`` or ``/tf`` (``render`` only): ``map`` -> ``<camera>_optical_frame``
    The camera's optical frame (z forward, x right, y down), as sim_camera publishes it:
    on ``/tf_static`` for a fixed camera, on ``/tf`` at ``POSE_RATE`` Hz for one on a
    moving mount. (With ``topic``, the camera's driver puts it on tf.)
"""

from __future__ import annotations

import functools
import io
import logging
import math
import queue
import threading
import time
import traceback
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import rospy
from sensor_msgs.msg import Image
from visualization_msgs.msg import MarkerArray

from drvs.algorithms import AlgorithmError, load_algorithms
from drvs.common.client_cache import ClosingCache
from drvs.common.counters import PeriodCounts
from drvs.common.guard import RESTART, LoopGuard
from drvs.common.health import Health, vision_system_health
from drvs.common.retry import retry_delay
from drvs.common.settings import (
    NON_NEGATIVE,
    POSITIVE,
    REQUIRED,
    ParamError,
    Settings,
    at_least,
    one_of,
    param,
)
from drvs.common.status import ACCEPTED, BUSY, INVALID, UNAVAILABLE, Refusal, is_temporary
from drvs.common.status import name as status_name
from drvs.common.validation import ValidationError, request_fields
from drvs.msg import VisionSystemStats
from drvs.ros.conversions import (
    msg_to_box,
    points_to_detected_object,
    points_to_polygon,
    refusal_to_detect_response,
)
from drvs.ros.diagnostics import DiagnosticsPublisher
from drvs.ros.frame_sources import FrameUnavailable, RenderSource, TopicSource
from drvs.ros.markers import detection_markers, markers_topic
from drvs.ros.messages import STATS_COUNTERS, stats_to_msg
from drvs.ros.service_client import ServiceCallError, ServiceClient
from drvs.sim.world_file import load_world
from drvs.srv import (
    CallbackCoordinates,
    CallbackCoordinatesRequest,
    DetectObjectBoundary,
    DetectObjectBoundaryResponse,
    RegisterVisionService,
    RegisterVisionServiceRequest,
    WatchObjectBoundary,
    WatchObjectBoundaryResponse,
)
from drvs.vision.frame import Frame
from drvs.vision.pipeline import draw_detections, in_region, on_floor
from drvs.vision.watch_runner import Terms, WatchRunner, parse_watch

DEFAULT_LEASE = 10.0
"""Seconds assumed when a server grants no lease (0): renew every 5 s."""

MAX_ALGORITHMS_COUNTED = 64
"""Distinct algorithm strings counted in ``~stats``; callers choose them, so the count is capped."""

POSE_RATE = 10.0
"""Times per second a camera on a moving mount (``render``) puts its pose on tf."""

STATS_PERIOD = 0.5
"""Least wall-clock seconds between two ``~stats`` messages: a busy camera counts hundreds of
events a second, and every subscriber (the scenario recorder) would receive each one."""
WATCH_POLL = 0.05
"""Longest wall-clock sleep of the watch loop: it looks again at the time of the next due watch
(ROS time, which may run slower or faster than the wall under ``/use_sim_time``) and for new watches."""


MAX_DETECTIONS_KEPT = 16
"""Algorithm strings whose objects are kept for the newest frame; callers choose them, so capped."""


SOURCES = ('render', 'topic')

ACCEPTED_REPLY = DetectObjectBoundaryResponse(accepted=True, status=ACCEPTED, message='', vision_systems=1)
"""The answer to every accepted request (rospy only serialises it: one is shared)."""


@dataclass(frozen=True)
class VisionSystemParams(Settings):
    camera: str = param(
        REQUIRED,
        'which `vision_systems` entry of the world this node is (`render`)',
        default_text="the node's name",
    )
    world: str = param('', 'the world file (required with `~source` `render`)', default_text='none')
    source: str = param(
        '',
        'where frames come from: rendered from the world, or a camera topic',
        check=one_of(*SOURCES),
        default_text='`render` with `~world`, else `topic`',
    )
    compressed: bool = param(False, '`topic`: subscribe to `image/compressed` instead of `image`')
    depth: bool = param(False, '`topic`: lift outlines with the aligned depth image `depth`')
    max_range: float = param(
        30.0,
        '`topic`: distance from the camera beyond which the floor is not part of the field of view',
        unit='m',
        check=POSITIVE,
    )
    frame_timeout: float = param(
        1.0,
        '`topic`: how long a request waits for a new frame when the newest is too old',
        unit='s',
        check=POSITIVE,
    )
    stale_after: float = param(
        3.0, '`topic`: time without frames after which the camera unregisters', unit='s', check=POSITIVE
    )
    tf_timeout: float = param(
        0.5,
        "`topic`: how long to wait for the camera's transform at an image's stamp",
        unit='s',
        check=POSITIVE,
    )
    map_frame: str = param('map', '`topic`: the frame outlines and fields of view are given in')
    tag_height: float = param(
        0.0,
        'height above the floor of the plane AprilTags lie on, unless the request (`h=H`) or the world says',
        unit='m',
        check=NON_NEGATIVE,
    )
    motion_rate: float = param(
        5.0,
        'frames fed to algorithms with memory (`motion`) while they are in use',
        unit='Hz',
        check=POSITIVE,
    )
    motion_window: float = param(
        5.0,
        'time after the last `motion` request during which frames keep being fed',
        unit='s',
        check=POSITIVE,
    )
    min_area: float = param(20.0, 'smallest object', unit='px', check=NON_NEGATIVE)
    epsilon: float = param(
        1.0, 'outline simplification tolerance (Douglas-Peucker)', unit='px', check=NON_NEGATIVE
    )
    max_frame_age: float = param(
        0.1,
        'a request reuses the newest frame if it is at most this old',
        unit='s',
        check=NON_NEGATIVE,
    )
    callback_timeout: float = param(
        2.0,
        'limit on one callback to a robot; a failed or hung one is logged and dropped',
        unit='s',
        check=POSITIVE,
    )
    max_callback_clients: int = param(
        64,
        "connections to robots' callback services kept, the least recently used closed beyond it",
        check=at_least(1),
    )
    callback_idle: float = param(
        30.0, 'an unused connection to a callback service is closed after this', unit='s', check=POSITIVE
    )
    workers: int = param(2, 'threads processing requests', check=at_least(1))
    queue_size: int = param(
        32, 'requests waiting for a worker; beyond it requests are refused `BUSY`', check=at_least(1)
    )
    min_watch_period: float = param(
        0.1,
        'shortest period granted to a watch; a shorter one asked for is lengthened',
        unit='s',
        check=POSITIVE,
    )
    max_watch_duration: float = param(
        60.0, 'longest duration granted to a watch: it expires then unless renewed', unit='s', check=POSITIVE
    )
    max_watches: int = param(
        256, 'watches standing at once; beyond it new watches are refused `BUSY`', check=at_least(1)
    )
    change_tolerance: float = param(
        0.03,
        '`changes_only` watches: how far an outline moves before it is reported again',
        unit='m',
        check=NON_NEGATIVE,
    )
    register_service: str = param('/drvs/register_vision_service', "the DRVS server's RegisterVisionService")
    register_timeout: float = param(2.0, 'limit on one registration call', unit='s', check=POSITIVE)
    retry_period: float = param(
        1.0,
        "longest wait between registration attempts beyond the server's `retry_after`",
        unit='s',
        check=POSITIVE,
    )
    move_threshold: float = param(
        0.01,
        'how far a field-of-view vertex moves before the new field of view is registered',
        unit='m',
        check=NON_NEGATIVE,
    )
    poses_topic: str = param('/world_sim/poses', "world_sim's pose topic (`render`)")
    debug_rate: float = param(
        1.0,
        '`~debug_image` views per second while subscribed (0: only after requests)',
        unit='Hz',
        check=NON_NEGATIVE,
    )

    def __post_init__(self):
        if not self.source:  # frozen: the resolved default is set once, here
            object.__setattr__(self, 'source', 'render' if self.world else 'topic')
        super().__post_init__()
        if self.source == 'render' and not self.world:
            raise ParamError(
                'world', 'required with ~source render (or use ~source topic and a camera topic)'
            )


@dataclass(frozen=True)
class Job:
    """A one-shot request, queued for a worker. Like a watch's :class:`drvs.vision.watch_runner.Terms`, it
    names the algorithm (parsed), the callback service and the request id a callback carries."""

    algorithm: object
    region: tuple[float, float, float, float]
    callback_service: str
    request_id: str
    arrival: float


class FrameDetections:
    """The objects found on the newest frame, per algorithm string (:func:`drvs.vision.pipeline.on_floor`).

    Requests that share a frame (``~max_frame_age``, :class:`drvs.vision.pipeline.FrameCache`) and
    ask with the same algorithm detect once, as the watches due at one time do; each
    request then only clips them to its region (:func:`drvs.vision.pipeline.in_region`). Not for
    algorithms with memory (``streaming``): what they find depends on what they have seen.
    Thread-safe: ``FrameDetections._lock`` guards the frame and its objects; detection
    runs outside it (two workers may detect at once; the newer frame's objects are kept).
    """

    def __init__(self, limit: int = MAX_DETECTIONS_KEPT):
        self.limit = limit
        self._lock = threading.Lock()
        self._frame: Frame | None = None
        self._objects: dict[str, list] = {}  # algorithm text -> on_floor(self._frame, algorithm)

    def on_floor(self, frame: Frame, algorithm) -> list:
        """:func:`drvs.vision.pipeline.on_floor` of ``frame`` and ``algorithm`` (a parsed algorithm)."""
        if algorithm.algorithm.streaming:
            return on_floor(frame, algorithm)
        with self._lock:
            objects = self._objects.get(algorithm.text) if frame is self._frame else None
        if objects is not None:
            return objects
        objects = on_floor(frame, algorithm)
        with self._lock:
            if self._frame is None or (frame is not self._frame and frame.stamp >= self._frame.stamp):
                self._frame, self._objects = frame, {}
            if frame is self._frame and len(self._objects) < self.limit:
                self._objects[algorithm.text] = objects
        return objects


class VisionSystemNode:
    """One camera serving DetectObjectBoundary; :meth:`start` does the work, :meth:`stop` undoes it."""

    def __init__(self, params: VisionSystemParams):
        self.params = params
        tag_heights = {}
        if params.source == 'render':
            world = load_world(params.world)
            self.source = RenderSource(world, world.camera(params.camera), params, self._count)
            tag_heights = world.tag_heights()
        else:
            self.source = TopicSource(params, self._count)
        self.algorithms = load_algorithms(params.min_area, params.epsilon, params.tag_height, tag_heights)
        # Requests: the algorithm strings that parsed lately, parsed again only when new (as parse()).
        self._parsed_algorithms = SimpleNamespace(
            parse=functools.lru_cache(maxsize=MAX_ALGORITHMS_COUNTED)(self.algorithms.parse)
        )
        self._streaming_until = -1.0  # motion: observe the stream until then (rospy time)
        self.service_name = ''
        self.stats = dict.fromkeys(STATS_COUNTERS, 0)
        self._stats_changed = True  # since the last ~stats message
        self._stats_published = -math.inf  # time.monotonic() of the last ~stats message
        self._stats_lock = threading.Lock()  # guards stats and requests_by_algorithm
        self.requests_by_algorithm: dict[str, int] = {}
        self._callback_clients = ClosingCache(
            lambda service: ServiceClient(service, CallbackCoordinates, params.callback_timeout),
            maxsize=params.max_callback_clients,
            ttl=params.callback_idle,
        )
        self._jobs: queue.Queue = queue.Queue(maxsize=params.queue_size)
        self._detections = FrameDetections()
        self.watches = WatchRunner(
            params.min_watch_period, params.max_watch_duration, params.change_tolerance, params.max_watches
        )
        self._stopping = threading.Event()
        self.guard = LoopGuard(on_fatal=lambda reason: rospy.signal_shutdown(reason), stop=self._stopping)
        self._registered: list | None = None
        self.lease: float | None = None  # granted by the server at the last registration
        self._callbacks_period = PeriodCounts()  # 'attempted' and 'failed' callbacks, for the health
        self._registration_lock = threading.Lock()  # guards the three fields below
        self._registered_until: float | None = None  # time.monotonic() when the granted lease ends
        self._registration_status = ''  # status name of the last refused registration
        self._registration_error = ''  # why the last registration failed, or why there is none
        self.diagnostics = DiagnosticsPublisher(
            f'drvs: {rospy.get_name()}', params.camera, self.health, guard=self.guard
        )

    # -- lifecycle -----------------------------------------------------------------------------
    def start(self) -> None:
        self.stats_pub = rospy.Publisher('~stats', VisionSystemStats, queue_size=1, latch=True)
        self.debug_pub = rospy.Publisher('~debug_image', Image, queue_size=1)
        self.markers_pub = rospy.Publisher(
            markers_topic(rospy.resolve_name(self.params.register_service)), MarkerArray, queue_size=10
        )
        self.source.start()
        self._register_client = ServiceClient(
            self.params.register_service, RegisterVisionService, timeout=self.params.register_timeout
        )
        for index in range(self.params.workers):
            self.guard.spawn(self._work, f'worker{index}', RESTART)
        service = rospy.Service('~detect_object_boundary', DetectObjectBoundary, self._handle_detect)
        self.service_name = service.resolved_name
        self.guard.spawn(self._watch_loop, 'watches', RESTART)
        rospy.Service('~watch_object_boundary', WatchObjectBoundary, self._handle_watch)
        self.guard.spawn(self._registration_loop, 'registration', RESTART)  # after the service is advertised
        if self.params.debug_rate > 0:
            self.guard.spawn(self._debug_loop, 'debug', RESTART)
        if any(a.streaming for a in self.algorithms.by_name.values()):
            self.guard.spawn(self._stream_loop, 'stream', RESTART)
        if isinstance(self.source, RenderSource) and self.source.moving:
            self.guard.spawn(self._pose_loop, 'camera pose', RESTART)
        rospy.on_shutdown(self.stop)
        self._publish_stats()
        self.diagnostics.start()
        rospy.loginfo('%s: %s; serving %s', rospy.get_name(), self.source.describe(), self.service_name)

    def stop(self) -> None:
        """Stop the workers, unregister from the server, release the frame source."""
        if self._stopping.is_set():
            return
        self._stopping.set()
        self.diagnostics.stop()
        for _ in range(self.params.workers):
            try:
                self._jobs.put_nowait(None)
            except queue.Full:
                break
        for thread in self.guard.threads:
            thread.join(timeout=self.params.callback_timeout + 1.0)
        if self._registered:
            self._call_register([], 'unregister')
        try:
            self._publish_stats()  # the final counts
        except rospy.ROSException as error:  # publishing after shutdown
            rospy.logdebug('could not publish the final stats: %s', error)
        self._register_client.close()
        self._callback_clients.clear()
        self.source.close()

    # -- requests ------------------------------------------------------------------------------
    def _handle_detect(self, request) -> DetectObjectBoundaryResponse:
        arrival = rospy.get_time()
        self._count(requests=1)
        try:
            algorithm, region = request_fields(
                request.algorithm,
                msg_to_box(request.region_of_interest),
                request.callback_service,
                self._parsed_algorithms,
            )
        except (AlgorithmError, ValidationError) as error:
            return self._refuse(request, Refusal(INVALID, str(error)))
        problem = self.source.unavailable()
        if problem:
            return self._refuse(request, Refusal(UNAVAILABLE, problem, self.params.retry_period))
        self._count_algorithm(request.algorithm)
        if algorithm.algorithm.streaming:
            self._streaming_until = arrival + self.params.motion_window
        job = Job(algorithm, region, request.callback_service, request.request_id, arrival)
        try:
            self._jobs.put_nowait(job)
        except queue.Full:
            refusal = Refusal(
                BUSY,
                f'busy: {self.params.queue_size} requests are waiting already; try again later',
                self.params.max_frame_age or 0.1,
            )
            return self._refuse(request, refusal)
        if _debug_logged():
            rospy.logdebug(
                '%s: accepted request %r (%s)', rospy.get_name(), request.request_id, request.algorithm
            )
        return ACCEPTED_REPLY

    def _refuse(self, request, refusal: Refusal) -> DetectObjectBoundaryResponse:
        self._count(refused=1)
        rospy.loginfo(
            '%s: refused request %r (%s): %s',
            rospy.get_name(),
            request.request_id,
            status_name(refusal.status),
            refusal.message,
        )
        return refusal_to_detect_response(refusal)

    def _handle_watch(self, request) -> WatchObjectBoundaryResponse:
        now = rospy.get_time()
        try:
            terms = parse_watch(
                request.algorithm,
                msg_to_box(request.region_of_interest),
                request.callback_service,
                request.request_id,
                request.period,
                request.duration,
                request.changes_only,
                self.algorithms,
            )
            if terms is None:
                cancelled = self.watches.cancel((request.callback_service, request.request_id))
                self._count(watch_calls=1)
                self._note_watches()
                if cancelled:
                    rospy.loginfo('%s: watch %r cancelled', rospy.get_name(), request.request_id)
                return WatchObjectBoundaryResponse(accepted=True, status=ACCEPTED)
            problem = self.source.unavailable()
            if problem:
                raise Refusal(UNAVAILABLE, problem, self.params.retry_period)
            grant = self.watches.stand(terms, float(request.duration), now)
        except (AlgorithmError, ValidationError) as error:
            return self._refuse_watch(request, Refusal(INVALID, str(error)))
        except Refusal as refusal:
            return self._refuse_watch(request, refusal)
        self._count(watch_calls=1)
        self._note_watches()
        if grant.new:
            self._count_algorithm(request.algorithm)
            rospy.loginfo(
                '%s: watch %r (%s) every %g s for %g s%s',
                rospy.get_name(),
                request.request_id,
                request.algorithm,
                grant.period,
                grant.duration,
                ', changes only' if terms.changes_only else '',
            )
        return WatchObjectBoundaryResponse(
            accepted=True, status=ACCEPTED, vision_systems=1, period=grant.period, duration=grant.duration
        )

    def _refuse_watch(self, request, refusal: Refusal) -> WatchObjectBoundaryResponse:
        rospy.loginfo(
            '%s: refused watch %r (%s): %s',
            rospy.get_name(),
            request.request_id,
            status_name(refusal.status),
            refusal.message,
        )
        return WatchObjectBoundaryResponse(
            accepted=False, status=refusal.status, message=refusal.message, retry_after=refusal.retry_after
        )

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
        try:
            frame, reused = self.source.frame(job.arrival)
        except FrameUnavailable as error:
            self._count(no_frame=1)
            rospy.logwarn_throttle(5.0, '%s: request %r dropped: %s', rospy.get_name(), job.request_id, error)
            return
        if job.algorithm.algorithm.streaming:
            job.algorithm.algorithm.observe(frame)  # the model must have seen the frame it judges
        found = in_region(self._detections.on_floor(frame, job.algorithm), job.region)
        outlines = [outline for outline, _ in found]
        if self.debug_pub.get_num_connections() > 0:
            self._publish_debug(frame, outlines)
        if _debug_logged():
            rospy.logdebug(
                '%s: request %r: %d object(s)%s',
                rospy.get_name(),
                job.request_id,
                len(outlines),
                ' (cached frame)' if reused else '',
            )
        if found:
            self._call_back(job, frame.stamp, found)

    def _stream_loop(self) -> None:
        """While motion requests come (``~motion_window``), feed the algorithms with memory the
        camera's frames at ``~motion_rate``, so their background model follows the scene."""
        period = 1.0 / self.params.motion_rate
        streaming = [a for a in self.algorithms.by_name.values() if a.streaming]
        while not self._stopping.wait(period):
            if rospy.get_time() > self._streaming_until:
                continue
            try:
                frame, _ = self.source.frame(rospy.get_time())
            except FrameUnavailable:
                continue
            for algorithm in streaming:
                algorithm.observe(frame)

    def _watch_loop(self) -> None:
        """Sleep until a watch is due, then evaluate every due watch on one frame."""
        while not self._stopping.wait(self._until_next_watch()):
            now = rospy.get_time()
            due = self.watches.due(now)
            self._note_watches()  # due() drops the expired ones
            if due:
                self._evaluate_watches(due, now)

    def _until_next_watch(self) -> float:
        """Wall seconds to sleep: until the next watch is due (read as ROS seconds), at most WATCH_POLL."""
        next_due = self.watches.next_due()
        if next_due is None:
            return WATCH_POLL
        return min(max(next_due - rospy.get_time(), 0.0), WATCH_POLL)

    def _evaluate_watches(self, due: list[Terms], now: float) -> None:
        try:
            frame, _ = self.source.frame(now)
        except FrameUnavailable as error:
            self._count(no_frame=1)
            rospy.logwarn_throttle(5.0, '%s: %d watch(es) skipped: %s', rospy.get_name(), len(due), error)
            return
        streaming = {terms.algorithm.algorithm for terms in due if terms.algorithm.algorithm.streaming}
        if streaming:  # as for a request: the model sees the frame it judges, and the stream goes on
            self._streaming_until = max(self._streaming_until, now + self.params.motion_window)
        for algorithm in streaming:
            algorithm.observe(frame)
        detected: dict[str, list] = {}  # algorithm text -> its objects on this frame: detect once
        for terms in due:
            try:
                if terms.algorithm.text not in detected:
                    detected[terms.algorithm.text] = on_floor(frame, terms.algorithm)
                found = in_region(detected[terms.algorithm.text], terms.region)
            except Exception:  # one watch that fails must not stop the others
                rospy.logerr(
                    '%s: watch %r failed:\n%s', rospy.get_name(), terms.request_id, traceback.format_exc()
                )
                continue
            self._count(watch_evaluations=1)
            objects = self.watches.evaluate(terms, found)
            if objects is not None and not self._call_back(terms, frame.stamp, objects):
                self.watches.callback_failed(terms)

    def _call_back(self, asked: Job | Terms, stamp: float, found) -> bool:
        """Send ``found`` ((outline, label) pairs; [] for a watch's "all gone") seen in a frame of
        ``stamp`` to the caller of a request or a watch; whether the call arrived."""
        request = CallbackCoordinatesRequest(
            algorithm=asked.algorithm.text,
            request_id=asked.request_id,
            vision_system=self.service_name,
            stamp=rospy.Time.from_sec(stamp),
            objects=[points_to_detected_object(outline, label) for outline, label in found],
        )
        buffer = io.BytesIO()
        request.serialize(buffer)  # once: counted, then sent as it is
        client = self._callback_clients.get(asked.callback_service)
        self._callbacks_period.add('attempted')
        try:
            client.call(request, serialized=buffer.getvalue())
        except ServiceCallError as error:
            self._count(callback_failures=1)
            self._callbacks_period.add('failed')
            rospy.logwarn(
                '%s: callback for request %r dropped: %s', rospy.get_name(), asked.request_id, error
            )
            arrived = False
        else:
            self._count(callbacks=1, callback_bytes=len(buffer.getvalue()), objects=len(found))
            arrived = True
        if self.markers_pub.get_num_connections() > 0:  # after the callback: the robot waits, RViz can
            outlines = [outline for outline, _ in found]
            self.markers_pub.publish(
                detection_markers(self.service_name, asked.algorithm.text, outlines, request.stamp)
            )
        return arrived

    # -- registration --------------------------------------------------------------------------
    def _registration_loop(self) -> None:
        last_ok = None
        retry_at = 0.0
        attempt = 0
        while not self._stopping.wait(0.05):
            self._callback_clients.expire()  # close idle callback connections even when no request comes
            self._publish_stats(at_most_every=STATS_PERIOD)  # counts that came too soon after the last
            footprint = self.source.footprint()
            if footprint is None or (not footprint and not self._registered):
                if not self._registered:
                    self._note_lease(None, _why_not_registering(footprint))
                continue  # not known yet, or nothing to unregister
            now = time.monotonic()
            moved = self._registered is None or _moved(
                self._registered, footprint, self.params.move_threshold
            )
            renew = bool(footprint) and (
                last_ok is None or now - last_ok >= (self.lease or DEFAULT_LEASE) / 2.0
            )
            if not (moved or renew) or now < retry_at:
                continue
            if not footprint:
                what = 'unregister'  # the camera feed went stale
            elif not self._registered:
                what = 'register'
            else:
                what = 'move' if moved else 'renew'
            wait = self._call_register(footprint, what)
            if wait is None:
                self._registered = footprint
                last_ok = now
                attempt = 0
            else:
                retry_at = now + retry_delay(wait, attempt, cap=self.params.retry_period)
                attempt += 1

    def _call_register(self, footprint, what: str) -> float | None:
        """Register ``footprint`` (empty: unregister); None on success, else the server's retry_after."""
        request = RegisterVisionServiceRequest(
            service_name=self.service_name,
            field_of_view=points_to_polygon(footprint),
            algorithms=self.algorithms.names(),
        )
        try:
            response = self._register_client.call(request)
        except ServiceCallError as error:
            rospy.logwarn_throttle(10.0, '%s: waiting for the DRVS server (%s)', rospy.get_name(), error)
            self._note_refusal('', str(error))
            return 0.0
        if response.status != ACCEPTED:
            self._note_refusal(status_name(response.status), response.message)
            if is_temporary(response.status):
                rospy.logwarn_throttle(
                    10.0,
                    '%s: %s refused for now (%s, retry after %.1f s): %s',
                    rospy.get_name(),
                    what,
                    status_name(response.status),
                    response.retry_after,
                    response.message,
                )
                return max(float(response.retry_after), 0.0)
            rospy.logerr('%s: %s refused: %s', rospy.get_name(), what, response.message)
            return self.params.retry_period
        if response.lease > 0:
            self.lease = float(response.lease)
        if what == 'unregister':
            self._note_lease(None, _why_not_registering(footprint))
            rospy.loginfo('%s: unregistered %s', rospy.get_name(), self.service_name)
        else:
            self._note_lease(time.monotonic() + (self.lease or DEFAULT_LEASE))
            if what != 'renew':
                rospy.loginfo(
                    '%s: %s %s with field of view %s (lease %s s)',
                    rospy.get_name(),
                    what,
                    self.service_name,
                    [(round(x, 3), round(y, 3)) for x, y in footprint],
                    f'{self.lease:g}' if self.lease else '-',
                )
        self._count(registrations=1)
        return None

    def _note_lease(self, until: float | None, why_not: str = '') -> None:
        """For the health report: a lease held until ``until`` (time.monotonic()), or none because
        ``why_not``."""
        with self._registration_lock:
            self._registered_until = until
            self._registration_status, self._registration_error = '', why_not

    def _note_refusal(self, status: str, error: str) -> None:
        """For the health report: a registration refused with ``status`` ('' if the server did not
        answer) because ``error``; a lease granted before runs its course."""
        with self._registration_lock:
            self._registration_status, self._registration_error = status, error

    # -- introspection -------------------------------------------------------------------------
    def health(self) -> Health:
        """The node's health now, for ``/diagnostics``; the callbacks counted since the last call."""
        callbacks = self._callbacks_period.take_period()
        with self._registration_lock:
            until = self._registered_until
            status, error = self._registration_status, self._registration_error
        return vision_system_health(
            registered=until is not None and time.monotonic() < until,
            source=self.params.source,
            frame_age=self.source.frame_age(),
            stale_after=self.params.stale_after,
            queue_length=self._jobs.qsize(),
            queue_size=self.params.queue_size,
            watches=len(self.watches),
            callback_failures_recent=callbacks.get('failed', 0),
            callbacks_recent=callbacks.get('attempted', 0),
            registration_status=status,
            registration_error=error,
        )

    def _count(self, **increments) -> None:
        with self._stats_lock:
            for key, value in increments.items():
                self.stats[key] += value
            self._stats_changed = True
        self._publish_stats(at_most_every=STATS_PERIOD)

    def _note_watches(self) -> None:
        """``watches`` in ``~stats``: the watches standing now (published when it changes)."""
        standing = len(self.watches)
        with self._stats_lock:
            changed = self.stats['watches'] != standing
            self.stats['watches'] = standing
            self._stats_changed |= changed
        if changed:
            self._publish_stats(at_most_every=STATS_PERIOD)

    def _count_algorithm(self, algorithm: str) -> None:
        with self._stats_lock:
            counts = self.requests_by_algorithm
            key = algorithm if algorithm in counts or len(counts) < MAX_ALGORITHMS_COUNTED else 'other'
            counts[key] = counts.get(key, 0) + 1
            self._stats_changed = True

    def _publish_stats(self, at_most_every: float = 0.0) -> None:
        """Publish ``~stats`` if they changed, unless the last message is younger than
        ``at_most_every`` wall seconds (the registration loop publishes what is left)."""
        with self._stats_lock:
            now = time.monotonic()
            if not self._stats_changed or now - self._stats_published < at_most_every:
                return
            self._stats_changed, self._stats_published = False, now
            message = stats_to_msg(self.stats, self.requests_by_algorithm, rospy.get_time())
        self.stats_pub.publish(message)

    def _pose_loop(self) -> None:
        """A camera on a moving mount: its pose on tf, ``POSE_RATE`` times a second."""
        while not self._stopping.wait(1.0 / POSE_RATE):
            self.source.broadcast_pose()

    def _debug_loop(self) -> None:
        period = 1.0 / self.params.debug_rate
        while not self._stopping.wait(period):
            if self.debug_pub.get_num_connections() > 0:
                try:
                    frame = self.source.newest()
                except FrameUnavailable:
                    continue
                if frame is not None:
                    self._publish_debug(frame, [])

    def _publish_debug(self, frame: Frame, outlines) -> None:
        image = draw_detections(frame, outlines)
        height, width = image.shape[:2]
        message = Image(height=height, width=width, encoding='rgb8', is_bigendian=0, step=width * 3)
        message.header.stamp = rospy.Time.from_sec(frame.stamp)
        message.header.frame_id = self.params.camera
        message.data = np.ascontiguousarray(image).tobytes()
        self.debug_pub.publish(message)


def _debug_logged() -> bool:
    """Whether a debug message would be logged (rospy formats and dispatches it before it knows)."""
    return logging.getLogger('rosout').isEnabledFor(logging.DEBUG)


def _why_not_registering(footprint) -> str:
    """Why a vision system holds no registration it could renew: its field of view is unknown
    (None) or empty (a stale feed, or no floor in sight)."""
    if footprint is None:
        return 'waiting for the field of view (CameraInfo, tf and a frame)'
    return 'no field of view to register: the camera feed is stale or it sees no floor'


def _moved(old, new, threshold: float) -> bool:
    """Whether a field of view changed by more than ``threshold`` metres at any vertex."""
    if len(old) != len(new):
        return True
    if not new:
        return False
    return float(np.max(np.abs(np.asarray(old) - np.asarray(new)))) > threshold
