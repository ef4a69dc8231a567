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
from drvs.common.validation import ValidationError, ros_name, watch_terms
from drvs.msg import Registry as RegistryMsg
from drvs.msg import ServerStats
from drvs.ros.conversions import msg_to_box, polygon_to_points, refusal_to_detect_response
from drvs.ros.markers import registry_markers
from drvs.ros.messages import header, registry_to_msg
from drvs.ros.node import NodeScaffold, internal_error, refusal_response
from drvs.ros.server_checks import MasterChecks
from drvs.ros.server_forwarding import Forwarder, Outgoing, ReplyFirstService, watch_service_of
from drvs.ros.server_fusion import FusionGlue
from drvs.server import answers
from drvs.server.dispatch import Busy, Dispatcher, OverShare
from drvs.server.fusion import Delivery, FusionSettings, FusionStage
from drvs.server.params import ServerSettings
from drvs.server.registration import Registrar
from drvs.server.registry import REGISTERED, Registration
from drvs.server.request_check import AlgorithmNames, check_supported, rate_limited, request_fields
from drvs.server.shared_registry import SharedRegistry
from drvs.server.sites import remote, requested_callback_uri
from drvs.server.tracker import TrackerSettings
from drvs.server.watch_sharing import WatchSharing, open_registry
from drvs.server.watch_table import ONE_SHOT, Forward, WatchTable
from drvs.srv import (
    DetectObjectBoundary,
    DetectObjectBoundaryRequest,
    DetectObjectBoundaryResponse,
    RegisterVisionService,
    RegisterVisionServiceResponse,
    WatchObjectBoundary,
    WatchObjectBoundaryResponse,
)

__all__ = ['DrvsServer']

SHARED_SYNC_PERIOD = 0.1
"""Seconds between two looks at a shared registry's change log (renewals and sweeps: their own periods)."""
WATCH_WAIT = 0.5
"""Longest wall-clock wait of the watch loop between two looks at the clock (ROS time may run faster)."""
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


def _caller(request) -> str:
    return request._connection_header.get('callerid', '')


class DrvsServer:
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
        caller = _caller(request)
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
        args = (what, request.request_id, _caller(request) or '?', name(refusal.status), refusal.message)
        if refusal.status in THROTTLED:  # a saturated server refuses thousands a second
            self.node.log_throttled(
                (what, refusal.status), rospy.loginfo, '%s %r from %s refused (%s): %s', *args
            )
        else:
            rospy.loginfo('%s %r from %s refused (%s): %s', *args)

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
        accepted, skipped = self.dispatcher.submit(names, outgoing, wake=False, caller=_caller(request))
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

    def _detect_fused(
        self, request, algorithm: str, region, names: list[str]
    ) -> DetectObjectBoundaryResponse:
        """A fused request: a round of the fusion stage, forwarded with its callback service and id;
        the robot is called back once, by the fusion stage (docs/interface.md, "Fused mode")."""
        answer = self._sent_to_none(region, algorithm) if not names else None  # may refuse UNSUPPORTED
        stage = self.fusion.stage
        with self.fusion.lock:
            wire_id = stage.open_round(
                _caller(request),
                request.request_id,
                request.algorithm,
                region,
                request.callback_service,
                names,
            )
        self.node.counters.add(fused_requests=1)
        if answer is not None:
            self.fusion.wake.set()  # answered at once: no vision system covers the region
            return answer
        forward = DetectObjectBoundaryRequest(
            algorithm=request.algorithm,
            region_of_interest=request.region_of_interest,
            callback_service=self.fusion.service_name,
            request_id=wire_id,
            fused=True,  # the vision system calls back even when it finds nothing
        )
        # A vision system at another site calls our fusion service at its address on our master.
        fusion_uri = self.checks.callback(self.fusion.service_name) if self._any_remote(names) else ''

        def settled(vision_system: str, reply) -> None:
            with self.fusion.lock:
                if reply is None:
                    stage.forward_answer(wire_id, vision_system, None)
                else:
                    stage.forward_answer(wire_id, vision_system, reply.status, reply.message)
            self.fusion.wake.set()

        try:
            accepted, skipped = self.dispatcher.submit(
                names, Outgoing(forward, settled, fusion_uri), wake=False, caller=_caller(request)
            )
        except (Busy, OverShare):
            with self.fusion.lock:
                stage.cancel_round(wire_id)
            raise
        if not accepted:
            with self.fusion.lock:
                stage.cancel_round(wire_id)
            raise answers.busy_everywhere(
                len(names),
                algorithm,
                self.settings.max_pending_per_vision_system,
                self.settings.busy_retry_after,
            )
        with self.fusion.lock:
            for vision_system in skipped:
                stage.forward_answer(wire_id, vision_system, None)
        self._held.forwards = getattr(self._held, 'forwards', 0) + len(accepted)
        return self._accepted(len(accepted), len(skipped))

    def _submit_delivery(self, callback_service: str, delivery: Delivery) -> bool:
        """Queue a fused callback for a robot on the forwarding workers; False when there is no room."""
        try:
            accepted, _ = self.dispatcher.submit([callback_service], delivery)
        except Busy:
            return False
        return bool(accepted)

    def _fused_watch_refused(self, forward: Forward, answer) -> None:
        """A vision system refused a fused watch's forward: the robot hears of it in its next callback."""
        _, wire_id = forward.watch.forwarded()
        with self.fusion.lock:
            self.fusion.stage.watch_refused(wire_id, forward.vision_system, answer.status, answer.message)

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
    def handle_watch(self, request) -> WatchObjectBoundaryResponse:
        self.node.counters.add(watch_requests=1)
        return self._answer('watch call', request, self._watch, self._refuse_watch)

    @staticmethod
    def _refuse_watch(refusal: Refusal) -> WatchObjectBoundaryResponse:
        return refusal_response(WatchObjectBoundaryResponse, refusal)

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
        key = (caller, request.request_id)
        forward_as = None
        if stands:
            self._check_callback(request)
            with self._watch_lock:
                standing = self.watches.get((caller, request.request_id))
            if standing is None or standing.algorithm_name != algorithm:
                # A renewal with the same algorithm is never UNSUPPORTED: the watch stands for the
                # vision systems that will come, as it did when the last one running it left.
                check_supported(self.registry.available_algorithms(), algorithm)
        with self._watch_lock:
            # The fusion stage's watch and the table's change together (the watch loop keeps the
            # stage's watches that the table has, under both locks).
            with self.fusion.lock:
                if stands and request.fused:
                    period = max(request.period, self.settings.min_watch_period)
                    wire_id = self.fusion.stage.set_watch(
                        key, request.algorithm, region, request.callback_service, period, request.changes_only
                    )
                    forward_as = (self.fusion.service_name, wire_id)
                else:
                    self.fusion.stage.drop_watch(key)
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
                    forward_as,
                )
            except ValidationError as error:
                raise Refusal(INVALID, str(error)) from None
            self._submit(answer.forwards)
            serving = len(self.watches.serving((caller, request.request_id)))
            standing = self.watches.get((caller, request.request_id))
        if self.sharing is not None:
            if standing is not None:
                self.sharing.save(standing)
            else:
                self.sharing.drop(caller, request.request_id)
        return WatchObjectBoundaryResponse(
            accepted=True,
            status=ACCEPTED,
            message=answers.watch_answer(answer.change, request.request_id, serving),
            vision_systems=serving,
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

    def _undelivered(self, forward: Forward) -> None:
        """A watch forward that failed (the forwarder's ``on_undelivered``): sent again later."""
        with self._watch_lock:
            self.watches.undelivered(forward)
        self._watch_wake.set()

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

    def _watch_loop(self) -> None:
        """Follow the registry's changes, expire watches, send one-shots when due (ROS time)."""
        while not self.node.stopped:
            self._watch_wake.clear()
            with self._watch_lock:
                self._submit(self.watches.sync())
                due = self.watches.next_due()
                fused = {w.key: self.watches.serving(w.key) for w in self.watches.standing() if w.forward_as}
                with self.fusion.lock:
                    self.fusion.stage.keep_watches(fused)
            self.forwarder.watch_clients.expire()
            wait = WATCH_WAIT if due is None else min(max(due - rospy.get_time(), 0.001), WATCH_WAIT)
            self._watch_wake.wait(wait)

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
