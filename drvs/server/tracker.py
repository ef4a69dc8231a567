"""The fusion tracker: every camera's outlines, frame by frame, as one table of tracked objects in ``map``.

:meth:`Tracker.frame` associates one camera frame's outlines with the tracks
(:mod:`drvs.server.track_association`: gating on each track's position predicted to the frame's
capture stamp, a global assignment on centroid distance and outline overlap, a tag's label as a
hard constraint), updates each track's constant-velocity filter (:mod:`drvs.server.track_motion`)
and starts tracks for the rest; :meth:`Tracker.tracks` predicts them to a time. Cameras whose
outlines disagree with their neighbours' are left out (:mod:`drvs.server.pose_check`). Stamps are
arguments: no clock here. Not thread-safe (the caller holds a lock). The method and every
constant: docs/fusion-tracking.md.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np
from shapely.geometry import Polygon, box

from drvs.server.outlines import Shape, clean, contains, polygon_centroid, union_outline
from drvs.server.pose_check import PoseCheck
from drvs.server.track_association import Candidate, Rules, Seen, Track, associate
from drvs.server.track_motion import Motion, MotionNoise

__all__ = ['DEFAULTS', 'FrameResult', 'Observation', 'TrackView', 'Tracker', 'TrackerSettings']

Point = tuple[float, float]
Box = tuple[float, float, float, float]


EXTENDED = 0.4
"""Metres: an object whose outline's half-diagonal reaches this (a shelf, a cart, not a person) is
placed by the union of the cameras' outlines, not by each camera's own (:meth:`Tracker._measured`)."""


@dataclass(frozen=True)
class Observation:
    """One outline from one camera frame, in map metres."""

    outline: tuple[Point, ...]
    """Counter-clockwise polygon (at least 3 points; a tag's: 4 corners, corner 0 first)."""
    label: str = ''
    """A tag's identity (e.g. ``'tag36h11:3'``): one track per label, never two labels in a track."""
    confidence: float = 0.0
    """The camera's own, 0..1 (0: unknown)."""
    height: float = 0.0
    """Metres above the floor of the object's top, when the algorithm measures it (0: unknown)."""
    clearance: float = 0.0
    """Metres above the floor of the object's underside, when the algorithm measured room under it
    (0: on the floor or unknown)."""


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
    """Outlines that joined existing tracks (merged pieces and shared blobs included)."""
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
    shared: int = 0
    """Of ``associated``: outlines of several tracked objects at once (two people in one blob); they
    neither move those tracks nor start one, and count as no miss."""
    stale: bool = False
    """The frame was captured more than the coast time before the newest frame fused: nothing
    fused, every outline counted in ``skipped`` (a camera showing an old frame, or a clock far
    behind the others')."""


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
    height: float = 0.0
    """Metres: the highest top its cameras' recent outlines measured (as fresh as those :attr:`outline`
    may be made of); 0 when none measured one."""
    clearance: float = 0.0
    """Metres: the room under it, the largest clearance among those outlines with its top
    (:meth:`~drvs.server.track_association.Track.clearance`); 0 when none measured one."""


class Tracker:
    """Fuses frames of many cameras into tracks (see the module docstring)."""

    def __init__(self, settings: TrackerSettings = DEFAULTS):
        self.settings = settings
        self._noise = MotionNoise(settings.acceleration_noise, settings.initial_speed)
        self._window = max(settings.reorder_window, settings.stationary_time) + 0.5
        self._tracks: dict[int, Track] = {}
        self._by_label: dict[str, Track] = {}
        self._next_id = 1
        self._gone: list[int] = []  # ended in frame() (a label seen again, a full table), not yet reported
        self._newest: float | None = None  # the newest frame stamp fused
        self._rules = Rules(
            settings.gate,
            settings.coast,
            settings.min_overlap,
            settings.merge_overlap,
            settings.merge_gap,
            settings.outline_age,
        )
        self._pose = PoseCheck(settings.pose_tolerance, settings.pose_min_objects, settings.pose_window)

    @property
    def newest(self) -> float | None:
        """The capture stamp of the newest frame fused (None before the first)."""
        return self._newest

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
        observations = [] if observations is None else list(observations)
        if not isinstance(stamp, int | float) or not math.isfinite(stamp):
            return FrameResult(0, 0, 0, False, skipped=len(observations))
        if self._newest is not None and stamp < self._newest - self.settings.coast:
            return FrameResult(0, 0, 0, False, skipped=len(observations), stale=True)
        self._newest = stamp if self._newest is None else max(self._newest, stamp)
        candidates, skipped = self._candidates(observations)
        association = associate(stamp, candidates, list(self._tracks.values()), self._by_label, self._rules)
        for track in association.ended:
            self._remove(track)
            self._gone.append(track.track_id)
        pairs, fresh, skipped = association.pairs, association.fresh, skipped + association.skipped
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
            covered = {id(track) for _, tracks in association.shared for track in tracks}
            self._misses(stamp, field_of_view, {id(track) for _, track in pairs} | covered)
        merged = sum(len(c.pieces) - 1 for c, _ in pairs if c.pieces)
        shared = len(association.shared)
        return FrameResult(
            len(pairs) + merged + shared,
            created,
            untracked,
            False,
            skipped=skipped,
            merged=merged,
            shared=shared,
        )

    def _candidates(self, observations: Sequence[Observation]) -> tuple[list[Candidate], int]:
        candidates: list[Candidate] = []
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
            height, clearance = (_metres(getattr(observation, name, 0.0)) for name in ('height', 'clearance'))
            confidence = min(1.0, max(0.0, float(confidence)))
            candidates.append(Candidate(shape, label, confidence, height=height, clearance=clearance))
        return candidates, skipped

    def _end_unseen(self, stamp: float) -> None:
        """Tracks unseen for longer than the coast time at ``stamp``: out of the table, to report."""
        for track in [t for t in self._tracks.values() if stamp - t.last_seen > self.settings.coast]:
            self._remove(track)
            self._gone.append(track.track_id)

    def _remove(self, track: Track) -> None:
        del self._tracks[track.track_id]
        if self._by_label.get(track.label) is track:
            del self._by_label[track.label]

    # -- updates -----------------------------------------------------------------------------------

    def _sigma2(self, shape: Shape) -> float:
        return self.settings.measurement_noise**2 + (0.1 * shape.radius) ** 2

    def _evidence(self, confidence: float) -> float:
        return confidence if confidence > 0 else self.settings.default_confidence

    def _update(self, track: Track, camera: str, stamp: float, candidate: Candidate) -> None:
        centroid = self._measured(track, camera, stamp, candidate.shape)
        track.motion.update(stamp, centroid, self._sigma2(candidate.shape))
        seen = track.seen.get(camera)
        if seen is None or seen.stamp <= stamp:
            track.seen[camera] = Seen(stamp, candidate.shape, candidate.height, candidate.clearance)
        track.last_seen = max(track.last_seen, stamp)
        track.fused = None
        track.evidence = 1 - (1 - track.evidence) * (1 - self._evidence(candidate.confidence))
        speed = track.motion.average_speed(self.settings.stationary_time)
        track.stationary = speed is not None and speed < self.settings.stationary_speed

    def _measured(self, track: Track, camera: str, stamp: float, shape: Shape) -> Point:
        """Where the frame puts the track: the centroid of this camera's outline together with the
        other cameras' recent ones (moved along the velocity to ``stamp``). A camera that sees only
        part of a big object (a shelf wider than its view) then moves the track no more than the
        part it adds: its own centroid alone would swing between the cameras' halves and read as
        motion."""
        s = self.settings
        age = s.coast if track.stationary else s.outline_age
        others = [
            seen for other, seen in track.seen.items() if other != camera and abs(stamp - seen.stamp) <= age
        ]
        if not others or max(seen.shape.radius for seen in [*others, Seen(stamp, shape)]) < EXTENDED:
            return shape.centroid  # a small object: every camera sees all of it
        vx, vy = track.velocity()
        moves = [(shape, (0.0, 0.0))] + [
            (seen.shape, (vx * (stamp - seen.stamp), vy * (stamp - seen.stamp))) for seen in others
        ]
        return polygon_centroid(union_outline(moves)) or shape.centroid

    def _create(self, camera: str, stamp: float, candidate: Candidate) -> None:
        shape = candidate.shape
        motion = Motion(self._noise, self._window, stamp, shape.centroid, self._sigma2(shape))
        track = Track(self._next_id, candidate.label, motion, self._evidence(candidate.confidence), stamp)
        track.seen[camera] = Seen(stamp, shape, candidate.height, candidate.clearance)
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

    def _compare(self, camera: str, stamp: float, candidate: Candidate, track: Track) -> None:
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
            # A stationary object's outlines stay valid however old: a shelf wider than one camera's
            # view is the union of every camera's part, whenever each was seen (within the coast time).
            outline_age = s.coast if track.stationary else s.outline_age
            outline = track.outline(at, outline_age, EXTENDED)
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
                    track.height(outline_age),
                    track.clearance(outline_age),
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


def _metres(value: object) -> float:
    """A height from an observation: a number >= 0, else 0 (not measured)."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
        return 0.0
    return float(value)


def _overlaps(outline: Sequence[Point], region: Box) -> bool:
    points = np.asarray(outline)
    low, high = points.min(axis=0), points.max(axis=0)
    if high[0] < region[0] or low[0] > region[2] or high[1] < region[1] or low[1] > region[3]:
        return False
    return bool(Polygon(points).intersects(box(*region)))
