"""The fusion stage's bookkeeping: fused requests and watches, the answers they wait for, and
the one callback each owes its robot.

A fused request becomes a *round*: it is forwarded to the vision systems that cover its region
with the server's own callback service and a request id of the round's (:meth:`FusionStage.open_round`);
their frames go to the tracker of the request's algorithm (:mod:`drvs.server.tracker`), their
refusals and failures are noted, and once every vision system asked has answered (or the
deadline has passed) the round owes its robot exactly one :class:`Delivery`. A fused watch owes
one every period. No ROS here; the clock is injected; not thread-safe (the server holds one
lock). The contract: docs/interface.md ("Fused mode"); the design: docs/design.md ("Fusion").
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field

from shapely.geometry import Polygon, box

from drvs.common.status import BUSY, INVALID, UNAVAILABLE, UNSUPPORTED, Refusal, name
from drvs.server.tracker import Observation, Tracker, TrackerSettings, TrackView

__all__ = ['OK', 'Delivery', 'FusionSettings', 'FusionStage']

OK = 0
"""The status of a delivery with what the vision systems found (CallbackCoordinates.OK)."""
REFUSAL_STATUSES = (INVALID, UNSUPPORTED)
"""Refusals a delivery passes on as its status when every vision system asked refused."""
Box = tuple[float, float, float, float]
Point = tuple[float, float]
Key = tuple[str, str]  # a watch's (caller id, request_id)
SIGNATURE_RESOLUTION = 0.02
"""Metres: a changes-only watch calls back when a track moved at least about this far."""


@dataclass(frozen=True)
class FusionSettings:
    """The fusion stage's limits (the server's ``~fused_*`` parameters)."""

    deadline: float = 2.0
    """Seconds a fused request waits for the vision systems asked before it is answered without them."""
    max_rounds: int = 1000
    """Fused requests waiting for their answers at once; beyond it new ones are refused BUSY."""
    max_algorithms: int = 64
    """Algorithm strings tracked at once (one tracker each)."""
    busy_retry_after: float = 0.5
    tracker: TrackerSettings = field(default_factory=TrackerSettings)


@dataclass(frozen=True)
class Delivery:
    """One fused callback owed to a robot: what CallbackCoordinates carries (with ``fused`` true)."""

    callback_service: str
    algorithm: str
    request_id: str
    stamp: float
    objects: tuple[TrackView, ...]
    status: int
    message: str
    answered: tuple[str, ...] = ()
    refused: tuple[str, ...] = ()
    missing: tuple[str, ...] = ()
    gone: tuple[int, ...] = ()
    watch: bool = False


@dataclass
class _Asked:
    """Who was asked for one round or one watch period, and what came back."""

    answered: dict[str, float] = field(default_factory=dict)  # vision system -> newest frame stamp
    refused: dict[str, tuple[int, str]] = field(default_factory=dict)  # vision system -> (status, message)
    failed: set[str] = field(default_factory=set)  # forwards that got no answer
    untracked: int = 0  # outlines left out because the tracker's table was full

    def refusal_lines(self) -> tuple[str, ...]:
        return tuple(f'{vs}: {name(status)}: {text}' for vs, (status, text) in sorted(self.refused.items()))


@dataclass
class _Round:
    wire_id: str
    caller: str
    request_id: str
    algorithm: str
    region: Box
    callback_service: str
    asked: frozenset[str]
    deadline: float
    heard: _Asked = field(default_factory=_Asked)

    def complete(self) -> bool:
        heard = self.heard
        return self.asked <= (heard.answered.keys() | heard.refused.keys() | heard.failed)


@dataclass
class _Watch:
    key: Key
    wire_id: str
    algorithm: str
    region: Box
    callback_service: str
    period: float
    changes_only: bool
    due: float
    serving: tuple[str, ...] = ()
    heard: _Asked = field(default_factory=_Asked)
    reported: dict[int, tuple] = field(default_factory=dict)  # track id -> signature last delivered
    delivered: bool = False


class FusionStage:
    """Fused rounds and watches, one tracker per algorithm string, and the deliveries they owe.

    :param clock: seconds, the same clock as the vision systems' stamps (the server passes ROS time).
    :param field_of_view: a registered vision system's field of view (None when unknown).
    :param settings: limits and the trackers' settings.
    """

    def __init__(
        self,
        clock: Callable[[], float],
        field_of_view: Callable[[str], Sequence[Point] | None],
        settings: FusionSettings | None = None,
    ):
        self.clock = clock
        self.field_of_view = field_of_view
        self.settings = settings or FusionSettings()
        self._trackers: dict[str, Tracker] = {}
        self._used: dict[str, float] = {}  # algorithm -> when its tracker last took a frame or a user
        self._rounds: dict[str, _Round] = {}
        self._watches: dict[Key, _Watch] = {}
        self._by_wire: dict[str, _Watch] = {}
        self._ids = itertools.count(1)
        self.late = 0
        """Frames that arrived for a round already answered (still fused: the tracks use them)."""
        self.untracked = 0
        """Outlines left untracked because a tracker's table was full."""

    # -- rounds --------------------------------------------------------------------------------
    def open_round(
        self,
        caller: str,
        request_id: str,
        algorithm: str,
        region: Box,
        callback_service: str,
        asked: Iterable[str],
    ) -> str:
        """A fused request forwarded to ``asked``: the request id its forwards carry.

        :raises Refusal: ``BUSY`` when :attr:`FusionSettings.max_rounds` wait already, or no
            tracker is free for a new algorithm string.
        """
        if len(self._rounds) >= self.settings.max_rounds:
            raise self._busy(f'{len(self._rounds)} fused requests wait for their vision systems')
        now = self.clock()
        self._tracker(algorithm, now)
        wire_id = f'fused-{next(self._ids)}'
        self._rounds[wire_id] = _Round(
            wire_id,
            caller,
            request_id,
            algorithm,
            _box(region),
            callback_service,
            frozenset(asked),
            now + self.settings.deadline,
        )
        return wire_id

    def cancel_round(self, wire_id: str) -> None:
        """Forget round ``wire_id``: its request was refused after all (nothing was forwarded)."""
        self._rounds.pop(wire_id, None)

    def forward_answer(self, wire_id: str, vision_system: str, status: int | None, message: str = '') -> None:
        """The reply of ``vision_system`` to the forward of round ``wire_id``: its status (ACCEPTED: 0),
        or None when the forward failed (no answer)."""
        fused_round = self._rounds.get(wire_id)
        if fused_round is None:
            return
        if status is None:
            fused_round.heard.failed.add(vision_system)
        elif status != OK:
            fused_round.heard.refused[vision_system] = (status, message)

    # -- watches -------------------------------------------------------------------------------
    def set_watch(
        self,
        key: Key,
        algorithm: str,
        region: Box,
        callback_service: str,
        period: float,
        changes_only: bool,
    ) -> str:
        """Start or renew the fused watch ``key``: the request id its forwards carry.

        :raises Refusal: ``BUSY`` when no tracker is free for a new algorithm string.
        """
        now = self.clock()
        self._tracker(algorithm, now)
        old = self._watches.get(key)
        if old is not None and old.algorithm == algorithm:
            old.region, old.callback_service, old.period, old.changes_only = (
                _box(region),
                callback_service,
                float(period),
                bool(changes_only),
            )
            return old.wire_id
        if old is not None:
            self.drop_watch(key)
        wire_id = f'fused-watch-{next(self._ids)}'
        watch = _Watch(
            key, wire_id, algorithm, _box(region), callback_service, period, changes_only, now + period
        )
        self._watches[key] = watch
        self._by_wire[wire_id] = watch
        return wire_id

    def wire_id(self, key: Key) -> str | None:
        """The request id the forwards of the fused watch ``key`` carry (None: not a fused watch)."""
        watch = self._watches.get(key)
        return None if watch is None else watch.wire_id

    def drop_watch(self, key: Key) -> None:
        watch = self._watches.pop(key, None)
        if watch is not None:
            self._by_wire.pop(watch.wire_id, None)

    def keep_watches(self, serving: Mapping[Key, Sequence[str]]) -> None:
        """The fused watches standing now, each with the vision systems serving it; others are dropped."""
        for key in list(self._watches):
            if key not in serving:
                self.drop_watch(key)
        for key, names in serving.items():
            watch = self._watches.get(key)
            if watch is not None:
                watch.serving = tuple(sorted(names))
                for gone in set(watch.heard.refused) - set(names):
                    del watch.heard.refused[gone]

    def watch_refused(self, wire_id: str, vision_system: str, status: int, message: str) -> None:
        """``vision_system`` refused the forward of the fused watch ``wire_id``."""
        watch = self._by_wire.get(wire_id)
        if watch is not None:
            watch.heard.refused[vision_system] = (status, message)

    # -- frames --------------------------------------------------------------------------------
    def callback(
        self,
        wire_id: str,
        vision_system: str,
        stamp: float,
        algorithm: str,
        observations: Sequence[Observation],
    ) -> bool:
        """One vision system's callback for a fused round or watch: fused into the tracks of
        ``algorithm``. False when ``wire_id`` names nothing waiting (a late frame: fused all the same
        if its algorithm is tracked, without counting misses)."""
        now = self.clock()
        owner: _Round | _Watch | None = self._rounds.get(wire_id) or self._by_wire.get(wire_id)
        tracker = self._trackers.get(algorithm if owner is None else owner.algorithm)
        if tracker is None:
            return False
        self._used[algorithm if owner is None else owner.algorithm] = now
        region = None if owner is None else owner.region
        result = tracker.frame(vision_system, stamp, observations, self._looked_at(vision_system, region))
        self.untracked += result.untracked
        if owner is not None:
            owner.heard.untracked += result.untracked
        if owner is None:
            self.late += 1
            return False
        owner.heard.answered[vision_system] = max(stamp, owner.heard.answered.get(vision_system, stamp))
        owner.heard.refused.pop(vision_system, None)
        return True

    def _looked_at(self, vision_system: str, region: Box | None) -> list[Point] | None:
        """Where a frame of ``vision_system`` for ``region`` looked: its field of view within the region."""
        outline = self.field_of_view(vision_system)
        if outline is None or len(outline) < 3:
            return None
        seen = Polygon(outline)
        if region is not None:
            seen = seen.intersection(box(*region))
        if seen.is_empty or seen.geom_type != 'Polygon':
            return None
        return [(float(x), float(y)) for x, y in seen.exterior.coords[:-1]]

    # -- deliveries ----------------------------------------------------------------------------
    def next_due(self) -> float | None:
        """When :meth:`due` next has something to deliver by the clock; None: nothing waits."""
        times = [r.deadline for r in self._rounds.values()] + [w.due for w in self._watches.values()]
        return min(times, default=None)

    def due(self) -> list[Delivery]:
        """The deliveries owed now: rounds complete or past their deadline, watches at their period.
        Tracks unseen for longer than the coasting time end first."""
        now = self.clock()
        self._expire(now)
        deliveries = []
        for wire_id, fused_round in list(self._rounds.items()):
            if fused_round.complete() or fused_round.deadline <= now:
                del self._rounds[wire_id]
                deliveries.append(self._answer(fused_round, now))
        for watch in self._watches.values():
            if watch.due <= now:
                watch.due = max(watch.due + watch.period, now)
                delivery = self._watch_delivery(watch, now)
                if delivery is not None:
                    deliveries.append(delivery)
        return deliveries

    def _answer(self, fused_round: _Round, now: float) -> Delivery:
        heard = fused_round.heard
        missing = tuple(sorted(fused_round.asked - heard.answered.keys() - heard.refused.keys()))
        status, message = _outcome(heard, missing, len(fused_round.asked), self.settings.deadline)
        stamp = max(heard.answered.values(), default=now)
        objects: tuple[TrackView, ...] = ()
        if status == OK and fused_round.asked:
            since = min(heard.answered.values(), default=now)
            tracker = self._trackers[fused_round.algorithm]
            objects = tuple(tracker.tracks(stamp, fused_round.region, since=since))
        return Delivery(
            fused_round.callback_service,
            fused_round.algorithm,
            fused_round.request_id,
            stamp,
            objects,
            status,
            message,
            tuple(sorted(heard.answered)),
            heard.refusal_lines(),
            missing,
        )

    def _watch_delivery(self, watch: _Watch, now: float) -> Delivery | None:
        heard, watch.heard = watch.heard, _Asked(refused=dict(watch.heard.refused))
        missing = tuple(sorted(set(watch.serving) - heard.answered.keys() - heard.refused.keys()))
        status, message = _outcome(heard, missing, len(watch.serving), watch.period)
        if status == OK and not heard.answered and watch.serving:
            message = (
                f'no frame from the {len(watch.serving)} vision systems serving the watch in the last period'
            )
        tracker = self._trackers.get(watch.algorithm)
        # The tracks seen in the period up to the newest frame, predicted to its stamp (the callback's).
        stamp = max(heard.answered.values(), default=now)
        objects = (
            () if tracker is None else tuple(tracker.tracks(stamp, watch.region, since=stamp - watch.period))
        )
        signatures = {track.track_id: _signature(track) for track in objects}
        gone = tuple(sorted(watch.reported.keys() - signatures.keys()))
        changed = signatures != watch.reported or not watch.delivered
        watch.reported, watch.delivered = signatures, True
        if watch.changes_only and not changed and not gone:
            return None
        return Delivery(
            watch.callback_service,
            watch.algorithm,
            watch.key[1],
            stamp,
            objects,
            status,
            message,
            tuple(sorted(heard.answered)),
            heard.refusal_lines(),
            missing,
            gone,
            watch=True,
        )

    # -- the world model -----------------------------------------------------------------------
    def tracks(self, at: float) -> list[tuple[str, TrackView]]:
        """Every live track of every algorithm, predicted to ``at``, with its algorithm string."""
        return [
            (algorithm, track)
            for algorithm, tracker in sorted(self._trackers.items())
            for track in tracker.tracks(at)
        ]

    def flagged(self) -> dict[str, str]:
        """Vision systems left out of fusion (their outlines disagree with their neighbours'), with why."""
        flagged: dict[str, str] = {}
        for algorithm, tracker in sorted(self._trackers.items()):
            for vision_system, reason in tracker.flagged().items():
                flagged.setdefault(vision_system, f'{reason} ({algorithm})')
        return flagged

    def forget(self, vision_system: str) -> None:
        """``vision_system`` left the registry: its tracks coast on the others' frames or end."""
        for tracker in self._trackers.values():
            tracker.forget(vision_system)

    @property
    def waiting(self) -> int:
        """Fused requests waiting for their answers."""
        return len(self._rounds)

    @property
    def watches(self) -> int:
        return len(self._watches)

    def track_count(self) -> int:
        return sum(len(tracker) for tracker in self._trackers.values())

    def _tracker(self, algorithm: str, now: float) -> Tracker:
        """The tracker of ``algorithm``, made on first use; an idle one makes room when all are taken.

        :raises Refusal: ``BUSY`` when :attr:`FusionSettings.max_algorithms` trackers are all in use.
        """
        tracker = self._trackers.get(algorithm)
        if tracker is None:
            if len(self._trackers) >= self.settings.max_algorithms:
                self._evict_idle(now)
            if len(self._trackers) >= self.settings.max_algorithms:
                raise self._busy(f'{len(self._trackers)} algorithm strings are tracked')
            tracker = self._trackers[algorithm] = Tracker(self.settings.tracker)
        self._used[algorithm] = now
        return tracker

    def _busy(self, what: str) -> Refusal:
        return Refusal(
            BUSY, f'busy: {what}, the most this server keeps; try again later', self.settings.busy_retry_after
        )

    def _evict_idle(self, now: float) -> None:
        in_use = {r.algorithm for r in self._rounds.values()} | {w.algorithm for w in self._watches.values()}
        idle = [a for a in self._trackers if a not in in_use]
        if idle:
            oldest = min(idle, key=lambda a: self._used.get(a, 0.0))
            del self._trackers[oldest]
            self._used.pop(oldest, None)

    def _expire(self, now: float) -> None:
        for tracker in self._trackers.values():
            tracker.expire(now)


def _outcome(heard: _Asked, missing: tuple[str, ...], asked: int, deadline: float) -> tuple[int, str]:
    """The status and message of a delivery from what the ``asked`` vision systems did."""
    refusals = heard.refusal_lines()
    notes = []
    if refusals:
        notes.append(f'{len(refusals)} refused: ' + '; '.join(refusals))
    if missing:
        notes.append(f'{len(missing)} did not answer within {deadline:g} s: ' + ', '.join(missing))
    if heard.untracked:
        notes.append(f'{heard.untracked} outlines left untracked: the track table is full')
    if heard.answered or asked == 0:
        found = (
            'no vision system covers the region'
            if asked == 0
            else f'{len(heard.answered)} of {asked} answered'
        )
        return OK, '; '.join([found, *notes])
    statuses = [status for status, _ in heard.refused.values()]
    if statuses and not missing and len(set(statuses)) == 1 and statuses[0] in REFUSAL_STATUSES:
        return statuses[0], '; '.join(notes)
    return UNAVAILABLE, '; '.join(['no vision system answered', *notes])


def _signature(track: TrackView) -> tuple:
    x, y = track.position
    return (round(x / SIGNATURE_RESOLUTION), round(y / SIGNATURE_RESOLUTION), track.stationary, track.label)


def _box(region: Sequence[float]) -> Box:
    return (float(region[0]), float(region[1]), float(region[2]), float(region[3]))
