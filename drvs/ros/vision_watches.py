"""A vision system's watches on ROS: the ``~watch_object_boundary`` service and the loop that
evaluates the due watches on one frame each. A part of :class:`drvs.ros.vision_system.VisionSystemNode`,
which it is mixed into; the decisions are in :mod:`drvs.vision.watch_runner`, the contract in
docs/interface.md ("Watches").
"""

from __future__ import annotations

import traceback

import rospy

from drvs.algorithms import AlgorithmError, FrameProblem
from drvs.common.status import ACCEPTED, INVALID, UNAVAILABLE, Refusal
from drvs.common.validation import ValidationError
from drvs.ros.conversions import msg_to_box
from drvs.ros.frame_sources import FrameUnavailable
from drvs.ros.node import refusal_response
from drvs.srv import WatchObjectBoundaryResponse
from drvs.vision.pipeline import in_region, on_floor
from drvs.vision.watch_runner import Terms, parse_watch

__all__ = ['VisionWatches']

WATCH_POLL = 0.05
"""Longest wall-clock sleep of the watch loop: it looks again at the time of the next due watch
(ROS time, which may run slower or faster than the wall under ``/use_sim_time``) and for new watches."""


class VisionWatches:
    """The watch calls and the watch loop of :class:`~drvs.ros.vision_system.VisionSystemNode` (mixed
    into it: they use its frame source, algorithms, watch runner, callbacks and counters)."""

    def _refuse_watch(self, request, refusal: Refusal) -> WatchObjectBoundaryResponse:
        self._log_refusal('watch', request.request_id, refusal)
        return refusal_response(WatchObjectBoundaryResponse, refusal)

    def _handle_watch(self, request) -> WatchObjectBoundaryResponse:
        try:
            return self._watch(request)
        except Exception as error:  # a bug: answer with a status, never rospy's bare error reply
            return self._refuse_watch(request, self._internal_error('a watch', error))

    def _watch(self, request) -> WatchObjectBoundaryResponse:
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
                request.fused,
                request.callback_uri,
            )
            if terms is None:
                key = (request.callback_service, request.request_id, request.callback_uri)
                cancelled = self.watches.cancel(key)
                self._count(watch_calls=1)
                self._note_watches()
                if cancelled:
                    rospy.loginfo('%s: watch %r cancelled', rospy.get_name(), request.request_id)
                return WatchObjectBoundaryResponse(accepted=True, status=ACCEPTED)
            if terms.algorithm.algorithm.streaming:  # as for a request: foreground learns while refused
                self._streaming_until = max(self._streaming_until, now + self.params.motion_window)
            problem = self.source.unavailable() or self._frame_problem(terms.algorithm, now)
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

    def _watch_loop(self) -> None:
        """Sleep until a watch is due, then evaluate every due watch on one frame."""
        while not self.node.wait(self._until_next_watch()):
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
                    self.frame_problems.clear(terms.algorithm.name)
                found = in_region(detected[terms.algorithm.text], terms.region)
            except FrameProblem as error:
                self._note_frame_problem(terms.algorithm, error, f'watch {terms.request_id!r}')
                continue
            except Exception:  # one watch that fails must not stop the others
                rospy.logerr(
                    '%s: watch %r failed:\n%s', rospy.get_name(), terms.request_id, traceback.format_exc()
                )
                continue
            self._count(watch_evaluations=1)
            objects = self.watches.evaluate(terms, found)
            if objects is not None and not self.callbacks.send(
                terms, self.service_name, frame.stamp, objects
            ):
                self.watches.callback_failed(terms)
