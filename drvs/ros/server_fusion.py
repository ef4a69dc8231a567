"""The DRVS server's fusion stage on ROS: the ``~fusion_callback`` service the vision systems call
back for fused requests and watches, the thread that delivers one callback per request or period
to the robots, and the ``~objects`` topic (drvs/TrackedObjects) with its RViz markers
(``~object_markers``). The decisions are in :mod:`drvs.server.fusion` and
:mod:`drvs.server.tracker`; the contract in docs/interface.md ("Fused mode"); why the stage runs
inside the server, and what it costs it: docs/design.md ("Fusion").
"""

from __future__ import annotations

import io
import math
import threading
from collections.abc import Callable

import rospy
from geometry_msgs.msg import Point, Vector3
from visualization_msgs.msg import Marker, MarkerArray

from drvs.common.client_cache import ClosingCache
from drvs.common.counters import Counters
from drvs.msg import DetectedObject, TrackedObjects
from drvs.ros.conversions import bounds_of, box_to_msg, points_to_polygon, polygon_to_points
from drvs.ros.markers import algorithm_colour, outline_marker, text_marker
from drvs.ros.messages import header
from drvs.ros.server_checks import caller_of
from drvs.ros.server_forwarding import Outgoing
from drvs.ros.service_client import ServiceCallError, ServiceClient
from drvs.server import answers
from drvs.server.dispatch import Busy, OverShare
from drvs.server.fusion import Delivery, FusionStage
from drvs.server.tracker import Observation, TrackView
from drvs.server.watch_table import Forward
from drvs.srv import (
    CallbackCoordinates,
    CallbackCoordinatesRequest,
    CallbackCoordinatesResponse,
    DetectObjectBoundaryRequest,
    DetectObjectBoundaryResponse,
)

__all__ = ['FusedRequests', 'FusionGlue', 'detected_object']

LONGEST_WAIT = 0.5
"""Wall-clock seconds the delivery loop waits at most between two looks at the (ROS) clock."""
MAX_CLIENTS = 4096
"""Connections to robots' callback services kept open."""
CLIENT_IDLE = 120.0
"""Seconds an unused connection to a robot's callback service stays open."""
MARKER_LIFETIME = 1.0
"""Seconds a track's markers stay in RViz unless the next ``~objects`` replaces them."""


def detected_object(track: TrackView) -> DetectedObject:
    """A fused track as drvs/DetectedObject: outline, bounds, label and the tracking fields."""
    return DetectedObject(
        boundary=points_to_polygon(track.outline),
        bounding_box=box_to_msg(bounds_of(track.outline)),
        label=track.label,
        track_id=track.track_id,
        confidence=track.confidence,
        velocity=Vector3(track.velocity[0], track.velocity[1], 0.0),
        stationary=track.stationary,
        seen_by=list(track.seen_by),
        height=track.height,
        clearance=track.clearance,
    )


def observations(objects) -> list[Observation]:
    """A callback's drvs/DetectedObject list as the tracker's observations."""
    return [
        Observation(
            tuple(polygon_to_points(o.boundary)),
            label=o.label,
            confidence=float(o.confidence),
            height=float(o.height),
            clearance=float(o.clearance),
        )
        for o in objects
    ]


class FusionGlue:
    """The fusion stage's service, delivery thread and topics.

    :param stage: the fused rounds and watches (guarded here by :attr:`lock`).
    :param submit: queue a :class:`Delivery` for the robot's callback service on the server's
        forwarding workers (raises :class:`~drvs.server.dispatch.Busy` when full).
    :param counters: the server's counters (``fused_callbacks``, ``fused_deliveries``,
        ``fused_failures``, ``fused_late``, ``fused_untracked``).
    :param timeout: limit on one delivery (connect, send, reply), seconds.
    :param objects_period: least time between two ``~objects`` messages, seconds.
    """

    def __init__(
        self,
        stage: FusionStage,
        submit: Callable[[str, Delivery], bool],
        counters: Counters,
        timeout: float,
        objects_period: float,
    ):
        self.stage = stage
        self.lock = threading.Lock()
        self.wake = threading.Event()
        self._submit = submit
        self.counters = counters
        self.objects_period = objects_period
        self._clients = ClosingCache(
            lambda service: ServiceClient(service, CallbackCoordinates, timeout, caller_id=rospy.get_name()),
            MAX_CLIENTS,
            CLIENT_IDLE,
        )
        self._objects_pub: rospy.Publisher | None = None
        self._markers_pub: rospy.Publisher | None = None
        self._objects_changed = False
        self._shown: set[tuple[str, int]] = set()  # marker (namespace, id) pairs now in RViz
        self.service_name = ''

    def start(self) -> None:
        self._objects_pub = rospy.Publisher('~objects', TrackedObjects, queue_size=2, latch=True)
        self._markers_pub = rospy.Publisher('~object_markers', MarkerArray, queue_size=2)
        service = rospy.Service('~fusion_callback', CallbackCoordinates, self.handle_callback)
        self.service_name = service.resolved_name

    def stop(self) -> None:
        self.wake.set()
        self._clients.clear()

    # -- the vision systems' callbacks ---------------------------------------------------------------
    def handle_callback(self, request: CallbackCoordinatesRequest) -> CallbackCoordinatesResponse:
        """A vision system's answer to a fused forward: fused into the tracks; never refused (a frame
        for a round already answered still feeds the tracks)."""
        found = observations(request.objects)
        with self.lock:
            untracked = self.stage.untracked
            known = self.stage.callback(
                request.request_id, request.vision_system, request.stamp.to_sec(), request.algorithm, found
            )
            untracked = self.stage.untracked - untracked
            self._objects_changed = True
        self.counters.add(fused_callbacks=1, fused_late=0 if known else 1, fused_untracked=untracked)
        self.wake.set()
        return CallbackCoordinatesResponse()

    # -- deliveries ----------------------------------------------------------------------------------
    def loop(self, stopped: Callable[[], bool]) -> None:
        """Deliver what the stage owes, when it owes it; publish ``~objects`` at most every period."""
        published = -math.inf
        while not stopped():
            self.wake.clear()
            with self.lock:
                deliveries = self.stage.due()
                due = self.stage.next_due()
            for delivery in deliveries:
                if not self._submit(delivery.callback_service, delivery):
                    self.counters.add(fused_failures=1)
                    rospy.logwarn(
                        'fused callback %r to %s not sent: too many forwards pending',
                        delivery.request_id,
                        delivery.callback_service,
                    )
            now = rospy.get_time()
            if self._objects_changed and now - published >= self.objects_period:
                self._publish_objects(now)
                published = now
            self._clients.expire()
            waits = [LONGEST_WAIT, self.objects_period if self._objects_changed else LONGEST_WAIT]
            if due is not None:
                waits.append(max(due - now, 0.001))
            self.wake.wait(min(waits))

    def deliver(self, delivery: Delivery) -> None:
        """Call the robot back with ``delivery`` (on a forwarding worker); a failure is logged and counted."""
        request = CallbackCoordinatesRequest(
            algorithm=delivery.algorithm,
            request_id=delivery.request_id,
            vision_system=rospy.get_name(),
            stamp=rospy.Time.from_sec(max(delivery.stamp, 0.0)),
            objects=[detected_object(track) for track in delivery.objects],
            fused=True,
            status=delivery.status,
            message=delivery.message,
            answered=list(delivery.answered),
            refused=list(delivery.refused),
            missing=list(delivery.missing),
            gone=list(delivery.gone),
        )
        buffer = io.BytesIO()
        request.serialize(buffer)
        try:
            self._clients.get(delivery.callback_service).call(request, serialized=buffer.getvalue())
        except ServiceCallError as error:
            self.counters.add(fused_failures=1)
            rospy.logwarn(
                'fused callback %r to %s failed: %s', delivery.request_id, delivery.callback_service, error
            )
            return
        self.counters.add(fused_deliveries=1)

    # -- the world model -----------------------------------------------------------------------------
    def _publish_objects(self, now: float) -> None:
        with self.lock:
            tracks = self.stage.tracks(now)
            self._objects_changed = False
        stamp = rospy.Time.from_sec(now)
        message = TrackedObjects(header=header(now))
        message.algorithms = [algorithm for algorithm, _ in tracks]
        message.objects = [detected_object(track) for _, track in tracks]
        self._objects_pub.publish(message)
        if self._markers_pub.get_num_connections() > 0:
            self._markers_pub.publish(self._markers(tracks, stamp))

    def _markers(self, tracks, stamp) -> MarkerArray:
        """Each track's outline, its id (and speed) as text, and an arrow for its velocity; the
        markers of tracks that ended are deleted."""
        markers, shown = [], set()
        for algorithm, track in tracks:
            colour = algorithm_colour(algorithm)
            x, y = track.position
            vx, vy = track.velocity
            speed = math.hypot(vx, vy)
            text = f'#{track.track_id}' + ('' if track.stationary else f' {speed:.2f} m/s')
            for namespace, marker in (
                ('tracks', outline_marker('tracks', track.track_id, track.outline, colour, stamp, z=0.03)),
                ('track_ids', text_marker('track_ids', track.track_id, text, (x, y), colour, stamp)),
                ('track_velocities', _arrow(track.track_id, (x, y), (vx, vy), colour, stamp)),
            ):
                marker.lifetime = rospy.Duration(MARKER_LIFETIME)
                markers.append(marker)
                shown.add((namespace, track.track_id))
        for namespace, marker_id in sorted(self._shown - shown):
            gone = Marker(ns=namespace, id=marker_id, action=Marker.DELETE)
            gone.header.frame_id = 'map'
            markers.append(gone)
        self._shown = shown
        return MarkerArray(markers=markers)


def _arrow(marker_id: int, position, velocity, colour, stamp) -> Marker:
    """An ARROW from the track's centre to where it will be in one second."""
    marker = Marker(ns='track_velocities', id=marker_id, type=Marker.ARROW, action=Marker.ADD)
    marker.header.frame_id = 'map'
    marker.header.stamp = stamp
    marker.pose.orientation.w = 1.0
    marker.scale.x, marker.scale.y, marker.scale.z = 0.04, 0.08, 0.1
    r, g, b, a = colour
    marker.color.r, marker.color.g, marker.color.b, marker.color.a = r, g, b, a
    x, y = position
    marker.points = [Point(x, y, 0.05), Point(x + velocity[0], y + velocity[1], 0.05)]
    return marker


class FusedRequests:
    """The fused one-shot requests of :class:`~drvs.ros.server.DrvsServer` (mixed into it: they use its
    registry, dispatcher, checks and :class:`FusionGlue`): a round of the fusion stage, forwarded
    with the stage's callback service, and the deliveries and refusals the stage hears of."""

    def _detect_fused(
        self, request, algorithm: str, region, names: list[str]
    ) -> DetectObjectBoundaryResponse:
        """A fused request: a round of the fusion stage, forwarded with its callback service and id;
        the robot is called back once, by the fusion stage (docs/interface.md, "Fused mode")."""
        answer = self._sent_to_none(region, algorithm) if not names else None  # may refuse UNSUPPORTED
        stage = self.fusion.stage
        with self.fusion.lock:
            wire_id = stage.open_round(
                caller_of(request),
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
                names, Outgoing(forward, settled, fusion_uri), wake=False, caller=caller_of(request)
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
