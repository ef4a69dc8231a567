"""Which cameras disagree with their neighbours about where shared objects are (a wrong pose).

For each pair of cameras that see the same track at nearly the same time, the tracker reports how
far apart their centroids are (one moved along the track's velocity to the other's stamp): a
*residual*. :class:`PoseCheck` keeps the mean of each shared object's last few residuals per pair;
a pair *agrees* when the median over its shared objects is within the tolerance. A camera that
agrees with none of its neighbours while one of those agrees with a third camera is flagged (two
cameras alone cannot tell which of them is wrong). The rule and its limits:
docs/fusion-tracking.md ("Wrong poses").
"""

from __future__ import annotations

import statistics
from collections import OrderedDict, deque
from dataclasses import dataclass, field

__all__ = ['MAX_OBJECTS', 'SAMPLES_PER_OBJECT', 'UNFLAG', 'PoseCheck']

MAX_OBJECTS = 64
"""Shared objects remembered per pair of cameras (the oldest go first)."""
SAMPLES_PER_OBJECT = 5
"""Residuals averaged per object and pair: one odd frame does not flag a camera."""
UNFLAG = 0.8
"""A flagged camera is fused again when it agrees with a neighbour within this fraction of the tolerance."""


@dataclass
class _Pair:
    # track id -> (newest stamp, its last residuals), oldest first
    objects: OrderedDict[int, tuple[float, deque[float]]] = field(default_factory=OrderedDict)
    median: float | None = None  # over objects, once there are min_objects of them


class PoseCheck:
    """Flags cameras that disagree with their neighbours by more than ``tolerance`` (metres), judged
    over at least ``min_objects`` shared objects seen within ``window`` seconds."""

    def __init__(self, tolerance: float, min_objects: int, window: float):
        self.tolerance = tolerance
        self.min_objects = min_objects
        self.window = window
        self._pairs: dict[frozenset[str], _Pair] = {}
        self._neighbours: dict[str, set[str]] = {}
        self._flagged: dict[str, str] = {}

    def record(self, camera: str, other: str, track_id: int, stamp: float, residual: float) -> None:
        """How far ``camera``'s outline of track ``track_id`` at ``stamp`` is from ``other``'s."""
        pair = self._pairs.setdefault(frozenset((camera, other)), _Pair())
        self._neighbours.setdefault(camera, set()).add(other)
        self._neighbours.setdefault(other, set()).add(camera)
        newest, samples = pair.objects.pop(track_id, (stamp, deque(maxlen=SAMPLES_PER_OBJECT)))
        samples.append(residual)
        pair.objects[track_id] = (max(newest, stamp), samples)
        while len(pair.objects) > MAX_OBJECTS:
            pair.objects.popitem(last=False)

    def judge(self, camera: str, stamp: float) -> bool:
        """Re-judge ``camera`` at ``stamp`` (after recording its frame's residuals); True if flagged."""
        closest: tuple[float, int] | None = None  # its best agreement: median, shared objects
        for other in self._neighbours.get(camera, ()):
            pair = self._pairs[frozenset((camera, other))]
            for track_id in [t for t, (newest, _) in pair.objects.items() if newest < stamp - self.window]:
                del pair.objects[track_id]
            if len(pair.objects) < self.min_objects:
                pair.median = None
                continue
            pair.median = statistics.median(sum(s) / len(s) for _, s in pair.objects.values())
            if closest is None or pair.median < closest[0]:
                closest = (pair.median, len(pair.objects))
        if closest is None:
            self._flagged.pop(camera, None)
        elif camera in self._flagged:
            if closest[0] <= UNFLAG * self.tolerance:
                del self._flagged[camera]
        elif closest[0] > self.tolerance and self._outvoted(camera):
            self._flagged[camera] = (
                f"its outlines are {closest[0]:.2f} m from its neighbours' (median of "
                f'{closest[1]} shared objects; tolerance {self.tolerance:g} m)'
            )
        return camera in self._flagged

    def _agrees(self, camera: str, other: str) -> bool:
        pair = self._pairs.get(frozenset((camera, other)))
        return pair is not None and pair.median is not None and pair.median <= self.tolerance

    def _outvoted(self, camera: str) -> bool:
        """True if a neighbour of ``camera`` that it disagrees with agrees with a third camera."""
        for other in self._neighbours.get(camera, ()):
            if other in self._flagged or self._agrees(camera, other):
                continue
            for third in self._neighbours.get(other, ()):
                if third != camera and third not in self._flagged and self._agrees(other, third):
                    return True
        return False

    def is_flagged(self, camera: str) -> bool:
        return camera in self._flagged

    def flagged(self) -> dict[str, str]:
        """Cameras flagged now, each with the reason."""
        return dict(self._flagged)

    def forget(self, camera: str) -> None:
        """Drop ``camera``'s residuals and flag."""
        for other in self._neighbours.pop(camera, set()):
            self._pairs.pop(frozenset((camera, other)), None)
            self._neighbours.get(other, set()).discard(camera)
        self._flagged.pop(camera, None)
