"""Which outlines of one camera frame belong to which track: the fusion tracker's association.

A labelled outline (a tag) joins the track with its label, wherever it is; an outline that holds
the predicted centroids of two tracks apart (two people in one blob) joins none; the others are
assigned globally (Hungarian, :func:`scipy.optimize.linear_sum_assignment`) on a cost of centroid
distance to each track's prediction and outline overlap, within a gate or an overlap; an outline
left over that lies mostly inside a track another outline of the frame joined, close to that
outline, is a second piece of it. The tracker's rows (:class:`Track`) live here too. The rules
and their constants: docs/fusion-tracking.md ("Association").
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment  # type: ignore[import]  # scipy ships no type information

from drvs.server.outlines import Shape, combine, contains, overlap_area, union_outline
from drvs.server.track_motion import Motion

__all__ = ['Association', 'Candidate', 'Rules', 'Seen', 'Track', 'associate']

Point = tuple[float, float]
_NO = 1e9  # the cost of a pair outside the gate
SAME_TOP = 0.05
"""Metres: two cameras' outlines of a track whose tops differ by no more are views of one object
(their clearances compare, :meth:`Track.clearance`)."""


@dataclass
class Seen:
    """One camera's newest outline of a track."""

    stamp: float
    shape: Shape
    height: float = 0.0  # metres above the floor of the object's top; 0: not measured
    clearance: float = 0.0  # metres above the floor of its underside; 0: on the floor or not measured


@dataclass(eq=False)
class Track:
    """One row of the track table."""

    track_id: int
    label: str
    motion: Motion
    evidence: float  # 0..1, see TrackView.confidence
    last_seen: float
    seen: dict[str, Seen] = field(default_factory=dict)  # camera -> its newest outline
    stationary: bool = False
    fused: tuple[float, float, np.ndarray] | None = (
        None  # (stamp, outline age, fused outline); None after an update
    )

    def velocity(self) -> Point:
        if self.stationary:
            return (0.0, 0.0)
        state = self.motion.state
        return (state.vx, state.vy)

    def position(self, stamp: float) -> Point:
        return self.motion.position(stamp, moving=not self.stationary)

    def size(self) -> float:
        """Half the diagonal of the smallest of its cameras' outlines: how big the object is at most."""
        return min(seen.shape.radius for seen in self.seen.values())

    def height(self, age: float) -> float:
        """The highest top its fresh outlines measured (:meth:`fresh`), metres; 0 when none did."""
        return max((seen.height for seen in self.fresh(age)), default=0.0)

    def clearance(self, age: float) -> float:
        """The room under it, metres: the largest clearance among its fresh outlines whose top is
        the track's (within :data:`SAME_TOP`: another camera's view of the same object, not of it
        merged with something higher); 0 when none measured one. A camera that saw only its top
        reports 0, unknown: one that saw floor under it has the proof."""
        fresh = self.fresh(age)
        top = max((seen.height for seen in fresh), default=0.0)
        return max((seen.clearance for seen in fresh if seen.height >= top - SAME_TOP), default=0.0)

    def fresh(self, age: float) -> list[Seen]:
        """The cameras' outlines at most ``age`` seconds older than its newest: its fused outline."""
        return [s for s in self.seen.values() if s.stamp >= self.last_seen - age]

    def outline(self, at: float, age: float, extended: float = math.inf) -> tuple[Point, ...]:
        """Its outline moved along the velocity to ``at`` (counter-clockwise): the union of its fresh
        outlines when one of them is ``extended`` (half-diagonal, metres: a shelf seen in parts),
        else the newest camera's alone (a person, a robot, a tag: every camera sees all of it, and a
        union of views taken at different times is bigger than the object and loses a tag's corners)."""
        vx, vy = self.velocity()
        if self.fused is None or self.fused[1] != age:  # computed at last_seen once, then moved as a whole
            stamp = self.last_seen
            fresh = self.fresh(age)
            if all(seen.shape.radius < extended for seen in fresh):
                fresh = [max(fresh, key=lambda seen: seen.stamp)]
            moves = [(seen.shape, (vx * (stamp - seen.stamp), vy * (stamp - seen.stamp))) for seen in fresh]
            self.fused = (stamp, age, np.array(union_outline(moves)))
        stamp, _, points = self.fused
        return tuple((x, y) for x, y in (points + (vx * (at - stamp), vy * (at - stamp))).tolist())


@dataclass
class Candidate:
    """One checked outline of the frame; ``pieces`` once other outlines merged into it."""

    shape: Shape
    label: str
    confidence: float
    pieces: list[Shape] = field(default_factory=list)
    height: float = 0.0  # the highest of its pieces' tops, metres; 0: not measured
    clearance: float = 0.0  # the lowest of its pieces' undersides, metres; 0: on the floor or not measured


@dataclass(frozen=True)
class Rules:
    """The constants of association (TrackerSettings' fields of the same names)."""

    gate: float
    coast: float
    min_overlap: float
    merge_overlap: float
    merge_gap: float
    outline_age: float


@dataclass
class Association:
    """What :func:`associate` decided."""

    pairs: list[tuple[Candidate, Track]] = field(default_factory=list)
    fresh: list[Candidate] = field(default_factory=list)  # need new tracks
    skipped: int = 0  # a label's second outline in the frame
    ended: list[Track] = field(default_factory=list)  # labelled tracks past their coast time
    shared: list[tuple[Candidate, list[Track]]] = field(default_factory=list)  # one blob of several tracks


def associate(
    stamp: float,
    candidates: Sequence[Candidate],
    tracks: Sequence[Track],
    by_label: Mapping[str, Track],
    rules: Rules,
) -> Association:
    """Associate one frame's ``candidates``, captured at ``stamp``, with the ``tracks``."""
    result = Association()
    labelled: dict[str, list[Candidate]] = {}
    plain: list[Candidate] = []
    for candidate in candidates:
        if candidate.label:
            labelled.setdefault(candidate.label, []).append(candidate)
        else:
            plain.append(candidate)
    for label, group in labelled.items():
        track = by_label.get(label)
        if track is not None and stamp - track.last_seen > rules.coast:
            result.ended.append(track)  # gone: the label starts a new track
            track = None
        if track is None:
            result.fresh.append(max(group, key=lambda c: c.shape.area))
        else:
            x, y = track.position(stamp)
            best = min(group, key=lambda c: math.hypot(c.shape.centroid[0] - x, c.shape.centroid[1] - y))
            result.pairs.append((best, track))
        result.skipped += len(group) - 1
    alive = [t for t in tracks if not t.label and stamp - t.last_seen <= rules.coast]
    if not plain or not alive:
        result.fresh.extend(plain)
        return result
    predicted = np.array([t.position(stamp) for t in alive])
    plain = _single(plain, alive, predicted, result)
    if not plain:
        return result
    cost, inside = _costs(stamp, plain, alive, predicted, rules)
    rows, cols = linear_sum_assignment(cost)
    joined: dict[int, Candidate] = {}  # column -> the candidate that joined the track
    for row, col in zip(rows.tolist(), cols.tolist(), strict=True):
        if cost[row, col] < _NO:
            joined[col] = plain[row]
    taken = {id(c) for c in joined.values()}
    for row, candidate in enumerate(plain):
        if id(candidate) in taken:
            continue
        col = _piece_of(stamp, candidate, inside[row], joined, alive, rules)
        if col is None:
            result.fresh.append(candidate)
        else:
            joined[col].pieces.append(candidate.shape)
            joined[col].height = max(joined[col].height, candidate.height)
            joined[col].clearance = min(joined[col].clearance, candidate.clearance)
    for col, candidate in joined.items():
        if candidate.pieces:
            candidate.pieces.insert(0, candidate.shape)
            candidate.shape = combine(candidate.pieces)
        result.pairs.append((candidate, alive[col]))
    return result


def _single(
    plain: list[Candidate], tracks: list[Track], predicted: np.ndarray, result: Association
) -> list[Candidate]:
    """The candidates that are no blob of several tracks; the others go to ``result.shared``.

    A camera sees two people who stand close, one behind the other, as one blob: an outline that
    holds the predicted centroids of two tracks farther apart than either's size is such a blob, and
    its centroid (between them) is neither's position."""
    bounds = np.array([c.shape.bounds for c in plain])
    x, y = predicted[None, :, 0], predicted[None, :, 1]
    in_box = (x >= bounds[:, 0:1]) & (x <= bounds[:, 2:3]) & (y >= bounds[:, 1:2]) & (y <= bounds[:, 3:4])
    kept = []
    for candidate, near in zip(plain, in_box, strict=True):
        cols = np.nonzero(near)[0]
        if len(cols) >= 2:
            cols = cols[contains(candidate.shape.points, predicted[cols])]
        if len(cols) >= 2 and _apart([tracks[j] for j in cols.tolist()], predicted[cols]):
            result.shared.append((candidate, [tracks[j] for j in cols.tolist()]))
        else:
            kept.append(candidate)
    return kept


def _apart(tracks: list[Track], predicted: np.ndarray) -> bool:
    """True if two of ``tracks`` (at ``predicted``) are farther apart than the larger one's size (the
    half-diagonal of its smallest fresh outline): two objects, not two tracks on one."""
    sizes = [t.size() for t in tracks]
    for i in range(len(tracks)):
        for j in range(i + 1, len(tracks)):
            if math.dist(predicted[i], predicted[j]) > max(sizes[i], sizes[j]):
                return True
    return False


def _costs(
    stamp: float, plain: list[Candidate], tracks: list[Track], predicted: np.ndarray, rules: Rules
) -> tuple[np.ndarray, np.ndarray]:
    """Cost (candidates x tracks): distance to the prediction over the gate plus one minus the
    overlap; ``_NO`` outside the gate without overlap. Also how much of each candidate lies inside
    each track. Both on bounding boxes (see :func:`_box_overlaps`), except where an outline beyond
    the gate would join a track by overlap alone: there the areas of the outlines decide."""
    centroids = np.array([c.shape.centroid for c in plain])
    distance = np.hypot(*(centroids[:, None, :] - predicted[None, :, :]).transpose(2, 0, 1))
    overlap, inside = _box_overlaps(stamp, plain, tracks, rules)
    for row, col in zip(*np.nonzero((distance > rules.gate) & (overlap >= rules.min_overlap)), strict=True):
        overlap[row, col], _ = _exact(stamp, plain[row].shape, tracks[col], rules)
    allowed = (distance <= rules.gate) | (overlap >= rules.min_overlap)
    cost = np.minimum(distance / rules.gate, 2.0) + (1.0 - overlap)
    return np.where(allowed, cost, _NO), inside


def _box_overlaps(
    stamp: float, plain: list[Candidate], tracks: list[Track], rules: Rules
) -> tuple[np.ndarray, np.ndarray]:
    """Overlap of each candidate's bounds with each track's (shared area / the smaller; the most
    with any camera's fresh outline of the track, moved along its velocity), and shared area /
    the candidate's. Vectorised: no shapely."""
    boxes = np.array([c.shape.bounds for c in plain])
    owners: list[int] = []
    seen_boxes: list[tuple[float, float, float, float]] = []
    for col, track in enumerate(tracks):
        vx, vy = track.velocity()
        for seen in track.fresh(rules.outline_age):
            dx, dy = vx * (stamp - seen.stamp), vy * (stamp - seen.stamp)
            low_x, low_y, high_x, high_y = seen.shape.bounds
            seen_boxes.append((low_x + dx, low_y + dy, high_x + dx, high_y + dy))
            owners.append(col)
    theirs = np.array(seen_boxes).reshape(-1, 4)
    width = np.minimum(boxes[:, None, 2], theirs[None, :, 2]) - np.maximum(
        boxes[:, None, 0], theirs[None, :, 0]
    )
    height = np.minimum(boxes[:, None, 3], theirs[None, :, 3]) - np.maximum(
        boxes[:, None, 1], theirs[None, :, 1]
    )
    shared = np.clip(width, 0, None) * np.clip(height, 0, None)
    mine_area = np.maximum((boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1]), 1e-12)[:, None]
    their_area = np.maximum((theirs[:, 2] - theirs[:, 0]) * (theirs[:, 3] - theirs[:, 1]), 1e-12)[None, :]
    overlap = np.zeros((len(plain), len(tracks)))
    inside = np.zeros((len(plain), len(tracks)))
    columns = np.array(owners, dtype=int)
    np.maximum.at(overlap.T, columns, (shared / np.minimum(mine_area, their_area)).T)
    np.maximum.at(inside.T, columns, (shared / mine_area).T)
    return overlap, inside


def _exact(stamp: float, shape: Shape, track: Track, rules: Rules) -> tuple[float, float]:
    """The most ``shape`` overlaps any fresh outline of ``track`` (shared area / the smaller area),
    and the most of it inside one (shared area / its area), by the outlines' areas."""
    vx, vy = track.velocity()
    overlap = inside = 0.0
    for seen in track.fresh(rules.outline_age):
        shared = overlap_area(shape, seen.shape, (vx * (stamp - seen.stamp), vy * (stamp - seen.stamp)))
        overlap = max(overlap, shared / min(shape.area, seen.shape.area))
        inside = max(inside, shared / shape.area)
    return overlap, inside


def _piece_of(
    stamp: float,
    candidate: Candidate,
    inside: np.ndarray,
    joined: dict[int, Candidate],
    tracks: list[Track],
    rules: Rules,
) -> int | None:
    """The track (column) this unmatched candidate is a second piece of, if any: the one it lies
    most inside (by area), at least ``merge_overlap``, and ``merge_gap`` from its other piece at most."""
    best: tuple[float, int] | None = None
    for col, other in joined.items():
        if inside[col] < rules.merge_overlap:  # bounds first: they cover at least the outline
            continue
        _, share = _exact(stamp, candidate.shape, tracks[col], rules)
        if share < rules.merge_overlap or (best is not None and share <= best[0]):
            continue
        if _gap(candidate.shape, other.shape, rules.merge_gap) <= rules.merge_gap:
            best = (share, col)
    return None if best is None else best[1]


def _gap(a: Shape, b: Shape, limit: float) -> float:
    """Distance between two outlines; their bounds' distance when that exceeds ``limit`` already."""
    dx = max(a.bounds[0] - b.bounds[2], b.bounds[0] - a.bounds[2], 0.0)
    dy = max(a.bounds[1] - b.bounds[3], b.bounds[1] - a.bounds[3], 0.0)
    if math.hypot(dx, dy) > limit:
        return math.hypot(dx, dy)
    return float(a.polygon().distance(b.polygon()))
