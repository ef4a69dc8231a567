"""The DRVS server's watches on ROS: the ``~watch_object_boundary`` service and the loop that keeps
the standing watches' forwards going (renewals, one-shots when due, what the registry's changes
ask for). A part of :class:`drvs.ros.server.DrvsServer`, which it is mixed into: the decisions are
in :mod:`drvs.server.watch_table` (and :mod:`drvs.server.watch_sharing` with a database); the
contract in docs/interface.md ("Watches"), the design in docs/design.md ("Watches: the server's
side").
"""

from __future__ import annotations

import rospy

from drvs.common.status import ACCEPTED, INVALID, Refusal
from drvs.common.validation import ValidationError, watch_terms
from drvs.ros.node import refusal_response
from drvs.ros.server_checks import caller_of
from drvs.ros.server_forwarding import watch_service_of
from drvs.server import answers
from drvs.server.dispatch import Busy
from drvs.server.request_check import check_supported
from drvs.server.watch_table import ONE_SHOT, Forward
from drvs.srv import WatchObjectBoundaryResponse

__all__ = ['ServerWatches']

WATCH_WAIT = 0.5
"""Longest wall-clock wait of the watch loop between two looks at the clock (ROS time may run faster)."""


class ServerWatches:
    """The watch calls and the watch loop of :class:`~drvs.ros.server.DrvsServer` (mixed into it:
    they use its registry, dispatcher, fusion glue, watch table and locks)."""

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
        caller = caller_of(request)
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

    # -- background loop ----------------------------------------------------------------------
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
