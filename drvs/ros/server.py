"""The DRVS server node: registry of vision systems, Algorithm 1 matching by capability, forwarding.

Services (in the node's namespace; run it as ``__name:=drvs``). Every response
carries a ``status`` (:mod:`drvs.common.status`): ``ACCEPTED``; ``INVALID`` with a
message naming the field; ``UNSUPPORTED`` (no registered vision system runs the
algorithm); or a temporary ``BUSY`` / ``RATE_LIMITED`` / ``UNAVAILABLE`` with
``retry_after`` seconds.

- ``~register_vision_service`` (drvs/RegisterVisionService): a vision system
  registers, moves (new field of view), changes (new ``algorithms``) or renews
  its entry; an empty field of view unregisters. ``algorithms`` lists the
  algorithm names it runs, an empty list meaning the built-ins
  (:data:`drvs.algorithms.BUILTIN_NAMES`). The response grants a ``lease``:
  renew at half of it. ``INVALID`` when the polygon is invalid (fewer than 3
  vertices, a coordinate not finite, zero area, self-intersecting), a name in
  ``algorithms`` is not an algorithm NAME (or there are too many,
  :func:`drvs.server.registry.algorithm_names`), the service is unknown to the master
  or not a drvs/DetectObjectBoundary, or the caller is not the node that
  provides it. ``UNAVAILABLE`` while the vision system is ejected after failed
  forwards (:mod:`drvs.server.registry`) or when the master does not answer.
- ``~detect_object_boundary`` (drvs/DetectObjectBoundary): a robot's request,
  checked in this order. ``INVALID``: the algorithm — in full when the server
  knows its NAME (the built-ins and the plugins installed where the server runs,
  :func:`drvs.algorithms.default_algorithms`), else its ``NAME[:PARAMS]`` syntax
  only (the vision systems that run it check its PARAMS) —, the region of
  interest, the callback service (a global name, known to the master, of type
  drvs/CallbackCoordinates). ``UNSUPPORTED`` when no registered vision system
  runs the algorithm's NAME; the message lists the names that are available.
  (While no vision system at all is registered nothing is known about what will
  be: the request is accepted and sent to none, as for a robot started before
  the cameras.) Then it is matched against the registry — the vision systems
  whose field of view meets the region *and* that run the algorithm —, queued
  for each of them, and acknowledged at once with ``vision_systems`` set: the
  forwards start once the acknowledgement is written (:class:`ReplyFirstService`).
  Forwards carry every field unchanged, one at a time per vision system over one
  persistent connection (:class:`ServiceClient`, re-created after a failure), each
  call limited to ``~forward_timeout``. On an open connection a forward is sent
  by the thread at hand (the request's, after its acknowledgement, or the one that
  saw the previous forward to that vision system end) and one thread, the reply
  loop (:class:`ReplyLoop`), waits for every reply; connecting (and watch
  forwards) is left to a bounded pool of workers (:class:`drvs.server.dispatch.Dispatcher`).
  ``BUSY`` when the pool is full; ``UNAVAILABLE`` when the master does not answer,
  or does not list a callback service that it listed within ``~callback_memory``
  seconds (a restarted master, before the robot registered again).
- ``~watch_object_boundary`` (drvs/WatchObjectBoundary): a robot's standing
  request (a *watch*, :mod:`drvs.server.watch_table`), keyed by its caller id and
  ``request_id``. ``INVALID``: ``request_id`` empty or too long, ``duration`` not
  finite or negative, and for a watch to stand (``duration`` > 0) ``period`` not
  finite or not positive and the same checks as ``~detect_object_boundary``
  (algorithm, region of interest, callback service), or a ``request_id`` and
  ``callback_service`` that another caller's watch uses already. ``UNSUPPORTED``
  as for a request. ``BUSY`` beyond ``~max_watches``. Granted: a period of at least
  ``~min_watch_period``, a duration of at most ``~max_watch_duration``. The same
  caller and ``request_id`` again renews it (the region may change); ``duration`` 0
  cancels it (a cancel of an unknown watch is accepted too; a cancel needs valid
  ``request_id`` and ``duration`` only). The answer says how many vision systems
  serve it now (maybe 0: vision systems that cover its region later join).
  The server forwards the watch to every vision system that covers the region and
  runs the algorithm — at its sibling ``<namespace>/watch_object_boundary``
  service, looked up when the vision system registers anew —, renews it there
  when the caller renews, withdraws it (``duration`` 0) from one that stops
  covering it or leaves the registry and from all on cancel or expiry. A vision
  system without a watch service (the paper's interface only) gets one
  DetectObjectBoundary request per period instead, with the watch's
  ``request_id`` and callback; that is never counted as a failure. A failed watch
  forward counts like a failed request forward; a refused one is logged.

All three services limit each caller (its caller id) to ``~max_requests_per_s``
with bursts of ``~burst`` (a token bucket per caller, :mod:`drvs.server.rate_limit`,
shared by the three); the excess is refused with ``RATE_LIMITED``.

Topics: ``~stats`` (drvs/ServerStats, latched): the server's counters (requests,
watch calls, refusals, forwards of each kind, failures, watches standing),
republished at most once a second while they change. ``~registry`` (drvs/Registry,
latched): every entry's ``service_name``, ``provider``, ``field_of_view``,
``algorithms`` and ``lease_expiry`` (ROS time), sorted by service name (algorithms
sorted too), republished after every change (registration, move, change of
algorithms, unregistration, expiry, removal; not renewals), at most once per
``~registry_period``. With each, ``~markers`` (visualization_msgs/MarkerArray,
latched, frame ``map``; :mod:`drvs.ros.markers`): a DELETEALL, then every registered
field of view's outline and name, for RViz.

Topic ``/diagnostics`` (diagnostic_msgs/DiagnosticArray, 1 Hz): status ``drvs: <node
name>``, hardware_id the host (:func:`drvs.common.health.server_health`). ERROR when the
forwarding pool is full (requests refused ``BUSY``); WARN when no vision system is
registered, the pool is more than 80 % full, requests were refused ``BUSY`` or
``RATE_LIMITED`` in the last second, or a vision system is ejected; OK otherwise.
Values: registered vision systems, pending and maximum forwards, rate-limited callers
(those over their share now), ejected vision systems, watches standing, and refusals
per status in the last period and since start.

Parameters: the fields of :class:`ServerSettings`, each declared with its default,
meaning and range; README.md's drvs_server table is generated from them.

Background loops (lease expiry, registry publisher, watches, stats) are guarded
(:class:`drvs.common.guard.LoopGuard`): an unexpected exception is logged with its
traceback and the loop restarts; one that keeps failing shuts the node down
with exit code 1. The watch loop follows every change of the registry and runs
the watches' expiries and one-shots on ROS time. Logs: info for register (with
the algorithms and whether it serves watches), move, change of algorithms,
unregister, expiry, removal and ejection, for every refused request and watch
call — but those refused ``BUSY`` or ``RATE_LIMITED``, and requests that skipped busy
vision systems, at most once per ``LOG_PERIOD`` seconds each, with the number not
logged since: a log line costs more than a request, and a saturated server refuses
thousands a second —, and for each new, cancelled or expired watch; debug per forward.
"""

from __future__ import annotations

import io
import logging
import math
import socket
import threading
import time
import traceback
from collections import OrderedDict
from dataclasses import dataclass

import rosgraph.names
import rospy
from visualization_msgs.msg import MarkerArray

from drvs.algorithms import AlgorithmError, AlgorithmSet, default_algorithms, split_algorithm
from drvs.common.client_cache import ClosingCache
from drvs.common.counters import PeriodCounts
from drvs.common.guard import RESTART, LoopGuard
from drvs.common.health import Health, server_health
from drvs.common.settings import NON_NEGATIVE, POSITIVE, ParamError, Settings, at_least, param
from drvs.common.status import ACCEPTED, BUSY, INVALID, RATE_LIMITED, UNAVAILABLE, UNSUPPORTED, Refusal, name
from drvs.common.validation import (
    ValidationError,
    field_of_view_polygon,
    global_ros_name,
    region_of_interest,
    ros_name,
)
from drvs.msg import Registry as RegistryMsg
from drvs.msg import ServerStats
from drvs.ros.conversions import box_to_msg, msg_to_box, polygon_to_points, refusal_to_detect_response
from drvs.ros.diagnostics import DiagnosticsPublisher
from drvs.ros.markers import registry_markers
from drvs.ros.messages import header, registry_to_msg
from drvs.ros.service_client import (
    MasterUnreachable,
    ReplyLoop,
    ServiceCallError,
    ServiceClient,
    ServiceInfo,
    UnknownService,
    probe_service,
)
from drvs.server.dispatch import Busy, Dispatcher
from drvs.server.rate_limit import RateLimiter
from drvs.server.registry import (
    CHANGED,
    MOVED,
    NOT_REGISTERED,
    REGISTERED,
    RENEWED,
    Registration,
    Registry,
    algorithm_names,
)
from drvs.server.watch_table import (
    CANCELLED,
    NOT_STANDING,
    ONE_SHOT,
    WITHDRAWAL,
    Forward,
    Watch,
    WatchTable,
    watch_terms,
)
from drvs.srv import (
    CallbackCoordinates,
    DetectObjectBoundary,
    DetectObjectBoundaryRequest,
    DetectObjectBoundaryResponse,
    RegisterVisionService,
    RegisterVisionServiceResponse,
    WatchObjectBoundary,
    WatchObjectBoundaryRequest,
    WatchObjectBoundaryResponse,
)

__all__ = ['ServerSettings', 'DrvsServer']

MAX_CALLBACKS_REMEMBERED = 10_000
"""Verified callback services kept; callers choose the names, so the memory is capped."""
MAX_REPLIES_KEPT = 4096
"""Acknowledgements kept for reuse, one per (vision systems forwarded to, skipped)."""
MAX_ALGORITHMS_REMEMBERED = 1024
"""Algorithm strings remembered as valid (with their NAME); callers choose them, so capped."""
MAX_WATCH_CLIENTS = 4096
"""Connections to vision systems' watch services kept open (one per vision system)."""
WATCH_CLIENT_IDLE = 120.0
"""Seconds a watch service connection may stay unused before it is closed."""
WATCH_WAIT = 0.5
"""Longest wall-clock wait of the watch loop between two looks at the clock (ROS time may run faster)."""
STATS_PERIOD = 1.0
"""Seconds between two ``~stats`` messages at most."""
LOG_PERIOD = 1.0
"""Seconds between two log lines about requests refused for load (or that skipped busy vision systems)."""
THROTTLED = (BUSY, RATE_LIMITED)
"""Refusals for load: logged at most once per ``LOG_PERIOD`` (per kind of call)."""
STATS_FIELDS = (
    'requests',
    'watch_requests',
    'refused',
    'forwards',
    'watch_forwards',
    'forward_failures',
    'fallback_forwards',
)
"""The counters of drvs/ServerStats (besides ``watches``, the number standing)."""


@dataclass(frozen=True)
class ServerSettings(Settings):
    lease: float = param(
        10.0, 'a registration expires unless renewed within this time', unit='s', check=POSITIVE
    )
    max_failures: int = param(
        3,
        'failed forwards in a row that remove (and eject) a vision system; renewals do not reset it',
        check=at_least(1),
    )
    ejection_time: float = param(
        10.0, 'an ejected vision system is refused this long × its ejections', unit='s', check=NON_NEGATIVE
    )
    max_ejection_time: float = param(
        300.0, 'the longest ejection; at least `~ejection_time`', unit='s', check=NON_NEGATIVE
    )
    forward_timeout: float = param(
        2.0, 'limit on one forward (connect, send, reply)', unit='s', check=POSITIVE
    )
    workers: int = param(8, 'forwarding threads (a hung vision system holds at most one)', check=at_least(1))
    max_pending: int = param(
        1000, 'forwards queued or running; beyond it requests are refused `BUSY`', check=at_least(1)
    )
    max_pending_per_vision_system: int = param(
        10, 'a vision system this far behind is skipped by new requests', check=at_least(1)
    )
    busy_retry_after: float = param(0.5, '`retry_after` of a `BUSY` refusal', unit='s', check=POSITIVE)
    unavailable_retry_after: float = param(
        1.0, '`retry_after` when the master did not answer', unit='s', check=POSITIVE
    )
    max_requests_per_s: float = param(
        50.0, 'calls per second per caller id, on all three services', unit='/s', check=POSITIVE
    )
    burst: int = param(100, 'requests a caller may send at once before the rate applies', check=at_least(1))
    check_timeout: float = param(
        1.0, 'limit on each master lookup / probe during validation', unit='s', check=POSITIVE
    )
    callback_cache: float = param(
        5.0, 'how long a verified callback service is trusted', unit='s', check=NON_NEGATIVE
    )
    callback_memory: float = param(
        60.0,
        'a verified callback service the master stops listing is `UNAVAILABLE`, not `INVALID`, this long',
        unit='s',
        check=NON_NEGATIVE,
    )
    registry_period: float = param(
        0.2, 'minimum time between two `~registry` messages', unit='s', check=NON_NEGATIVE
    )
    min_watch_period: float = param(0.1, 'shortest period a watch is granted', unit='s', check=POSITIVE)
    max_watch_duration: float = param(
        60.0, 'longest duration a watch is granted (it expires unless renewed)', unit='s', check=POSITIVE
    )
    max_watches: int = param(
        1000, 'watches standing at once; beyond it new watches are refused `BUSY`', check=at_least(1)
    )

    def __post_init__(self):
        super().__post_init__()
        if not self.max_ejection_time >= self.ejection_time:
            raise ParamError(
                'max_ejection_time',
                f'must be at least ~ejection_time ({self.ejection_time!r}), got {self.max_ejection_time!r}',
            )


def _caller(request) -> str:
    return request._connection_header.get('callerid', '')


class LogThrottle:
    """At most one log line per kind of event and ``period`` seconds, and how many were not logged.

    >>> clock = iter([0.0, 0.5, 0.7, 1.2]).__next__
    >>> throttle = LogThrottle(1.0, clock)
    >>> [throttle.allow('BUSY') for _ in range(4)]
    [0, None, None, 2]
    """

    def __init__(self, period: float, clock=time.monotonic):
        self.period = period
        self.clock = clock
        self._lock = threading.Lock()  # guards _next and _unlogged
        self._next: dict[object, float] = {}  # kind -> when the next line may be logged
        self._unlogged: dict[object, int] = {}  # kind -> events not logged since the last line

    def allow(self, kind) -> int | None:
        """None: do not log this event (it is counted); else log it, with this many not logged before."""
        with self._lock:
            now = self.clock()
            if now < self._next.get(kind, -math.inf):
                self._unlogged[kind] = self._unlogged.get(kind, 0) + 1
                return None
            self._next[kind] = now + self.period
            return self._unlogged.pop(kind, 0)


def _not_logged(count: int) -> str:
    return f' ({count} more like it not logged in the last {LOG_PERIOD:g} s)' if count else ''


class ReplyFirstService(rospy.Service):
    """A ``rospy.Service`` that calls ``after_reply()`` once each reply is written.

    rospy writes a handler's reply when the handler returns. Work the handler starts
    at once (the server's forwards) would compete with that write for the
    interpreter, and the caller would wait longer for its acknowledgement; so the
    handler only queues, and ``after_reply``, run on the same thread once the reply
    is out (or failed), sends. This overrides ``ServiceImpl._handle_request``,
    rospy's per-request step (ROS 1 Noetic's rospy, the last ROS 1 release).
    """

    def __init__(self, name: str, service_class, handler, after_reply):
        self._after_reply = after_reply  # before rospy.Service registers: a call may come at once
        super().__init__(name, service_class, handler)

    def _handle_request(self, transport, request) -> None:
        try:
            super()._handle_request(transport, request)
        finally:
            self._after_reply()


class DrvsServer:
    """The server's ROS glue; :meth:`start` creates the services, topic and threads."""

    def __init__(self, settings: ServerSettings):
        self.settings = settings
        self.registry = Registry(
            lease=settings.lease,
            max_failures=settings.max_failures,
            ejection_time=settings.ejection_time,
            max_ejection_time=settings.max_ejection_time,
        )
        self.dispatcher = Dispatcher(
            self._forward,
            workers=settings.workers,
            max_pending=settings.max_pending,
            max_per_destination=settings.max_pending_per_vision_system,
            retry_after=settings.busy_retry_after,
            begin=self._begin_forward,
        )
        self.replies = ReplyLoop('forward-replies')  # waits for the replies of forwards in flight
        self.rate_limiter = RateLimiter(settings.max_requests_per_s, settings.burst)
        self._stopping = threading.Event()
        self.guard = LoopGuard(on_fatal=lambda reason: rospy.signal_shutdown(reason), stop=self._stopping)
        self._lock = threading.Lock()  # guards _callbacks
        # Verified callback service -> when verified (time.monotonic()), oldest first; bounded in size
        # and age (_remembered). Not a cachetools.TTLCache: every request looks here, and its reads
        # cost more than the rest of the check.
        self._callbacks: OrderedDict[str, float] = OrderedDict()
        self._remembered = max(settings.callback_memory, settings.callback_cache, 1e-3)
        self._replies: dict[tuple[int, int], DetectObjectBoundaryResponse] = {}  # see _accepted()
        self._changed = threading.Condition()
        self._dirty = True
        self._registry_publisher = None
        self.watches = WatchTable(
            self.registry,
            rospy.get_time,
            min_period=settings.min_watch_period,
            max_duration=settings.max_watch_duration,
            max_watches=settings.max_watches,
            busy_retry_after=settings.busy_retry_after,
        )
        self._watch_lock = threading.Lock()  # guards watches, and keeps their forwards in order
        self._watch_wake = threading.Event()  # set when the registry changed or a forward failed
        self._watch_clients = ClosingCache(self._make_watch_client, MAX_WATCH_CLIENTS, WATCH_CLIENT_IDLE)
        self._stats_lock = threading.Lock()  # guards stats
        self.stats = dict.fromkeys(STATS_FIELDS, 0)
        self._held = threading.local()  # .forwards: queued by this thread's handler, not sent yet
        self._algorithm_names: dict[str, str] = {}  # valid algorithm string -> its NAME
        self._log_throttle = LogThrottle(LOG_PERIOD)
        self.algorithms: AlgorithmSet | None = None  # those the server can check in full; set by start()
        self.refusals = PeriodCounts()  # refusals by status name, for the health report
        self.diagnostics = DiagnosticsPublisher(
            f'drvs: {rospy.get_name()}', socket.gethostname(), self.health, guard=self.guard
        )

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> None:
        self.algorithms = default_algorithms()
        self._registry_publisher = rospy.Publisher('~registry', RegistryMsg, queue_size=1, latch=True)
        self._markers_publisher = rospy.Publisher('~markers', MarkerArray, queue_size=1, latch=True)
        self._stats_publisher = rospy.Publisher('~stats', ServerStats, queue_size=1, latch=True)
        self.replies.start()
        self.dispatcher.start()
        self.guard.spawn(self._expire_loop, 'lease-expiry', RESTART)
        self.guard.spawn(self._publish_loop, 'registry-publisher', RESTART)
        self.guard.spawn(self._watch_loop, 'watches', RESTART)
        self.guard.spawn(self._stats_loop, 'stats-publisher', RESTART)
        rospy.Service('~register_vision_service', RegisterVisionService, self.handle_register)
        ReplyFirstService(
            '~detect_object_boundary', DetectObjectBoundary, self.handle_detect, self._release_forwards
        )
        rospy.Service('~watch_object_boundary', WatchObjectBoundary, self.handle_watch)
        self.diagnostics.start()
        rospy.loginfo(
            'DRVS server ready: lease %g s, max_failures %d, forward_timeout %g s, %d workers, '
            'rate limit %g/s (burst %d) per caller; watches: period at least %g s, duration at most %g s; '
            'algorithms checked in full: %s',
            self.settings.lease,
            self.settings.max_failures,
            self.settings.forward_timeout,
            self.settings.workers,
            self.settings.max_requests_per_s,
            self.settings.burst,
            self.settings.min_watch_period,
            self.settings.max_watch_duration,
            ', '.join(self.algorithms.names()),
        )

    def stop(self) -> None:
        self._stopping.set()
        self.diagnostics.stop()
        self._watch_wake.set()
        with self._changed:
            self._changed.notify_all()
        self.dispatcher.stop(timeout=self.settings.forward_timeout + 1.0)
        self.replies.stop(timeout=self.settings.forward_timeout + 1.0)
        for entry in self.registry.entries():
            self._close(self.registry.unregister(entry.service_name))
        self._watch_clients.clear()

    # -- refusals ----------------------------------------------------------------------------
    def _rate_limit(self, request) -> Refusal | None:
        caller = _caller(request)
        wait = self.rate_limiter.take(caller)
        if wait <= 0:
            return None
        return Refusal(
            RATE_LIMITED,
            f'rate limited: {caller or "(no caller id)"} sends more than '
            f'{self.settings.max_requests_per_s:g} requests/s (bursts of {self.settings.burst}); '
            f'retry after {wait:.3f} s',
            wait,
        )

    def _refuse_register(self, refusal: Refusal) -> RegisterVisionServiceResponse:
        self.refusals.add(name(refusal.status))
        log = rospy.logwarn if refusal.status == INVALID else rospy.loginfo
        log('registration refused (%s): %s', name(refusal.status), refusal.message)
        return RegisterVisionServiceResponse(
            accepted=False, status=refusal.status, message=refusal.message, retry_after=refusal.retry_after
        )

    def _refuse_detect(self, request, refusal: Refusal) -> DetectObjectBoundaryResponse:
        self._log_refusal('request', request, refusal)
        return refusal_to_detect_response(refusal)

    def _refuse_watch(self, request, refusal: Refusal) -> WatchObjectBoundaryResponse:
        self._log_refusal('watch call', request, refusal)
        return WatchObjectBoundaryResponse(
            accepted=False, status=refusal.status, message=refusal.message, retry_after=refusal.retry_after
        )

    def _log_refusal(self, what: str, request, refusal: Refusal) -> None:
        self.refusals.add(name(refusal.status))
        self._count(refused=1)
        unlogged = 0
        if refusal.status in THROTTLED:  # a saturated server refuses thousands a second
            unlogged = self._log_throttle.allow((what, refusal.status))
            if unlogged is None:
                return
        rospy.loginfo(
            '%s %r from %s refused (%s): %s%s',
            what,
            request.request_id,
            _caller(request) or '?',
            name(refusal.status),
            refusal.message,
            _not_logged(unlogged),
        )

    # -- registration ------------------------------------------------------------------------
    def handle_register(self, request) -> RegisterVisionServiceResponse:
        try:
            return self._register(request, _caller(request))
        except Refusal as refusal:
            return self._refuse_register(refusal)
        except Exception as error:  # a bug: answer with a status, never rospy's bare error reply
            return self._refuse_register(self._internal_error('registration', error))

    def _register(self, request, caller: str) -> RegisterVisionServiceResponse:
        limited = self._rate_limit(request)
        if limited:
            raise limited
        try:
            ros_name('service_name', request.service_name)
        except ValidationError as error:
            raise Refusal(INVALID, str(error)) from None
        service = rosgraph.names.resolve_name(request.service_name, caller or '/')
        if caller == rospy.get_name():
            raise Refusal(
                INVALID,
                f'service_name: the caller {caller} is the DRVS server itself; forwarding to it would loop',
            )
        points = polygon_to_points(request.field_of_view)
        entry = self.registry.get(service)
        if not points:
            return self._unregister(service, entry, caller)
        try:
            field_of_view_polygon(points)
            algorithms = algorithm_names(request.algorithms)
        except ValidationError as error:
            raise Refusal(INVALID, f'{error} (service_name {service})') from None
        if entry is not None and entry.provider == caller:  # a renewal or move by the verified provider
            instance, watch_service = entry.instance, entry.watch_service
        else:
            provider = caller or '(no caller id)'
            instance = self._check_service(
                'service_name', service, DetectObjectBoundary, provider_must_be=provider
            ).uri
            watch_service = self._has_watch_service(service, provider)
        try:
            change = self.registry.register(
                service,
                points,
                provider=caller,
                make_client=self._make_client,
                instance=instance,
                algorithms=sorted(algorithms),
                watch_service=watch_service,
            )
        except ValidationError as error:
            raise Refusal(INVALID, f'{error} (service_name {service})') from None
        if change == REGISTERED:
            with self._watch_lock:  # a restarted vision system holds no watches: forward them again
                self.watches.forget(service)
            rospy.loginfo(
                'registered %s by %s: field of view %s, algorithms %s; %s',
                service,
                caller,
                points,
                ', '.join(sorted(algorithms)),
                'a watch service' if watch_service else 'no watch service (watches by one-shot requests)',
            )
        elif change == MOVED:
            rospy.loginfo(
                'moved %s: field of view %s, algorithms %s', service, points, ', '.join(sorted(algorithms))
            )
        elif change == CHANGED:
            rospy.loginfo('changed %s: algorithms %s', service, ', '.join(sorted(algorithms)))
        else:
            rospy.logdebug('renewed %s', service)
        if change != RENEWED:
            self._mark_changed()
        return RegisterVisionServiceResponse(
            accepted=True,
            status=ACCEPTED,
            message=f'{change} {service}; lease {self.settings.lease:g} s',
            lease=self.settings.lease,
        )

    def _unregister(
        self, service: str, entry: Registration | None, caller: str
    ) -> RegisterVisionServiceResponse:
        if entry is not None and entry.provider != caller:
            raise Refusal(
                INVALID,
                f'service_name: {service} was registered by {entry.provider}; {caller} may not unregister it',
            )
        removed = self.registry.unregister(service)
        if removed is None:
            return RegisterVisionServiceResponse(
                accepted=True, status=ACCEPTED, message=f'{NOT_REGISTERED}: {service}'
            )
        self._close(removed)
        rospy.loginfo('unregistered %s (asked by %s)', service, caller)
        self._mark_changed()
        return RegisterVisionServiceResponse(
            accepted=True, status=ACCEPTED, message=f'unregistered {service}'
        )

    def _make_client(self, service: str) -> ServiceClient:
        return ServiceClient(
            service, DetectObjectBoundary, self.settings.forward_timeout, caller_id=rospy.get_name()
        )

    def _make_watch_client(self, service: str) -> ServiceClient:
        return ServiceClient(
            service, WatchObjectBoundary, self.settings.forward_timeout, caller_id=rospy.get_name()
        )

    def _has_watch_service(self, service: str, provider: str) -> bool:
        """Whether the vision system of ``service`` serves watches: its sibling
        ``watch_object_boundary`` is a drvs/WatchObjectBoundary of the same node.

        :raises Refusal: ``UNAVAILABLE`` when the master did not answer.
        """
        try:
            self._check_service(
                'watch service', watch_service_of(service), WatchObjectBoundary, provider_must_be=provider
            )
        except Refusal as refusal:
            if refusal.status != INVALID:
                raise
            rospy.logdebug('%s: %s', service, refusal.message)
            return False
        return True

    def _close(self, entry: Registration | None) -> None:
        """Drop what the server still holds for a removed entry: queued forwards, its connection."""
        if entry is None:
            return
        dropped = self.dispatcher.drop(entry.service_name)
        if dropped:
            rospy.loginfo('dropped %d queued forwards to %s', dropped, entry.service_name)
        if entry.client is not None:
            entry.client.close()

    def _check_service(
        self, field: str, service: str, service_class, provider_must_be: str | None = None
    ) -> ServiceInfo:
        """Check that ``service`` is known to the master and of the expected type (and provider).

        :raises Refusal: ``INVALID`` naming ``field`` and the problem; ``UNAVAILABLE`` when the
            master or the service did not answer in time.
        """
        try:
            info = probe_service(service, self.settings.check_timeout, caller_id=rospy.get_name())
        except UnknownService:
            raise Refusal(INVALID, f'{field}: {service} is not known to the ROS master') from None
        except MasterUnreachable as error:
            raise Refusal(
                UNAVAILABLE,
                f'{field}: cannot check {service}: {error}; retry later',
                self.settings.unavailable_retry_after,
            ) from None
        except ServiceCallError as error:
            raise Refusal(INVALID, f'{field}: {service} cannot be reached: {error}') from None
        if info.type != service_class._type or info.md5sum != service_class._md5sum:
            raise Refusal(
                INVALID,
                f'{field}: {service} is of type {info.type or "(unknown)"}, expected {service_class._type}',
            )
        if provider_must_be is not None and info.provider != provider_must_be:
            raise Refusal(
                INVALID,
                f'{field}: {service} is provided by {info.provider}, not by the caller {provider_must_be}; '
                'a node may register only its own service',
            )
        return info

    # -- requests ----------------------------------------------------------------------------
    def handle_detect(self, request) -> DetectObjectBoundaryResponse:
        self._count(requests=1)
        try:
            return self._detect(request)
        except Refusal as refusal:
            return self._refuse_detect(request, refusal)
        except Exception as error:  # a bug: answer with a status, never rospy's bare error reply
            return self._refuse_detect(request, self._internal_error('request', error))

    def _internal_error(self, what: str, error: Exception) -> Refusal:
        rospy.logerr('%s failed unexpectedly:\n%s', what, traceback.format_exc())
        return Refusal(
            UNAVAILABLE,
            f'internal error in the DRVS server ({type(error).__name__}: {error}); '
            'it is logged there; retry later',
            self.settings.unavailable_retry_after,
        )

    def _detect(self, request) -> DetectObjectBoundaryResponse:
        limited = self._rate_limit(request)
        if limited:
            raise limited
        algorithm, region = self._request_fields(request)
        self._check_callback(request.callback_service)
        names = self.registry.match(region, algorithm)
        if not names:
            return self._sent_to_none(region, algorithm)
        # The request itself is forwarded: every field unchanged (the caller's connection
        # header is not part of the message). They are sent once the reply is out.
        accepted, skipped = self.dispatcher.submit(names, Outgoing(request), wake=False)  # raises Busy
        self._held.forwards = getattr(self._held, 'forwards', 0) + len(accepted)
        if skipped and accepted and (unlogged := self._log_throttle.allow('skipped')) is not None:
            rospy.logwarn(
                'request %s: skipped busy vision systems %s%s',
                request.request_id,
                skipped,
                _not_logged(unlogged),
            )
        if not accepted:
            raise Busy(
                f'busy: all {len(names)} vision systems that cover the region and run {algorithm!r} have '
                f'{self.settings.max_pending_per_vision_system} forwards pending; try again later',
                self.settings.busy_retry_after,
            )
        return self._accepted(len(accepted), len(skipped))

    def _accepted(self, forwarded: int, skipped: int) -> DetectObjectBoundaryResponse:
        """The acknowledgement of a request sent to ``forwarded`` vision systems (``skipped`` busy),
        made once and shared: rospy only serialises a reply, and a new one costs more than the check
        that made it."""
        reply = self._replies.get((forwarded, skipped))
        if reply is None:
            message = f'forwarded to {forwarded} vision system{"s" if forwarded != 1 else ""}'
            if skipped:
                message += f'; {skipped} busy vision system(s) skipped'
            reply = DetectObjectBoundaryResponse(
                accepted=True, status=ACCEPTED, message=message, vision_systems=forwarded
            )
            if len(self._replies) < MAX_REPLIES_KEPT:
                self._replies[(forwarded, skipped)] = reply
        return reply

    def _release_forwards(self) -> None:
        """After a reply to ``~detect_object_boundary``: send its forwards."""
        held = getattr(self._held, 'forwards', 0)
        if held:
            self._held.forwards = 0
            self.dispatcher.release(held)

    def _request_fields(self, request) -> tuple[str, tuple[float, float, float, float]]:
        """The algorithm's NAME and the region of a request or watch, its callback name checked.

        :raises Refusal: ``INVALID`` naming the field.
        """
        try:
            algorithm = self._algorithm_name(request.algorithm)
            region = region_of_interest(msg_to_box(request.region_of_interest))
            global_ros_name('callback_service', request.callback_service)
        except (AlgorithmError, ValidationError) as error:
            raise Refusal(INVALID, str(error)) from None
        return algorithm, region

    def _algorithm_name(self, text: str) -> str:
        """The NAME of the request's algorithm, checked in full if the server knows it, else its syntax.

        :raises AlgorithmError: bad syntax; PARAMS that a known algorithm refuses.
        """
        known = self._algorithm_names.get(text)
        if known is not None:
            return known
        algorithm, _ = split_algorithm(text)
        if algorithm in self.algorithms:
            self.algorithms.parse(text)
        if len(self._algorithm_names) >= MAX_ALGORITHMS_REMEMBERED:
            self._algorithm_names.clear()
        self._algorithm_names[text] = algorithm
        return algorithm

    def _sent_to_none(self, region, algorithm: str) -> DetectObjectBoundaryResponse:
        """The answer to a valid request that no vision system will get: why none.

        :raises Refusal: ``UNSUPPORTED`` when vision systems are registered and none runs ``algorithm``.
        """
        available = self._check_supported(algorithm)
        if available and self.registry.match(region):
            message = f'no vision system that runs {algorithm!r} covers the region of interest'
        else:
            message = 'no vision system covers the region of interest'
        return DetectObjectBoundaryResponse(accepted=True, status=ACCEPTED, message=message, vision_systems=0)

    def _check_supported(self, algorithm: str) -> list[str]:
        """The algorithms the live vision systems run (none while nobody is registered).

        :raises Refusal: ``UNSUPPORTED`` when vision systems are registered and none runs ``algorithm``.
        """
        available = self.registry.available_algorithms()
        if available and algorithm not in available:
            raise Refusal(
                UNSUPPORTED,
                f'algorithm: no registered vision system runs {algorithm!r}; '
                f'available: {", ".join(available)}',
            )
        return available

    # -- watches -----------------------------------------------------------------------------
    def handle_watch(self, request) -> WatchObjectBoundaryResponse:
        self._count(watch_requests=1)
        try:
            return self._watch(request)
        except Refusal as refusal:
            return self._refuse_watch(request, refusal)
        except Exception as error:  # a bug: answer with a status, never rospy's bare error reply
            return self._refuse_watch(request, self._internal_error('watch call', error))

    def _watch(self, request) -> WatchObjectBoundaryResponse:
        limited = self._rate_limit(request)
        if limited:
            raise limited
        caller = _caller(request)
        try:
            stands = watch_terms(request.request_id, request.period, request.duration)
        except ValidationError as error:
            raise Refusal(INVALID, str(error)) from None
        algorithm, region = self._request_fields(request) if stands else ('', (0.0, 0.0, 0.0, 0.0))
        if stands:
            self._check_callback(request.callback_service)
            with self._watch_lock:
                standing = self.watches.get((caller, request.request_id))
            if standing is None or standing.algorithm_name != algorithm:
                # A renewal with the same algorithm is never UNSUPPORTED: the watch stands for the
                # vision systems that will come, as it did when the last one running it left.
                self._check_supported(algorithm)
        with self._watch_lock:
            try:
                answer = self.watches.request(
                    caller,
                    request.request_id,
                    request.algorithm,
                    algorithm,
                    region,
                    request.callback_service,
                    request.period,
                    request.duration,
                    request.changes_only,
                )
            except ValidationError as error:
                raise Refusal(INVALID, str(error)) from None
            self._submit(answer.forwards)
            serving = self.watches.serving((caller, request.request_id))
        return WatchObjectBoundaryResponse(
            accepted=True,
            status=ACCEPTED,
            message=_watch_message(answer.change, request.request_id, len(serving)),
            vision_systems=len(serving),
            period=answer.period,
            duration=answer.duration,
        )

    def _submit(self, forwards: list[Forward]) -> None:
        """Queue watch forwards in order (the caller holds ``_watch_lock``); one that finds no room
        is left to the watch table (:meth:`WatchTable.undelivered`)."""
        for forward in forwards:
            one_shot = forward.kind == ONE_SHOT
            destination = forward.vision_system if one_shot else watch_service_of(forward.vision_system)
            try:
                accepted, _ = self.dispatcher.submit([destination], forward)
            except Busy:
                accepted = []
            if not accepted:
                rospy.logdebug(
                    '%s of watch %r to %s not sent: too many forwards pending',
                    forward.kind,
                    forward.watch.request_id,
                    destination,
                )
                self.watches.undelivered(forward)

    def _check_callback(self, service: str) -> None:
        """Check the callback service, trusting a check made within ``~callback_cache`` seconds.

        :raises Refusal: as :meth:`_check_service`, except that a service verified within
            ``~callback_memory`` seconds and now unknown to the master is ``UNAVAILABLE``
            (a restarted master that its node has not registered with yet), not ``INVALID``.
        """
        now = time.monotonic()
        with self._lock:
            verified = self._callbacks.get(service)
        if verified is not None and now - verified >= self._remembered:
            verified = None  # forgotten
        if verified is not None and now - verified < self.settings.callback_cache:
            return
        try:
            self._check_service('callback_service', service, CallbackCoordinates)
        except Refusal as refusal:
            if verified is not None and refusal.status == INVALID:
                raise Refusal(
                    UNAVAILABLE,
                    f'{refusal.message} now, though it was {now - verified:.1f} s ago '
                    '(a restarted master?); retry later',
                    self.settings.unavailable_retry_after,
                ) from None
            raise
        with self._lock:
            callbacks = self._callbacks
            callbacks[service] = now
            callbacks.move_to_end(service)
            while callbacks and (
                len(callbacks) > MAX_CALLBACKS_REMEMBERED
                or now - next(iter(callbacks.values())) >= self._remembered
            ):
                callbacks.popitem(last=False)

    # -- forwarding -------------------------------------------------------------------------
    def _begin_forward(self, destination: str, item, done) -> bool:
        """Send a robot's request without waiting (the dispatcher's ``begin``, on whichever thread
        has it: the handler's after its reply, or the one that saw the previous forward end); the
        reply loop settles it. False for what a worker must do: watch forwards, one-shots, and a
        request to a vision system without an open connection."""
        if isinstance(item, Forward):
            return False
        entry = self.registry.get(destination)
        if entry is None or entry.client is None:
            return False  # removed while queued: the worker drops it
        client, started = entry.client, time.monotonic()

        def settled(answer, error) -> None:
            self._settle(
                destination, client, f'forward of {item.request.request_id!r}', started, answer, error
            )
            done()

        if not client.start(item.request, self.replies, settled, serialized=item.serialized()):
            return False
        self._count(forwards=1)
        return True

    def _forward(self, destination: str, item) -> None:
        """Send one queued item on a worker, blocking: a robot's request, or a watch's :class:`Forward`."""
        if isinstance(item, Forward) and item.kind != ONE_SHOT:
            self._forward_watch(destination, item)
            return
        entry = self.registry.get(destination)
        if entry is None or entry.client is None:  # removed while the forward was queued
            return
        if isinstance(item, Forward):
            self._count(forwards=1, fallback_forwards=1)
            what = f'one-shot of watch {item.watch.request_id!r}'
            self._call(destination, entry.client, one_shot_request(item.watch), what)
        else:
            self._count(forwards=1)
            what = f'forward of {item.request.request_id!r}'
            self._call(destination, entry.client, item.request, what, item.serialized())

    def _forward_watch(self, destination: str, forward: Forward) -> None:
        service = forward.vision_system
        if forward.kind != WITHDRAWAL and service not in self.registry:  # removed while queued
            return
        self._count(watch_forwards=1)
        what = f'{forward.kind} of watch {forward.watch.request_id!r}'
        answer = self._call(service, self._watch_clients.get(destination), watch_request(forward), what)
        if answer is None:
            with self._watch_lock:
                self.watches.undelivered(forward)
            self._watch_wake.set()
        elif not answer.accepted:
            rospy.logwarn('%s refused by %s (%s): %s', what, destination, name(answer.status), answer.message)

    def _call(self, service: str, client: ServiceClient, request, what: str, serialized: bytes | None = None):
        """Send ``request`` (its bytes ``serialized`` if known) through ``client``, blocking; its answer,
        or None when it failed (:meth:`_settle`)."""
        started = time.monotonic()
        try:
            answer = client.call(request, serialized)
        except ServiceCallError as error:
            return self._settle(service, client, what, started, None, error)
        return self._settle(service, client, what, started, answer, None)

    def _settle(self, service: str, client: ServiceClient, what: str, started: float, answer, error):
        """The outcome of a call to the vision system ``service``: ``answer``, or None after ``error``.

        A failure counts against the registered vision system ``service`` (and may remove
        and eject it, :meth:`Registry.record_failure`); a success clears its failures. A
        call to a vision system no longer registered (a withdrawal) counts for neither.
        """
        if error is not None:
            self._count(forward_failures=1)
            if service not in self.registry:
                rospy.loginfo('%s to %s failed (no longer registered): %s', what, client.service, error)
                return None
            failures = self.registry.failures(service) + 1
            rospy.logwarn('%s to %s failed (%d in a row): %s', what, client.service, failures, error)
            removed = self.registry.record_failure(service)
            if removed is not None:
                rospy.logwarn(
                    'removed %s after %d failed forwards in a row; ejected for %.0f s',
                    service,
                    failures,
                    (self.registry.ejected_until(service) or time.monotonic()) - time.monotonic(),
                )
                self._close(removed)
                self._mark_changed()
            return None
        if service in self.registry:
            self.registry.record_success(service)
        if _debug_logged():
            rospy.logdebug(
                '%s to %s in %.1f ms: status %s %s',
                what,
                client.service,
                (time.monotonic() - started) * 1000,
                name(answer.status),
                answer.message,
            )
        return answer

    # -- background loops --------------------------------------------------------------------
    def _expire_loop(self) -> None:
        period = min(self.settings.lease / 4, 0.5)
        while not self._stopping.wait(period):
            for entry in self.registry.expire():
                rospy.loginfo('lease of %s expired: removed', entry.service_name)
                self._close(entry)
                self._mark_changed()

    def _mark_changed(self) -> None:
        with self._changed:
            self._dirty = True
            self._changed.notify()
        self._watch_wake.set()

    def _watch_loop(self) -> None:
        """Follow the registry's changes, expire watches, send one-shots when due (ROS time)."""
        while not self._stopping.is_set():
            self._watch_wake.clear()
            with self._watch_lock:
                self._submit(self.watches.sync())
                due = self.watches.next_due()
            self._watch_clients.expire()
            wait = WATCH_WAIT if due is None else min(max(due - rospy.get_time(), 0.001), WATCH_WAIT)
            self._watch_wake.wait(wait)

    def _count(self, **increments: int) -> None:
        with self._stats_lock:
            for key, number in increments.items():
                self.stats[key] += number

    def stats_msg(self) -> ServerStats:
        """The counters now (drvs/ServerStats), stamped with ROS time."""
        with self._stats_lock:
            counts = dict(self.stats)
        return ServerStats(header=header(rospy.get_time()), watches=len(self.watches), **counts)

    def _stats_loop(self) -> None:
        last = None
        while True:
            message = self.stats_msg()
            counts = tuple(getattr(message, key) for key in (*STATS_FIELDS, 'watches'))
            if counts != last:
                self._stats_publisher.publish(message)
                last = counts
            if self._stopping.wait(STATS_PERIOD):
                return

    def _publish_loop(self) -> None:
        stop = self._stopping
        while not stop.is_set():
            with self._changed:
                while not self._dirty and not stop.is_set():
                    self._changed.wait()
                self._dirty = False
            if stop.is_set():
                return
            registry = self.registry_msg()
            self._registry_publisher.publish(registry)
            self._markers_publisher.publish(
                registry_markers(
                    [(e.service_name, polygon_to_points(e.field_of_view)) for e in registry.vision_systems],
                    registry.header.stamp,
                )
            )
            stop.wait(self.settings.registry_period)

    def health(self) -> Health:
        """The server's health now, for ``/diagnostics``; the refusals counted since the last call."""
        recent = self.refusals.take_period()  # first: the totals then include every recent one
        return server_health(
            registered=len(self.registry),
            pending_forwards=self.dispatcher.pending,
            max_pending=self.settings.max_pending,
            refusals_by_status=self.refusals.totals(),
            refusals_recent=recent,
            rate_limited_callers=self.rate_limiter.limited(),
            ejected=self.registry.ejected(),
            watches=len(self.watches),
        )

    def registry_msg(self) -> RegistryMsg:
        """The registry now, with each lease's expiry in ROS time."""
        return registry_to_msg(self.registry.entries(), rospy.get_time(), self.registry.clock())


class Outgoing:
    """A robot's request on its way to the vision systems: serialised once, for all of them."""

    __slots__ = ('request', '_data')

    def __init__(self, request: DetectObjectBoundaryRequest):
        self.request = request
        self._data: bytes | None = None

    def serialized(self) -> bytes:
        """The request's bytes (two threads may make them at once: the same bytes)."""
        if self._data is None:
            buffer = io.BytesIO()
            self.request.serialize(buffer)
            self._data = buffer.getvalue()
        return self._data


def _debug_logged() -> bool:
    """Whether a debug message would be logged (rospy formats and dispatches it before it knows)."""
    return logging.getLogger('rosout').isEnabledFor(logging.DEBUG)


def watch_service_of(service: str) -> str:
    """The watch service of the vision system whose DetectObjectBoundary is ``service``: its sibling.

    >>> watch_service_of('/cam1/detect_object_boundary')
    '/cam1/watch_object_boundary'
    """
    return rosgraph.names.ns_join(rosgraph.names.namespace(service), 'watch_object_boundary')


def one_shot_request(watch: Watch) -> DetectObjectBoundaryRequest:
    """The DetectObjectBoundary request that serves ``watch`` once, to a vision system without watches."""
    return DetectObjectBoundaryRequest(
        algorithm=watch.algorithm,
        region_of_interest=box_to_msg(watch.region),
        callback_service=watch.callback_service,
        request_id=watch.request_id,
    )


def watch_request(forward: Forward) -> WatchObjectBoundaryRequest:
    """The WatchObjectBoundary forward of ``forward`` (a new watch, a renewal or a withdrawal)."""
    watch = forward.watch
    return WatchObjectBoundaryRequest(
        algorithm=watch.algorithm,
        region_of_interest=box_to_msg(watch.region),
        callback_service=watch.callback_service,
        request_id=watch.request_id,
        period=watch.period,
        duration=forward.duration,
        changes_only=watch.changes_only,
    )


def _watch_message(change: str, request_id: str, serving: int) -> str:
    if change == CANCELLED:
        return f'watch {request_id!r} cancelled'
    if change == NOT_STANDING:
        return f'no watch {request_id!r} stands: nothing to cancel'
    served = '1 vision system serves' if serving == 1 else f'{serving} vision systems serve'
    return f'watch {request_id!r} {change}; {served} it'
