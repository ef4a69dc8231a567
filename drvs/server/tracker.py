"""The fusion tracker: every camera's outlines, frame by frame, as one table of tracked objects in ``map``.

:meth:`Tracker.frame` associates one camera frame's outlines with the tracks (gating on each
track's position predicted to the frame's capture stamp, then a global assignment on a cost of
centroid distance and outline overlap; a tag's label is a hard constraint), updates each track's
constant-velocity filter (:mod:`drvs.server.track_motion`) and starts tracks for the rest;
:meth:`Tracker.tracks` predicts them to a time. Cameras whose outlines disagree with their
neighbours' are left out (:mod:`drvs.server.pose_check`). Stamps are arguments: no clock here.
Not thread-safe (the caller holds a lock). The method and every constant: docs/fusion-tracking.md.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields

import numpy as np
from scipy.optimize import linear_sum_assignment  # type: ignore[import]  # scipy ships no type information
from shapely.geometry import Polygon, box

from drvs.server.outlines import Shape, clean, combine, contains, overlap_area, union_outline
from drvs.server.pose_check import PoseCheck
from drvs.server.track_motion import Motion, MotionNoise

__all__ = ['DEFAULTS', 'FrameResult', 'Observation', 'TrackView', 'Tracker', 'TrackerSettings']

Point = tuple[float, float]
Box = tuple[float, float, float, float]
_NO = 1e9  # the cost of a pair outside the gate


@dataclass(frozen=True)
class Observation:
    """One outline from one camera frame, in map metres."""

    outline: tuple[Point, ...]
    """Counter-clockwise polygon (at least 3 points; a tag's: 4 corners, corner 0 first)."""
    label: str = ''
    """A tag's identity (e.g. ``'tag36h11:3'``): one track per label, never two labels in a track."""
    confidence: float = 0.0
    """The camera's own, 0..1 (0: unknown)."""


@dataclass(frozen=True)
class TrackerSettings:
    """The tracker's constants; docs/fusion-tracking.md says why each default."""

    gate: float = 1.0
    """Metres: farthest centroid distance to a track's prediction at which an outline may join it
    (outlines that overlap the track's join it however far their centroids are)."""
    coast: float = 2.0
    """Seconds a track unseen survives (predicted) before it is gone."""
    stationary_speed: float = 0.1
    """m/s: a track whose filtered centroid moved slower than this on average over
    ``stationary_time`` is stationary."""
    stationary_time: float = 1.0
    """Seconds: see ``stationary_speed``."""
    max_tracks: int = 256
    """Tracks kept at most (gone ones count until expired); outlines that would need more are
    counted in ``FrameResult.untracked``."""
    pose_tolerance: float = 0.3
    """Metres: a camera whose outlines are farther than this from its neighbours' (median over its
    shared objects) is flagged and left out."""
    pose_min_objects: int = 3
    """Shared objects needed before a camera is judged."""
    pose_window: float = 30.0
    """Seconds: shared objects not seen together for this long no longer count."""
    pose_max_age: float = 0.5
    """Seconds: a neighbour's outline older (or newer) than this is not compared with."""
    measurement_noise: float = 0.05
    """Metres: standard deviation of an outline's centroid (plus 10 % of the outline's half-diagonal:
    a big object's centroid moves more with what each camera sees of it)."""
    acceleration_noise: float = 1.0
    """m/s²: standard deviation of the white-noise acceleration of the constant-velocity model."""
    initial_speed: float = 1.5
    """m/s: standard deviation of a new track's velocity (0 with this uncertainty)."""
    reorder_window: float = 1.0
    """Seconds: a frame this much older than a track's newest still updates its motion in order;
    older frames join the track without moving it."""
    min_overlap: float = 0.1
    """Overlap (shared area / the smaller area) above which an outline may join a track beyond the gate."""
    merge_overlap: float = 0.5
    """A second outline of one frame at least this much inside a track (shared area / its area)
    that another outline of the frame joined, and ``merge_gap`` from it at most, joins it too."""
    merge_gap: float = 0.3
    """Metres: see ``merge_overlap``."""
    outline_age: float = 0.5
    """Seconds: a camera's outline older than the track's newest by more than this leaves the
    fused outline."""
    miss_weight: float = 0.2
    """A miss (a camera looking at a track's predicted position without seeing it) multiplies its
    evidence by 1 - this."""
    default_confidence: float = 0.5
    """Evidence of an outline whose camera gave no confidence."""

    def __post_init__(self) -> None:
        for item in fields(self):
            value = getattr(self, item.name)
            if not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
                raise ValueError(f'{item.name}: must be a positive number, got {value!r}')
        for name in ('min_overlap', 'merge_overlap', 'miss_weight', 'default_confidence'):
            if getattr(self, name) > 1:
                raise ValueError(f'{name}: must be at most 1, got {getattr(self, name)!r}')


DEFAULTS = TrackerSettings()


@dataclass(frozen=True)
class FrameResult:
    """What :meth:`Tracker.frame` did with one frame's outlines."""

    associated: int
    """Outlines that joined existing tracks (merged pieces included)."""
    created: int
    """Tracks started."""
    untracked: int
    """Outlines refused because the track table is full."""
    ignored: bool
    """The camera is flagged (left out): nothing fused."""
    skipped: int = 0
    """Outlines skipped: not a floor shape (fewer than 3 points, no area, a coordinate that is not a
    finite number), or a second outline with a label this frame already had."""
    merged: int = 0
    """Of ``associated``: second pieces of one object (see ``TrackerSettings.merge_overlap``)."""


@dataclass(frozen=True)
class TrackView:
    """One track predicted to a time."""

    track_id: int
    """At least 1, never reused within a :class:`Tracker`."""
    outline: tuple[Point, ...]
    """The union of each contributing camera's latest outline, moved along the velocity; CCW."""
    position: Point
    """The centroid predicted."""
    velocity: Point
    """m/s; (0, 0) when stationary."""
    confidence: float
    """0..1: the evidence that an object is there (detections weighted by their confidence, less
    misses) fading linearly to 0 over the coast time since last seen."""
    stationary: bool
    seen_by: tuple[str, ...]
    """Vision systems, sorted, whose frames updated it since the ``since`` asked for."""
    label: str
    last_seen: float
    """Capture stamp of the newest frame that updated it."""


@dataclass
class _Seen:
    stamp: float  # of this camera's newest frame that updated the track
    shape: Shape


@dataclass(eq=False)
class _Track:
    track_id: int
    label: str
    motion: Motion
    evidence: float
    last_seen: float
    seen: dict[str, _Seen] = field(default_factory=dict)
    stationary: bool = False

    def velocity(self) -> Point:
        if self.stationary:
            return (0.0, 0.0)
        state = self.motion.state
        return (state.vx, state.vy)

    def position(self, stamp: float) -> Point:
        return self.motion.position(stamp, moving=not self.stationary)

    def fresh(self, age: float) -> list[_Seen]:
        """The cameras' outlines that make its fused outline."""
        return [s for s in self.seen.values() if s.stamp >= self.last_seen - age]


@dataclass
class _Candidate:
    shape: Shape
    label: str
    confidence: float
    pieces: list[Shape] = field(default_factory=list)


class Tracker:
    """Fuses frames of many cameras into tracks (see the module docstring)."""

    def __init__(self, settings: TrackerSettings = DEFAULTS):
        self.settings = settings
        self._noise = MotionNoise(settings.acceleration_noise, settings.initial_speed)
        self._window = max(settings.reorder_window, settings.stationary_time) + 0.5
        self._tracks: dict[int, _Track] = {}
        self._by_label: dict[str, _Track] = {}
        self._next_id = 1
        self._gone: list[int] = []  # ended in frame() (a label seen again, a full table), not yet reported
        self._pose = PoseCheck(settings.pose_tolerance, settings.pose_min_objects, settings.pose_window)

    def __len__(self) -> int:
        return len(self._tracks)

    # -- frames ------------------------------------------------------------------------------------

    def frame(
        self,
        vision_system: str,
        stamp: float,
        observations: Sequence[Observation],
        field_of_view: Sequence[Point] | None = None,
    ) -> FrameResult:
        """All outlines one camera found in one frame captured at ``stamp`` (capture time; frames of
        different cameras arrive out of stamp order and with clock skew). ``field_of_view``: where
        this camera looks; a track predicted inside it that gets no outline counts as a miss."""
        if not isinstance(stamp, int | float) or not math.isfinite(stamp):
            return FrameResult(0, 0, 0, False, skipped=len(observations))
        candidates, skipped = self._candidates(observations)
        pairs, fresh = self._associate(stamp, candidates)
        skipped += len([c for c in fresh if c is None])
        fresh = [c for c in fresh if c is not None]
        for candidate, track in pairs:
            self._compare(vision_system, stamp, candidate, track)
        if self._pose.judge(vision_system, stamp):
            return FrameResult(0, 0, 0, True, skipped=skipped)
        for candidate, track in pairs:
            self._update(track, vision_system, stamp, candidate)
        created = untracked = 0
        for candidate in fresh:
            if len(self._tracks) >= self.settings.max_tracks:
                self._end_unseen(stamp)  # make room: tracks past their coast time go (reported by expire)
            if len(self._tracks) >= self.settings.max_tracks:
                untracked += 1
                continue
            self._create(vision_system, stamp, candidate)
            created += 1
        if field_of_view is not None:
            self._misses(stamp, field_of_view, {id(track) for _, track in pairs})
        merged = sum(len(c.pieces) - 1 for c, _ in pairs if c.pieces)
        return FrameResult(len(pairs) + merged, created, untracked, False, skipped=skipped, merged=merged)

    def _candidates(self, observations: Sequence[Observation]) -> tuple[list[_Candidate], int]:
        candidates: list[_Candidate] = []
        skipped = 0
        for observation in observations:
            shape = clean(getattr(observation, 'outline', ()))
            if shape is None:
                skipped += 1
                continue
            confidence = getattr(observation, 'confidence', 0.0)
            if not isinstance(confidence, int | float) or not math.isfinite(confidence):
                confidence = 0.0
            label = getattr(observation, 'label', '')
            label = label if isinstance(label, str) else str(label)
            candidates.append(_Candidate(shape, label, min(1.0, max(0.0, float(confidence)))))
        return candidates, skipped

    def _end_unseen(self, stamp: float) -> None:
        """Tracks unseen for longer than the coast time at ``stamp``: out of the table, to report."""
        for track in [t for t in self._tracks.values() if stamp - t.last_seen > self.settings.coast]:
            self._remove(track)
            self._gone.append(track.track_id)

    def _remove(self, track: _Track) -> None:
        del self._tracks[track.track_id]
        if self._by_label.get(track.label) is track:
            del self._by_label[track.label]

    # -- association -------------------------------------------------------------------------------

    def _associate(
        self, stamp: float, candidates: list[_Candidate]
    ) -> tuple[list[tuple[_Candidate, _Track]], list[_Candidate | None]]:
        """Pairs (candidate, track), and the candidates that need new tracks (None: a label's
        second outline in the frame, skipped)."""
        pairs: list[tuple[_Candidate, _Track]] = []
        fresh: list[_Candidate | None] = []
        labelled: dict[str, list[_Candidate]] = {}
        plain: list[_Candidate] = []
        for candidate in candidates:
            if candidate.label:
                labelled.setdefault(candidate.label, []).append(candidate)
            else:
                plain.append(candidate)
        for label, group in labelled.items():
            track = self._by_label.get(label)
            if track is not None and stamp - track.last_seen > self.settings.coast:
                self._remove(track)  # gone: the label starts a new track
                self._gone.append(track.track_id)
                track = None
            if track is None:
                best = max(group, key=lambda c: c.shape.area)
                fresh.append(best)
            else:
                x, y = track.position(stamp)
                best = min(group, key=lambda c: math.hypot(c.shape.centroid[0] - x, c.shape.centroid[1] - y))
                pairs.append((best, track))
            fresh.extend([None] * (len(group) - 1))
        coast = self.settings.coast
        tracks = [t for t in self._tracks.values() if not t.label and stamp - t.last_seen <= coast]
        if not plain or not tracks:
            fresh.extend(plain)
            return pairs, fresh
        cost, inside = self._costs(stamp, plain, tracks)
        rows, cols = linear_sum_assignment(cost)
        joined: dict[int, _Candidate] = {}  # column -> the candidate that joined the track
        for row, col in zip(rows.tolist(), cols.tolist(), strict=True):
            if cost[row, col] < _NO:
                joined[col] = plain[row]
        taken = {id(c) for c in joined.values()}
        for row, candidate in enumerate(plain):
            if id(candidate) in taken:
                continue
            col = self._piece_of(candidate, inside[row], joined)
            if col is None:
                fresh.append(candidate)
            else:
                joined[col].pieces.append(candidate.shape)
        for col, candidate in joined.items():
            if candidate.pieces:
                candidate.pieces.insert(0, candidate.shape)
                candidate.shape = combine(candidate.pieces)
            pairs.append((candidate, tracks[col]))
        return pairs, fresh

    def _costs(
        self, stamp: float, plain: list[_Candidate], tracks: list[_Track]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Cost (candidates x tracks): distance to the prediction over the gate plus one minus the
        overlap; ``_NO`` outside the gate without overlap. Also how much of each candidate lies
        inside each track (shared area / the candidate's area)."""
        s = self.settings
        centroids = np.array([c.shape.centroid for c in plain])
        predicted = np.array([t.position(stamp) for t in tracks])
        distance = np.hypot(*(centroids[:, None, :] - predicted[None, :, :]).transpose(2, 0, 1))
        overlap = np.zeros(distance.shape)
        inside = np.zeros(distance.shape)
        boxes = np.array([c.shape.bounds for c in plain])
        for col, track in enumerate(tracks):
            velocity = track.velocity()
            for seen in track.fresh(s.outline_age):
                dt = stamp - seen.stamp
                offset = (velocity[0] * dt, velocity[1] * dt)
                low_x, low_y, high_x, high_y = seen.shape.bounds
                near = (
                    (boxes[:, 0] < high_x + offset[0])
                    & (boxes[:, 2] > low_x + offset[0])
                    & (boxes[:, 1] < high_y + offset[1])
                    & (boxes[:, 3] > low_y + offset[1])
                )
                for row in np.flatnonzero(near).tolist():
                    shape = plain[row].shape
                    shared = overlap_area(shape, seen.shape, offset)
                    if shared > 0:
                        overlap[row, col] = max(overlap[row, col], shared / min(shape.area, seen.shape.area))
                        inside[row, col] = max(inside[row, col], shared / shape.area)
        allowed = (distance <= s.gate) | (overlap >= s.min_overlap)
        cost = np.minimum(distance / s.gate, 2.0) + (1.0 - overlap)
        return np.where(allowed, cost, _NO), inside

    def _piece_of(
        self, candidate: _Candidate, inside: np.ndarray, joined: dict[int, _Candidate]
    ) -> int | None:
        """The track (column) this unmatched candidate is a second piece of, if any."""
        best: int | None = None
        for col, other in joined.items():
            if inside[col] < self.settings.merge_overlap or (
                best is not None and inside[col] <= inside[best]
            ):
                continue
            if _gap(candidate.shape, other.shape, self.settings.merge_gap) <= self.settings.merge_gap:
                best = col
        return best

    # -- updates -----------------------------------------------------------------------------------

    def _sigma2(self, shape: Shape) -> float:
        return self.settings.measurement_noise**2 + (0.1 * shape.radius) ** 2

    def _evidence(self, confidence: float) -> float:
        return confidence if confidence > 0 else self.settings.default_confidence

    def _update(self, track: _Track, camera: str, stamp: float, candidate: _Candidate) -> None:
        track.motion.update(stamp, candidate.shape.centroid, self._sigma2(candidate.shape))
        seen = track.seen.get(camera)
        if seen is None or seen.stamp <= stamp:
            track.seen[camera] = _Seen(stamp, candidate.shape)
        track.last_seen = max(track.last_seen, stamp)
        track.evidence = 1 - (1 - track.evidence) * (1 - self._evidence(candidate.confidence))
        speed = track.motion.average_speed(self.settings.stationary_time)
        track.stationary = speed is not None and speed < self.settings.stationary_speed

    def _create(self, camera: str, stamp: float, candidate: _Candidate) -> None:
        shape = candidate.shape
        motion = Motion(self._noise, self._window, stamp, shape.centroid, self._sigma2(shape))
        track = _Track(self._next_id, candidate.label, motion, self._evidence(candidate.confidence), stamp)
        track.seen[camera] = _Seen(stamp, shape)
        self._next_id += 1
        self._tracks[track.track_id] = track
        if track.label:
            self._by_label[track.label] = track

    def _misses(self, stamp: float, field_of_view: Sequence[Point], updated: set[int]) -> None:
        try:
            polygon = np.asarray(field_of_view, dtype=float)
        except (TypeError, ValueError):
            return
        if (
            polygon.ndim != 2
            or polygon.shape[0] < 3
            or polygon.shape[1] != 2
            or not np.isfinite(polygon).all()
        ):
            return
        others = [t for t in self._tracks.values() if id(t) not in updated and t.last_seen < stamp]
        if not others:
            return
        inside = contains(polygon, np.array([t.position(stamp) for t in others]))
        for track, missed in zip(others, inside.tolist(), strict=True):
            if missed:
                track.evidence *= 1 - self.settings.miss_weight

    # -- wrong poses -------------------------------------------------------------------------------

    def _compare(self, camera: str, stamp: float, candidate: _Candidate, track: _Track) -> None:
        """Record how far ``camera``'s outline is from each other camera's of the same track."""
        s = self.settings
        vx, vy = track.velocity()
        cx, cy = candidate.shape.centroid
        for other, seen in track.seen.items():
            dt = stamp - seen.stamp
            if other == camera or abs(dt) > s.pose_max_age or self._pose.is_flagged(other):
                continue
            if not 2 / 3 <= candidate.shape.area / seen.shape.area <= 3 / 2:
                continue  # one of them sees only part of the object
            residual = math.hypot(
                cx - seen.shape.centroid[0] - vx * dt, cy - seen.shape.centroid[1] - vy * dt
            )
            self._pose.record(camera, other, track.track_id, stamp, residual)

    # -- queries -----------------------------------------------------------------------------------

    def tracks(
        self, at: float, region: tuple[float, float, float, float] | None = None, since: float | None = None
    ) -> list[TrackView]:
        """Every live track predicted to time ``at`` (not gone), optionally only those whose
        predicted outline overlaps ``region`` (min_x, min_y, max_x, max_y); ``seen_by`` counts
        frames with stamp >= ``since`` (default: ``at`` minus the coast time)."""
        s = self.settings
        if since is None:
            since = at - s.coast
        views = []
        for track in self._tracks.values():
            age = at - track.last_seen
            if age > s.coast:
                continue
            vx, vy = track.velocity()
            fresh = track.fresh(s.outline_age)
            outline = union_outline(
                [(seen.shape, (vx * (at - seen.stamp), vy * (at - seen.stamp))) for seen in fresh]
            )
            if region is not None and not _overlaps(outline, region):
                continue
            freshness = min(1.0, 1.0 - age / s.coast)
            views.append(
                TrackView(
                    track.track_id,
                    outline,
                    track.position(at),
                    (vx, vy),
                    float(min(1.0, max(0.0, track.evidence * freshness))),
                    track.stationary,
                    tuple(sorted(c for c, seen in track.seen.items() if seen.stamp >= since)),
                    track.label,
                    track.last_seen,
                )
            )
        return views

    def expire(self, now: float) -> list[int]:
        """Tracks unseen for longer than the coast time at ``now``: removed, their ids returned once."""
        self._end_unseen(now)
        gone, self._gone = self._gone, []
        return gone

    def flagged(self) -> dict[str, str]:
        """Vision systems left out of fusion now, each with the reason (for /diagnostics)."""
        return self._pose.flagged()

    def forget(self, vision_system: str) -> None:
        """``vision_system`` unregistered or was removed: drop its pose check (its tracks coast)."""
        self._pose.forget(vision_system)


def _gap(a: Shape, b: Shape, limit: float) -> float:
    """Distance between two outlines; their bounds' distance when that exceeds ``limit`` already."""
    dx = max(a.bounds[0] - b.bounds[2], b.bounds[0] - a.bounds[2], 0.0)
    dy = max(a.bounds[1] - b.bounds[3], b.bounds[1] - a.bounds[3], 0.0)
    if math.hypot(dx, dy) > limit:
        return math.hypot(dx, dy)
    return float(a.polygon().distance(b.polygon()))


def _overlaps(outline: Sequence[Point], region: Box) -> bool:
    points = np.asarray(outline)
    low, high = points.min(axis=0), points.max(axis=0)
    if high[0] < region[0] or low[0] > region[2] or high[1] < region[1] or low[1] > region[3]:
        return False
    return bool(Polygon(points).intersects(box(*region)))
