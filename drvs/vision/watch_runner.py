"""A vision system's standing requests ("watches"): which to evaluate when, and what to send back.

Watches keyed by (``callback_service``, ``request_id``, ``callback_uri``: robots of two sites may
share names), granted and expired; one frame
for every watch due; with ``changes_only``, a callback only when the outlines or labels
changed (not the confidence).
No ROS and no clock of its own (calls take ``now``); one lock, ``WatchRunner._lock``. The
service: docs/nodes/vision_system.md; the rules and why: docs/design.md ("Vision systems").

>>> runner = WatchRunner(min_period=0.1, max_duration=60.0, change_tolerance=0.03)
>>> terms = Terms('/robot/callback_coordinates', 'crate', None, (0, 0, 4, 3), 0.5, True)
>>> runner.stand(terms, 100.0, now=0.0)
Grant(period=0.5, duration=60.0, new=True)
>>> [t.request_id for t in runner.due(0.0)], runner.next_due()
(['crate'], 0.5)
>>> square = [(0, 0), (1, 0), (1, 1), (0, 1)]
>>> runner.evaluate(runner.due(0.5)[0], [(square, '')]) == [(square, '')]
True
>>> runner.evaluate(runner.due(1.0)[0], [([(0.01, 0), (1, 0), (1, 1), (0, 1)], '')]) is None
True
>>> runner.evaluate(runner.due(1.5)[0], [])
[]
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from drvs.algorithms import AlgorithmSet, Parsed
from drvs.common.status import BUSY, Refusal
from drvs.common.validation import global_ros_name, request_fields, rosrpc_uri, watch_terms

logger = logging.getLogger('rosout.' + __name__)

__all__ = ['Grant', 'Terms', 'WatchRunner', 'outline_distance', 'outlines_changed', 'parse_watch']

Box = tuple[float, float, float, float]
Found = Sequence[tuple[Sequence[Sequence[float]], str] | tuple[Sequence[Sequence[float]], str, float]]
"""What an evaluation found: (outline, label[, confidence]) tuples, each outline a ring of (x, y) in
metres (:class:`drvs.vision.pipeline.Located`); changes are judged on outlines and labels only."""


@dataclass(frozen=True)
class Terms:
    """What a watch asks for. Immutable: a renewal replaces the terms whole."""

    callback_service: str
    request_id: str
    algorithm: Parsed  # its .text is the request's algorithm string
    region: Box
    period: float  # seconds between evaluations (the granted one, once standing)
    changes_only: bool
    fused: bool = False  # for the server's fusion stage: call back every period, even with nothing found
    callback_uri: str = ''  # the callback service's address (a caller at another site); '': ask the master

    @property
    def key(self) -> tuple[str, str, str]:
        return (self.callback_service, self.request_id, self.callback_uri)


@dataclass(frozen=True)
class Grant:
    """What the vision system grants a watch: its period and duration, and whether it is new."""

    period: float
    duration: float
    new: bool


@dataclass
class _Watch:
    terms: Terms
    expires: float
    next_due: float
    reported: list | None  # what the robot was last told ([]: nothing; None: unknown, a callback failed)
    full_report: bool = False  # renewed since the last report: report in full at the next evaluation


def parse_watch(
    algorithm: str,
    box: Sequence[float],
    callback_service: str,
    request_id: str,
    period: float,
    duration: float,
    changes_only: bool,
    algorithms: AlgorithmSet | None = None,
    fused: bool = False,
    callback_uri: str = '',
) -> Terms | None:
    """Check a WatchObjectBoundary request; its terms, or None for a cancel (``duration`` 0).

    The watch's own fields are checked as the server checks them
    (:func:`drvs.common.validation.watch_terms`), then the fields it shares with
    DetectObjectBoundary. A cancel needs only ``callback_service``, ``request_id``
    and ``duration``; its other fields are not looked at.

    >>> parse_watch('colour:0,0,0,9,9,9', (0, 0, 1, 1), '/r/callback', 'w', 0.0, 5.0, False)
    Traceback (most recent call last):
    ...
    drvs.common.validation.ValidationError: period: 0; expected a finite number of seconds greater than 0
    >>> parse_watch('', (0, 0, 0, 0), '/r/callback', 'w', 0.0, 0.0, False) is None
    True

    :raises drvs.algorithms.AlgorithmError: for the algorithm.
    :raises ValidationError: for any other field, naming it.
    """
    global_ros_name('callback_service', callback_service)
    if not watch_terms(request_id, period, duration):
        return None
    parsed, region = request_fields(algorithm, box, callback_service, algorithms)
    if callback_uri:
        rosrpc_uri('callback_uri', callback_uri)
    return Terms(
        callback_service,
        request_id,
        parsed,
        region,
        float(period),
        bool(changes_only),
        bool(fused),
        callback_uri,
    )


class WatchRunner:
    """The watches standing on one vision system.

    :param min_period: shortest period granted, seconds.
    :param max_duration: longest duration granted, seconds.
    :param change_tolerance: metres an outline may move before a ``changes_only`` watch reports it.
    :param max_watches: watches that may stand at once.
    """

    def __init__(
        self, min_period: float, max_duration: float, change_tolerance: float, max_watches: int = 256
    ):
        self.min_period = min_period
        self.max_duration = max_duration
        self.change_tolerance = change_tolerance
        self.max_watches = max_watches
        self._watches: dict[tuple[str, str, str], _Watch] = {}
        self._lock = threading.Lock()

    def __len__(self) -> int:
        with self._lock:
            return len(self._watches)

    def stand(self, terms: Terms, duration: float, now: float) -> Grant:
        """Start or renew the watch of ``terms`` for ``duration`` (> 0) seconds from ``now``.

        :raises Refusal: ``BUSY`` for a new watch when ``max_watches`` stand already.
        """
        terms = replace(terms, period=max(terms.period, self.min_period))
        duration = min(duration, self.max_duration)
        with self._lock:
            watch = self._watches.get(terms.key)
            if watch is None:
                if len(self._watches) >= self.max_watches:
                    first = min(w.expires for w in self._watches.values())
                    raise Refusal(
                        BUSY,
                        f'busy: {len(self._watches)} watches stand already; try again later',
                        max(first - now, self.min_period),
                    )
                self._watches[terms.key] = _Watch(terms, expires=now + duration, next_due=now, reported=[])
                return Grant(terms.period, duration, new=True)
            old = watch.terms
            if (old.algorithm.text, old.region, old.period) != (
                terms.algorithm.text,
                terms.region,
                terms.period,
            ):
                watch.next_due = now
            watch.terms, watch.expires, watch.full_report = terms, now + duration, True
            return Grant(terms.period, duration, new=False)

    def cancel(self, key: tuple[str, str, str]) -> bool:
        """End the watch named ``key`` (callback_service, request_id, callback_uri); whether it stood."""
        with self._lock:
            return self._watches.pop(key, None) is not None

    def due(self, now: float) -> list[Terms]:
        """The watches to evaluate at ``now``, all on one frame; they are due next a period on.

        Watches whose duration ran out are dropped first.
        """
        with self._lock:
            for key in [k for k, w in self._watches.items() if w.expires <= now]:
                logger.debug('watch %r of %s expired', key[1], key[0])
                del self._watches[key]
            due = [w for w in self._watches.values() if w.next_due <= now]
            for watch in due:
                watch.next_due = _next_on_grid(now, watch.terms.period)
            return [w.terms for w in due]

    def next_due(self) -> float | None:
        """When a watch is due or expires next; None when none stands."""
        with self._lock:
            return min((min(w.next_due, w.expires) for w in self._watches.values()), default=None)

    def evaluate(self, terms: Terms, found: Found) -> list | None:
        """What to call back for a watch of :meth:`due` that found ``found``: the objects, [] (all
        gone), or None (no callback). None too when the watch was cancelled or renewed since it
        was due: the new terms are evaluated next."""
        found = list(found)
        with self._lock:
            watch = self._watches.get(terms.key)
            if watch is None or watch.terms is not terms:
                return None
            if not terms.changes_only:
                return found if found or terms.fused else None
            if found:
                if watch.full_report or not watch.reported or self.changed(watch.reported, found):
                    watch.reported, watch.full_report = found, False
                    return found
                return None
            if watch.reported is None or watch.reported:
                watch.reported = []
                return []
            return None

    def callback_failed(self, terms: Terms) -> None:
        """The callback :meth:`evaluate` asked for did not arrive: the robot may hold anything, so
        the next evaluation reports what it finds, or that nothing is there."""
        with self._lock:
            watch = self._watches.get(terms.key)
            if watch is not None:
                watch.reported = None

    def changed(self, old: Found, new: Found) -> bool:
        return outlines_changed(old, new, self.change_tolerance)


def _next_on_grid(now: float, period: float) -> float:
    """The first multiple of ``period`` after ``now``."""
    after = (math.floor(now / period) + 1) * period
    return after if after > now else after + period


def outline_distance(
    a: Sequence[Sequence[float]], b: Sequence[Sequence[float]], ordered: bool = False
) -> float:
    """How far apart two outlines are, in metres.

    The Hausdorff distance between their boundaries, measured from every vertex of
    each to the other's boundary (not to its vertices), so it does not depend on
    where a ring starts, which way it runs or how many vertices lie along a
    straight edge. ``ordered``: the outlines' vertex order means something (a tag's
    corner 0 first: its heading), so with as many vertices each, corresponding
    corners are compared too and a turn on the spot counts.

    >>> square = [(0, 0), (1, 0), (1, 1), (0, 1)]
    >>> outline_distance(square, [(1, 1), (0.5, 1), (0, 1), (0, 0), (1, 0)])
    0.0
    >>> outline_distance(square, [(0, 1), (0, 0), (1, 0), (1, 1)], ordered=True)
    1.0
    """
    points_a, points_b = np.asarray(a, float)[:, :2], np.asarray(b, float)[:, :2]
    distance = float(max(_to_ring(points_a, points_b).max(), _to_ring(points_b, points_a).max()))
    if ordered and len(points_a) == len(points_b):
        distance = max(distance, float(np.hypot(*(points_a - points_b).T).max()))
    return distance


def _to_ring(points: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """The distance of each point (N, 2) to the closed ring (M, 2): to its nearest edge."""
    start = ring
    edge = np.roll(ring, -1, axis=0) - start
    offset = points[:, None, :] - start[None, :, :]  # (N, M, 2)
    length2 = np.maximum((edge**2).sum(axis=1), 1e-300)  # a repeated vertex: an edge of length 0
    along = np.clip((offset * edge).sum(axis=2) / length2, 0.0, 1.0)
    return np.hypot(*(offset - along[..., None] * edge).transpose(2, 0, 1)).min(axis=1)


def outlines_changed(old: Found, new: Found, tolerance: float) -> bool:
    """Whether ``new`` differs from ``old`` by more than ``tolerance`` metres, compared as sets.

    Changed: another number of objects, other labels, or an object of ``new``
    farther than ``tolerance`` (:func:`outline_distance`) from the object of ``old``
    with the same label it is paired with. Pairs are made nearest first, so the
    order in which objects are listed does not matter. A labelled object is one the
    algorithm identifies (a tag): its corners are compared in order. A confidence
    (a third member) is not compared: it varies from frame to frame with the object
    standing still.

    >>> square = [(0, 0), (1, 0), (1, 1), (0, 1)]
    >>> moved = [(x + 0.1, y) for x, y in square]
    >>> outlines_changed([(square, ''), (moved, '')], [(moved, ''), (square, '')], 0.03)
    False
    >>> outlines_changed([(square, '')], [(moved, '')], 0.03)
    True
    """
    if len(old) != len(new) or sorted(found[1] for found in old) != sorted(found[1] for found in new):
        return True
    for label in {found[1] for found in new}:
        olds = [found[0] for found in old if found[1] == label]
        news = [found[0] for found in new if found[1] == label]
        pairs = sorted(
            (outline_distance(o, n, ordered=bool(label)), i, j)
            for i, o in enumerate(olds)
            for j, n in enumerate(news)
        )
        paired_old, paired_new = set(), set()
        for distance, i, j in pairs:
            if i in paired_old or j in paired_new:
                continue
            if distance > tolerance:
                return True
            paired_old.add(i)
            paired_new.add(j)
    return False
