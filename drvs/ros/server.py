"""The DRVS server node's ROS glue: its three services, its topics and background loops, wired
to the server's decisions in :mod:`drvs.server` (registry, dispatch, rate limits, watches,
request and callback checks). What it does, its parameters, topics and logs:
docs/nodes/drvs_server.md.
"""

from __future__ import annotations

import os
import socket
import threading

import rosgraph.names
import rospy
from visualization_msgs.msg import MarkerArray

from drvs.algorithms import AlgorithmSet, default_algorithms
from drvs.common.health import Health, server_health
from drvs.common.rate_limit import RateLimiter
from drvs.common.status import ACCEPTED, BUSY, INVALID, RATE_LIMITED, Refusal, name
from drvs.common.validation import ValidationError, ros_name
from drvs.msg import Registry as RegistryMsg
from drvs.msg import ServerStats
from drvs.ros.conversions import msg_to_box, polygon_to_points, refusal_to_detect_response
from drvs.ros.markers import registry_markers
from drvs.ros.messages import header, registry_to_msg
from drvs.ros.node import NodeScaffold, internal_error, refusal_response
from drvs.ros.server_checks import MasterChecks, caller_of
from drvs.ros.server_forwarding import Forwarder, Outgoing, ReplyFirstService
from drvs.ros.server_fusion import FusedRequests, FusionGlue
from drvs.ros.server_watches import ServerWatches
from drvs.server import answers
from drvs.server.dispatch import Dispatcher
from drvs.server.fusion import FusionSettings, FusionStage
from drvs.server.params import ServerSettings
from drvs.server.registration import Registrar
from drvs.server.registry import REGISTERED, Registration
from drvs.server.request_check import AlgorithmNames, check_supported, rate_limited, request_fields
from drvs.server.shared_registry import SharedRegistry
from drvs.server.sites import remote, requested_callback_uri
from drvs.server.tracker import TrackerSettings
from drvs.server.watch_sharing import WatchSharing, open_registry
from drvs.server.watch_table import WatchTable
from drvs.srv import (
    DetectObjectBoundary,
    DetectObjectBoundaryResponse,
    RegisterVisionService,
    RegisterVisionServiceResponse,
    WatchObjectBoundary,
)

__all__ = ['DrvsServer']

SHARED_SYNC_PERIOD = 0.1
"""Seconds between two looks at a shared registry's change log (renewals and sweeps: their own periods)."""
STATS_PERIOD = 1.0
"""Seconds between two ``~stats`` messages at most."""
THROTTLED = (BUSY, RATE_LIMITED)
"""Refusals for load: logged at most once per :data:`drvs.ros.node.LOG_PERIOD` (per kind of call)."""
STATS_FIELDS = (
    'requests',
    'watch_requests',
    'refused',
    'forwards',
    'watch_forwards',
    'forward_failures',
    'fallback_forwards',
    'watches',
    'fused_requests',
    'fused_callbacks',
    'fused_late',
    'fused_deliveries',
    'fused_failures',
    'fused_untracked',
    'tracks',
)
"""The counters of drvs/ServerStats (``watches``: the number standing)."""


class DrvsServer(ServerWatches, FusedRequests):
    """The server's ROS glue; :meth:`start` creates the services, topics and threads."""

    def __init__(self, settings: ServerSettings):
        self.settings = settings
        self.node = NodeScaffold(self.health, counters=STATS_FIELDS)
        replica = f'{rospy.get_name()}@{socket.gethostname()}:{os.getpid()}'
        self.registry = open_registry(settings, replica)
        self.checks = MasterChecks(
            settings.check_timeout,
            settings.unavailable_retry_after,
            settings.callback_cache,
            settings.callback_memory,
        )
        self.forwarder = Forwarder(
            settings.forward_timeout,
            self.registry,
            self.node.counters,
            self._removed,
            self._undelivered,
            on_refused=self._fused_watch_refused,
            site=settings.site,
            resolve_callback=self.checks.callback,
        )
        self.dispatcher = Dispatcher(
            self.forwarder.send,
            workers=settings.workers,
            max_pending=settings.max_pending,
            max_per_destination=settings.max_pending_per_vision_system,
            retry_after=settings.busy_retry_after,
            begin=self.forwarder.begin,
        )
        stage = FusionStage(
            rospy.get_time,
            self._field_of_view,
            FusionSettings(
                deadline=settings.fused_deadline,
                max_rounds=settings.max_fused_requests,
                busy_retry_after=settings.busy_retry_after,
                tracker=TrackerSettings(coast=settings.track_coast, max_tracks=settings.max_tracks),
            ),
        )
        self.fusion = FusionGlue(
            stage,
            self._submit_delivery,
            self.node.counters,
            settings.forward_timeout,
            settings.objects_period,
        )
        self.forwarder.deliver = self.fusion.deliver
        if isinstance(self.registry, SharedRegistry):
            self.registry.make_client = self.forwarder.make_client
        self.rate_limiter = RateLimiter(settings.max_requests_per_s, settings.burst)
        self.registrar = Registrar(
            self.registry,
            rospy.get_name(),
            self.checks.vision_system,
            self.forwarder.make_client,
            on_change=self._registry_changed,
            on_removed=self._removed,
        )
        self._acknowledgements = answers.SharedReplies()
        self._changed = threading.Condition()  # guards _dirty: the registry changed since last published
        self._dirty = True
        self.watches = WatchTable(
            self.registry,
            rospy.get_time,
            min_period=settings.min_watch_period,
            max_duration=settings.max_watch_duration,
            max_watches=settings.max_watches,
            busy_retry_after=settings.busy_retry_after,
        )
        self._watch_lock = threading.Lock()  # guards watches, and keeps their forwards in order
        self.sharing = (  # the watches kept in a shared registry's database (None: in memory only)
            WatchSharing(
                self.registry, self.watches, self._watch_lock, settings.watch_takeover, rospy.get_time
            )
            if isinstance(self.registry, SharedRegistry)
            else None
        )
        self._watch_wake = threading.Event()  # set when the registry changed or a forward failed
        self._held = threading.local()  # .forwards: queued by this thread's handler, not sent yet
        self.algorithms: AlgorithmSet | None = None  # those the server can check in full; set by start()
        self.algorithm_names: AlgorithmNames | None = None
        self._registry_publisher = self._markers_publisher = self._stats_publisher = None

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> None:
        self.algorithms = default_algorithms()
        self.algorithm_names = AlgorithmNames(self.algorithms)
        self._registry_publisher = rospy.Publisher('~registry', RegistryMsg, queue_size=1, latch=True)
        self._markers_publisher = rospy.Publisher('~markers', MarkerArray, queue_size=1, latch=True)
        self._stats_publisher = rospy.Publisher('~stats', ServerStats, queue_size=1, latch=True)
        self.forwarder.start()
        self.dispatcher.start()
        shared = isinstance(self.registry, SharedRegistry)
        self.node.every(
            SHARED_SYNC_PERIOD if shared else min(self.settings.lease / 4, 0.5), self._expire, 'lease-expiry'
        )
        self.node.spawn(self._publish_loop, 'registry-publisher')
        self.node.spawn(self._watch_loop, 'watches')
        self.node.spawn(self._stats_loop, 'stats-publisher')
        self.fusion.start()
        self.node.spawn(lambda: self.fusion.loop(lambda: self.node.stopped), 'fusion')
        rospy.Service('~register_vision_service', RegisterVisionService, self.handle_register)
        ReplyFirstService(
            '~detect_object_boundary', DetectObjectBoundary, self.handle_detect, self._release_forwards
        )
        rospy.Service('~watch_object_boundary', WatchObjectBoundary, self.handle_watch)
        self.node.start()
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
        self.node.stop()
        self.fusion.stop()
        self._watch_wake.set()
        with self._changed:
            self._changed.notify_all()
        self.dispatcher.stop(timeout=self.settings.forward_timeout + 1.0)
        self.forwarder.stop(timeout=self.settings.forward_timeout + 1.0)
        if isinstance(self.registry, SharedRegistry):  # the entries stay in the database, for the replicas
            for entry in self.registry.entries():
                self._close(entry)
            self.registry.store.close()
            return
        for entry in self.registry.entries():
            self._close(self.registry.unregister(entry.service_name))

    # -- refusals ----------------------------------------------------------------------------
    def _rate_limit(self, request) -> Refusal | None:
        caller = caller_of(request)
        wait = self.rate_limiter.take(caller)
        if wait <= 0:
            return None
        return rate_limited(caller, wait, self.settings.max_requests_per_s, self.settings.burst)

    def _internal_error(self, what: str, error: Exception) -> Refusal:
        return internal_error('the DRVS server', what, error, self.settings.unavailable_retry_after)

    def _refuse_register(self, refusal: Refusal) -> RegisterVisionServiceResponse:
        self.node.refused(refusal)
        log = rospy.logwarn if refusal.status == INVALID else rospy.loginfo
        log('registration refused (%s): %s', name(refusal.status), refusal.message)
        return refusal_response(RegisterVisionServiceResponse, refusal)

    def _log_refusal(self, what: str, request, refusal: Refusal) -> None:
        self.node.refused(refusal)
        self.node.counters.add(refused=1)
        args = (what, request.request_id, caller_of(request) or '?', name(refusal.status), refusal.message)
        if refusal.status in THROTTLED:  # a saturated server refuses thousands a second
            self.node.log_throttled(
                (what, refusal.status), rospy.loginfo, '%s %r from %s refused (%s): %s', *args
            )
        else:
            rospy.loginfo('%s %r from %s refused (%s): %s', *args)

    # -- registration ------------------------------------------------------------------------
    def handle_register(self, request) -> RegisterVisionServiceResponse:
        try:
            return self._register(request, caller_of(request))
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
        points = polygon_to_points(request.field_of_view)
        done = self.registrar.register(service, points, request.algorithms, caller)
        return RegisterVisionServiceResponse(
            accepted=True, status=ACCEPTED, message=done.message, lease=done.lease
        )

    def _registry_changed(self, change: str, service: str) -> None:
        """A vision system registered, moved or changed its algorithms (the registrar's ``on_change``)."""
        if change == REGISTERED:
            with self._watch_lock:  # a restarted vision system holds no watches: forward them again
                self.watches.forget(service)
        self._mark_changed()

    def _close(self, entry: Registration | None) -> None:
        """Drop what the server still holds for a removed entry: queued forwards, its connection."""
        if entry is None:
            return
        dropped = self.dispatcher.drop(entry.service_name)
        if dropped:
            rospy.loginfo('dropped %d queued forwards to %s', dropped, entry.service_name)
        if entry.client is not None:
            entry.client.close()

    def _removed(self, entry: Registration) -> None:
        """A vision system unregistered, or removed after failed forwards."""
        self._close(entry)
        self._forget(entry)
        self._mark_changed()

    def _forget(self, entry: Registration) -> None:
        """The fusion stage drops what it holds of a vision system that left: its tracks coast."""
        with self.fusion.lock:
            self.fusion.stage.forget(entry.service_name)

    def _field_of_view(self, service: str):
        entry = self.registry.get(service)
        return None if entry is None else entry.field_of_view

    def _check_callback(self, request) -> str:
        """Check a request's callback service, unless verified lately (:meth:`MasterChecks.callback`);
        its address on our master. A caller leaves ``callback_uri`` empty (:mod:`drvs.server.sites`)."""
        requested_callback_uri(request.callback_uri)
        return self.checks.callback(request.callback_service)

    def _any_remote(self, names: list[str]) -> bool:
        """Whether one of the vision systems ``names`` is at another site than this server."""
        entries = [self.registry.get(service) for service in names]
        return any(entry is not None and remote(self.settings.site, entry.site) for entry in entries)

    # -- requests ----------------------------------------------------------------------------
    def handle_detect(self, request) -> DetectObjectBoundaryResponse:
        self.node.counters.add(requests=1)
        return self._answer('request', request, self._detect, refusal_to_detect_response)

    def _answer(self, what: str, request, handle, refuse):
        """``handle(request)``, or ``refuse(refusal)`` (logged and counted) when it refuses or fails."""
        try:
            return handle(request)
        except Refusal as caught:
            refusal = caught
        except Exception as error:  # a bug: answer with a status, never rospy's bare error reply
            refusal = self._internal_error(what, error)
        self._log_refusal(what, request, refusal)
        return refuse(refusal)

    def _detect(self, request) -> DetectObjectBoundaryResponse:
        limited = self._rate_limit(request)
        if limited:
            raise limited
        algorithm, region = self._request_fields(request)
        callback_uri = self._check_callback(request)
        names = self.registry.match(region, algorithm)
        if request.fused:
            return self._detect_fused(request, algorithm, region, names)
        if not names:
            return self._sent_to_none(region, algorithm)
        # The request itself is forwarded: every field unchanged (the caller's connection
        # header is not part of the message). They are sent once the reply is out.
        outgoing = Outgoing(request, callback_uri=callback_uri)
        # Raises Busy, or OverShare when the caller holds its fair share of every one of them.
        accepted, skipped = self.dispatcher.submit(names, outgoing, wake=False, caller=caller_of(request))
        self._held.forwards = getattr(self._held, 'forwards', 0) + len(accepted)
        if skipped and accepted:
            self.node.log_throttled(
                'skipped',
                rospy.logwarn,
                'request %s: skipped busy vision systems %s',
                request.request_id,
                skipped,
            )
        if not accepted:
            raise answers.busy_everywhere(
                len(names),
                algorithm,
                self.settings.max_pending_per_vision_system,
                self.settings.busy_retry_after,
            )
        return self._accepted(len(accepted), len(skipped))

    def _accepted(self, forwarded: int, skipped: int) -> DetectObjectBoundaryResponse:
        """The acknowledgement of a request sent to ``forwarded`` vision systems (``skipped`` busy),
        made once and shared (:class:`~drvs.server.answers.SharedReplies`)."""
        return self._acknowledgements.get(
            (forwarded, skipped),
            lambda: DetectObjectBoundaryResponse(
                accepted=True,
                status=ACCEPTED,
                message=answers.forwarded(forwarded, skipped),
                vision_systems=forwarded,
            ),
        )

    def _sent_to_none(self, region, algorithm: str) -> DetectObjectBoundaryResponse:
        """The answer to a valid request that no vision system will get: why none.

        :raises Refusal: ``UNSUPPORTED`` when vision systems are registered and none runs ``algorithm``.
        """
        available = self.registry.available_algorithms()
        check_supported(available, algorithm)
        covered = bool(available) and bool(self.registry.match(region))
        return DetectObjectBoundaryResponse(
            accepted=True, status=ACCEPTED, message=answers.sent_to_none(covered, algorithm), vision_systems=0
        )

    def _release_forwards(self) -> None:
        """After a reply to ``~detect_object_boundary``: send its forwards."""
        held = getattr(self._held, 'forwards', 0)
        if held:
            self._held.forwards = 0
            self.dispatcher.release(held)

    def _request_fields(self, request) -> tuple[str, tuple[float, float, float, float]]:
        """The algorithm's NAME and the region of a request or watch (:func:`request_fields`)."""
        return request_fields(
            self.algorithm_names,
            request.algorithm,
            msg_to_box(request.region_of_interest),
            request.callback_service,
        )

    # -- watches -----------------------------------------------------------------------------
    # -- background loops --------------------------------------------------------------------
    def _expire(self) -> None:
        version = self.registry.version
        for entry in self.registry.sync():
            rospy.loginfo('lease of %s expired: removed', entry.service_name)
            self._close(entry)
            self._forget(entry)
            self._mark_changed()
        if isinstance(self.registry, SharedRegistry):
            for client in self.registry.take_retired():  # an entry of another site at a new address
                client.close()
        if self.sharing is not None and self.sharing.follow():
            self._watch_wake.set()
        if self.registry.version != version:
            self._mark_changed()

    def _mark_changed(self) -> None:
        with self._changed:
            self._dirty = True
            self._changed.notify()
        self._watch_wake.set()

    def stats_msg(self) -> ServerStats | None:
        """The counters (drvs/ServerStats, stamped with ROS time) if they changed since the last call."""
        with self.fusion.lock:
            tracks = self.fusion.stage.track_count()
        self.node.counters.set(watches=len(self.watches), tracks=tracks)
        counts = self.node.counters.take_changed()
        return None if counts is None else ServerStats(header=header(rospy.get_time()), **counts)

    def _stats_loop(self) -> None:
        while True:
            message = self.stats_msg()
            if message is not None:
                self._stats_publisher.publish(message)
            if self.node.wait(STATS_PERIOD):
                return

    def _publish_loop(self) -> None:
        while not self.node.stopped:
            with self._changed:
                while not self._dirty and not self.node.stopped:
                    self._changed.wait()
                self._dirty = False
            if self.node.stopped:
                return
            registry = self.registry_msg()
            self._registry_publisher.publish(registry)
            self._markers_publisher.publish(
                registry_markers(
                    [(e.service_name, polygon_to_points(e.field_of_view)) for e in registry.vision_systems],
                    registry.header.stamp,
                )
            )
            self.node.wait(self.settings.registry_period)

    def health(self) -> Health:
        """The server's health now, for ``/diagnostics``; the refusals counted since the last call."""
        refusals = self.node.refusals
        with self.fusion.lock:
            left_out, tracks = self.fusion.stage.flagged(), self.fusion.stage.track_count()
        recent = refusals.take_period()  # first: the totals then include every recent one
        shared = isinstance(self.registry, SharedRegistry)
        return server_health(
            registry=self.registry.store.where if shared else 'memory',
            registry_problem=self.registry.problem() if shared else None,
            site=self.settings.site,
            registered=len(self.registry),
            pending_forwards=self.dispatcher.pending,
            max_pending=self.settings.max_pending,
            refusals_by_status=refusals.totals(),
            refusals_recent=recent,
            rate_limited_callers=self.rate_limiter.limited(),
            ejected=self.registry.ejected(),
            watches=len(self.watches),
            left_out=left_out,
            tracks=tracks,
        )

    def registry_msg(self) -> RegistryMsg:
        """The registry now, with each lease's expiry in ROS time."""
        return registry_to_msg(self.registry.entries(), rospy.get_time(), self.registry.clock())
