"""The vision_system node: one camera serving DetectObjectBoundary and WatchObjectBoundary.

ROS glue only: frames come from :mod:`drvs.ros.frame_sources` (or :mod:`drvs.ros.render_source`,
the simulation's own rendering), registration is decided by :mod:`drvs.vision.registration`,
watches by :mod:`drvs.vision.watch_runner`. Parameters, topics, services and behaviour are in
docs/nodes/vision_system.md.
"""

from __future__ import annotations

import functools
import math
import queue
import threading
import time
import traceback
from types import SimpleNamespace

import numpy as np
import rospy
from sensor_msgs.msg import Image

from drvs.algorithms import AlgorithmError, FrameProblem, Parsed, load_algorithms
from drvs.algorithms.foreground import read_reference
from drvs.common.counters import PeriodCounts
from drvs.common.failover import ServerList
from drvs.common.health import Health, vision_system_health
from drvs.common.settings import ParamError
from drvs.common.status import ACCEPTED, BUSY, INVALID, UNAVAILABLE, Refusal, is_temporary
from drvs.common.status import name as status_name
from drvs.common.validation import ValidationError, request_fields, rosrpc_uri
from drvs.msg import VisionSystemStats
from drvs.ros.callback_sender import CallbackSender
from drvs.ros.conversions import msg_to_box, points_to_polygon
from drvs.ros.frame_sources import FrameUnavailable, TopicSource
from drvs.ros.markers import markers_topic
from drvs.ros.messages import STATS_COUNTERS, stats_to_msg
from drvs.ros.node import NodeScaffold, debug_logged, internal_error, refusal_response
from drvs.ros.service_client import ServiceCallError, ServiceClient
from drvs.ros.vision_watches import VisionWatches
from drvs.srv import (
    DetectObjectBoundary,
    DetectObjectBoundaryResponse,
    RegisterVisionService,
    RegisterVisionServiceRequest,
    WatchObjectBoundary,
)
from drvs.vision.detections import FrameDetections, Job
from drvs.vision.frame import Frame
from drvs.vision.frame_problems import FrameProblems, depth_problem
from drvs.vision.params import VisionSystemParams
from drvs.vision.pipeline import draw_detections, in_region
from drvs.vision.registration import RENEW, UNREGISTER, Attempt, Registration
from drvs.vision.watch_runner import WatchRunner

__all__ = ['VisionSystemNode']

MAX_ALGORITHMS_COUNTED = 64
"""Distinct algorithm strings counted in ``~stats``; callers choose them, so the count is capped."""

POSE_RATE = 10.0
"""Times per second a camera on a moving mount (``render``) puts its pose on tf."""

STATS_PERIOD = 0.5
"""Least wall-clock seconds between two ``~stats`` messages: a busy camera counts hundreds of
events a second, and every subscriber (the scenario recorder) would receive each one."""

REGISTRATION_PERIOD = 0.05
"""Wall-clock seconds between two looks at the field of view (:class:`Registration` decides)."""

ACCEPTED_REPLY = DetectObjectBoundaryResponse(accepted=True, status=ACCEPTED, message='', vision_systems=1)
"""The answer to every accepted request (rospy only serialises it: one is shared)."""


class VisionSystemNode(VisionWatches):
    """One camera serving DetectObjectBoundary; :meth:`start` does the work, :meth:`stop` undoes it."""

    def __init__(self, params: VisionSystemParams):
        self.params = params
        self.node = NodeScaffold(self.health, STATS_COUNTERS, hardware_id=params.camera)
        if params.source == 'render':
            from drvs.ros.render_source import RenderSource  # pybullet: only for the simulation's rendering

            self.source = RenderSource(params, self._count)
        else:
            self.source = TopicSource(params, self._count)
        reference = None
        if params.reference:
            try:
                reference = read_reference(params.reference)
            except ValueError as error:
                raise ParamError('reference', str(error)) from None
        self.algorithms = load_algorithms(
            params.min_area,
            params.epsilon,
            params.tag_height,
            self.source.tag_heights(),
            depth=self.source.depth,
            reference=reference,
            fixed=not self.source.moving,
        )
        self.frame_problems = FrameProblems()  # why an algorithm cannot use the frames now
        # Requests: the algorithm strings that parsed lately, parsed again only when new (as parse()).
        self._parsed_algorithms = SimpleNamespace(
            parse=functools.lru_cache(maxsize=MAX_ALGORITHMS_COUNTED)(self.algorithms.parse)
        )
        self._streaming = [a for a in self.algorithms.by_name.values() if a.streaming]
        self._streaming_until = -1.0  # motion: observe the stream until then (rospy time)
        self.service_name = ''
        self.requests_by_algorithm = PeriodCounts(MAX_ALGORITHMS_COUNTED)  # accepted, in ~stats
        self._stats_lock = threading.Lock()  # guards _stats_published
        self._stats_published = -math.inf  # time.monotonic() of the last ~stats message
        self.callbacks = CallbackSender(
            self._count, params.callback_timeout, params.max_callback_clients, params.callback_idle
        )
        self._jobs: queue.Queue = queue.Queue(maxsize=params.queue_size)
        self._detections = FrameDetections()
        self.watches = WatchRunner(
            params.min_watch_period, params.max_watch_duration, params.change_tolerance, params.max_watches
        )
        self.registration = Registration(params.move_threshold, params.retry_period)
        # Guarded by the registration thread.
        self.servers = ServerList(params.register_services, return_after=params.server_return)
        self._register_clients: dict[str, ServiceClient] = {}

    # -- lifecycle -----------------------------------------------------------------------------
    def start(self) -> None:
        self.stats_pub = rospy.Publisher('~stats', VisionSystemStats, queue_size=1, latch=True)
        self.debug_pub = rospy.Publisher('~debug_image', Image, queue_size=1)
        self.callbacks.start(markers_topic(rospy.resolve_name(self.servers.current)))
        self.source.start()
        foreground = self.algorithms.get('foreground')
        if foreground is not None and not self.params.reference and hasattr(self.source, 'empty_floor'):
            foreground.set_reference(self.source.empty_floor())  # the simulation knows its empty floor
        for index in range(self.params.workers):
            self.node.spawn(self._work, f'worker{index}')
        service = rospy.Service('~detect_object_boundary', DetectObjectBoundary, self._handle_detect)
        self.service_name = service.resolved_name
        self.node.spawn(self._watch_loop, 'watches')
        rospy.Service('~watch_object_boundary', WatchObjectBoundary, self._handle_watch)
        self.node.every(REGISTRATION_PERIOD, self._registration_tick, 'registration')  # service advertised
        if self.params.debug_rate > 0:
            self.node.every(1.0 / self.params.debug_rate, self._debug_tick, 'debug')
        if self._streaming:
            self.node.every(1.0 / self.params.motion_rate, self._stream_tick, 'stream')
        if self.source.moving:
            self.node.every(1.0 / POSE_RATE, self.source.broadcast_pose, 'camera pose')
        rospy.on_shutdown(self.stop)
        self._publish_stats()
        self.node.start()
        rospy.loginfo('%s: %s; serving %s', rospy.get_name(), self.source.describe(), self.service_name)

    def stop(self) -> None:
        """Stop the workers, unregister from the server, release the frame source."""
        if self.node.stopped:
            return
        self.node.stop()
        for _ in range(self.params.workers):
            try:
                self._jobs.put_nowait(None)
            except queue.Full:
                break
        self.node.join(self.params.callback_timeout + 1.0)
        farewell = self.registration.farewell()
        if farewell is not None:
            self._register(farewell)
        try:
            self._publish_stats()  # the final counts
        except rospy.ROSException as error:  # publishing after shutdown
            rospy.logdebug('could not publish the final stats: %s', error)
        for client in self._register_clients.values():
            client.close()
        self.callbacks.close()
        self.source.close()

    # -- requests ------------------------------------------------------------------------------
    def _handle_detect(self, request) -> DetectObjectBoundaryResponse:
        try:
            return self._detect(request)
        except Exception as error:  # a bug: answer with a status, never rospy's bare error reply
            return self._refuse(request, self._internal_error('a request', error))

    def _detect(self, request) -> DetectObjectBoundaryResponse:
        arrival = rospy.get_time()
        self._count(requests=1)
        try:
            algorithm, region = request_fields(
                request.algorithm,
                msg_to_box(request.region_of_interest),
                request.callback_service,
                self._parsed_algorithms,
            )
            if request.callback_uri:
                rosrpc_uri('callback_uri', request.callback_uri)
        except (AlgorithmError, ValidationError) as error:
            return self._refuse(request, Refusal(INVALID, str(error)))
        problem = self.source.unavailable()
        if problem:
            return self._refuse(request, Refusal(UNAVAILABLE, problem, self.params.retry_period))
        if algorithm.algorithm.streaming:  # also while refused below: foreground learns its reference
            self._streaming_until = arrival + self.params.motion_window
        problem = self._frame_problem(algorithm, arrival)
        if problem:
            return self._refuse(request, Refusal(UNAVAILABLE, problem, self.params.retry_period))
        self._count_algorithm(request.algorithm)
        job = Job(
            algorithm,
            region,
            request.callback_service,
            request.request_id,
            arrival,
            request.fused,
            request.callback_uri,
        )
        try:
            self._jobs.put_nowait(job)
        except queue.Full:
            refusal = Refusal(
                BUSY,
                f'busy: {self.params.queue_size} requests are waiting already; try again later',
                self.params.max_frame_age or 0.1,
            )
            return self._refuse(request, refusal)
        if debug_logged():
            rospy.logdebug(
                '%s: accepted request %r (%s)', rospy.get_name(), request.request_id, request.algorithm
            )
        return ACCEPTED_REPLY

    def _refuse(self, request, refusal: Refusal) -> DetectObjectBoundaryResponse:
        self._count(refused=1)
        self._log_refusal('request', request.request_id, refusal)
        return refusal_response(DetectObjectBoundaryResponse, refusal, vision_systems=0)

    def _log_refusal(self, what: str, request_id: str, refusal: Refusal) -> None:
        """One line per refusal, at most one a second per kind (a flood of BUSY says it once)."""
        status = status_name(refusal.status)
        self.node.log_throttled(
            (what, status),
            rospy.loginfo,
            '%s: refused %s %r (%s): %s',
            rospy.get_name(),
            what,
            request_id,
            status,
            refusal.message,
        )

    def _internal_error(self, what: str, error: Exception) -> Refusal:
        return internal_error(f'vision system {rospy.get_name()}', what, error, self.params.retry_period)

    def _work(self) -> None:
        while not self.node.stopped:
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
        try:
            found = in_region(self._detections.on_floor(frame, job.algorithm), job.region)
        except FrameProblem as error:
            self._note_frame_problem(job.algorithm, error, f'request {job.request_id!r}')
            return
        self.frame_problems.clear(job.algorithm.name)
        outlines = [outline for outline, *_ in found]
        if self.debug_pub.get_num_connections() > 0:
            self._publish_debug(frame, outlines)
        if debug_logged():
            rospy.logdebug(
                '%s: request %r: %d object(s)%s',
                rospy.get_name(),
                job.request_id,
                len(outlines),
                ' (cached frame)' if reused else '',
            )
        if found or job.fused:  # the fusion stage hears "nothing here" too: its round need not wait
            self.callbacks.send(job, self.service_name, frame.stamp, found)

    def _stream_tick(self) -> None:
        """While motion requests come (``~motion_window``), feed the algorithms with memory the
        camera's frames (at ``~motion_rate``), so their background model follows the scene."""
        if rospy.get_time() > self._streaming_until:
            return
        try:
            frame, _ = self.source.frame(rospy.get_time())
        except FrameUnavailable:
            return
        for algorithm in self._streaming:
            algorithm.observe(frame)

    def _frame_problem(self, algorithm: Parsed, now: float) -> str | None:
        return self.frame_problems.why(algorithm, self.source.latest, lambda: self.source.depth_problem, now)

    def _note_frame_problem(self, algorithm: Parsed, error: FrameProblem, what: str) -> None:
        problem = depth_problem(algorithm, self.source.depth_problem) or str(error)
        self.frame_problems.note(algorithm.name, problem, rospy.get_time())
        self.node.log_throttled(
            ('frame problem', algorithm.name),
            rospy.logwarn,
            '%s: %s not served: %s',
            rospy.get_name(),
            what,
            problem,
        )

    # -- registration --------------------------------------------------------------------------
    def _registration_tick(self) -> None:
        self.callbacks.expire()  # close idle callback connections even when no request comes
        self._publish_stats(at_most_every=STATS_PERIOD)  # counts that came too soon after the last
        attempt = self.registration.due(self.source.footprint())
        if attempt is not None:
            self._register(attempt)

    def _register(self, attempt: Attempt) -> None:
        """Make ``attempt``'s call to the server and tell :attr:`registration` its answer."""
        request = RegisterVisionServiceRequest(
            service_name=self.service_name,
            field_of_view=points_to_polygon(attempt.footprint),
            algorithms=self.algorithms.names(),
        )
        what = attempt.what
        server = self.servers.to_ask()
        client = self._register_clients.get(server)
        if client is None:
            client = ServiceClient(server, RegisterVisionService, timeout=self.params.register_timeout)
            self._register_clients[server] = client
        try:
            response = client.call(request)
        except ServiceCallError as error:
            rospy.logwarn_throttle(10.0, '%s: waiting for the DRVS server (%s)', rospy.get_name(), error)
            self.registration.unanswered(attempt, str(error))
            self._heard(server, None, str(error))
            return
        self._heard(server, response.status, response.message)
        if response.status != ACCEPTED:
            self.registration.refused(attempt, response.status, response.message, response.retry_after)
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
            else:
                rospy.logerr('%s: %s refused: %s', rospy.get_name(), what, response.message)
            return
        self.registration.accepted(attempt, response.lease)
        lease = self.registration.lease
        if what == UNREGISTER:
            rospy.loginfo('%s: unregistered %s', rospy.get_name(), self.service_name)
        elif what != RENEW:
            rospy.loginfo(
                '%s: %s %s with field of view %s (lease %s s)',
                rospy.get_name(),
                what,
                self.service_name,
                [(round(x, 3), round(y, 3)) for x, y in attempt.footprint],
                f'{lease:g}' if lease else '-',
            )
        self._count(registrations=1)

    def _heard(self, server: str, status: int | None, why: str) -> None:
        """A registration call to ``server`` ended (no answer: ``status`` None): on ``UNAVAILABLE`` or no
        answer the next one goes to the next server (which registers this vision system anew if it
        does not know it: every call carries it all)."""
        heard = self.servers.heard(server, status, why)
        if heard.line:
            (rospy.logwarn if heard.warning else rospy.loginfo)('%s: %s', rospy.get_name(), heard.line)

    # -- introspection -------------------------------------------------------------------------
    def health(self) -> Health:
        """The node's health now, for ``/diagnostics``; the callbacks counted since the last call."""
        callbacks = self.callbacks.period.take_period()
        registration = self.registration.report()
        return vision_system_health(
            registered=registration.registered,
            source=self.params.source,
            frame_age=self.source.frame_age(),
            stale_after=self.params.stale_after,
            queue_length=self._jobs.qsize(),
            queue_size=self.params.queue_size,
            watches=len(self.watches),
            callback_failures_recent=callbacks.get('failed', 0),
            callbacks_recent=callbacks.get('attempted', 0),
            registration_status=registration.status,
            registration_error=registration.error,
            server=self.servers.current,
            server_moves=self.servers.moves,
            frame_problems=[
                *([self.source.pose_problem] if self.source.pose_problem else []),
                *([f'depth left out: {self.source.depth_problem}'] if self.source.depth_problem else []),
                *self.frame_problems.messages(rospy.get_time()),
            ],
        )

    def _count(self, **increments: int) -> None:
        self.node.counters.add(**increments)
        self._publish_stats(at_most_every=STATS_PERIOD)

    def _note_watches(self) -> None:
        """``watches`` in ``~stats``: the watches standing now (published when it changes)."""
        if self.node.counters.set(watches=len(self.watches)):
            self._publish_stats(at_most_every=STATS_PERIOD)

    def _count_algorithm(self, algorithm: str) -> None:
        self.requests_by_algorithm.add(algorithm)  # beyond MAX_ALGORITHMS_COUNTED strings: 'other'
        self.node.counters.add()  # nothing more counted, but ~stats changed

    def _publish_stats(self, at_most_every: float = 0.0) -> None:
        """Publish ``~stats`` if they changed, unless the last message is younger than
        ``at_most_every`` wall seconds (the registration loop publishes what is left)."""
        with self._stats_lock:
            now = time.monotonic()
            if now - self._stats_published < at_most_every:
                return
            counts = self.node.counters.take_changed()
            if counts is None:
                return
            self._stats_published = now
        self.stats_pub.publish(stats_to_msg(counts, self.requests_by_algorithm.totals(), rospy.get_time()))

    def _debug_tick(self) -> None:
        if self.debug_pub.get_num_connections() > 0:
            try:
                frame = self.source.newest()
            except FrameUnavailable:
                return
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
