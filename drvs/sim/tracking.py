"""The fused tracks of a run measured against ground truth: CLEAR MOT and identity metrics.

Each ``/drvs/objects`` message is one period: its tracks (an algorithm string, a track id and
the outline's centroid) against where the bodies that algorithm is meant to find truly were at
the message's stamp. Per algorithm, py-motmetrics accumulates the periods and gives MOTA, IDF1,
ID switches and fragmentations; this module adds position errors, duplicates and ID switches
per 100 track-seconds. Definitions and the matching rule: docs/running-scenarios.md
("Tracking metrics").
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from shapely.geometry import Polygon

from drvs.sim.world import World

GATE = 0.5
"""Metres: a track matches a body only if its centroid lies at most this far from the body's centre."""
TARGETS = {
    'duplicates': (0, 'at most'),
    'idf1': (0.9, 'at least'),
    'switches_per_100_track_seconds': (1.0, 'at most'),
    'position_error_p50_tagged_robots': (0.05, 'at most'),
    'position_error_p50_people': (0.15, 'at most'),
}
"""Issue 25's targets: name -> (limit, 'at most' or 'at least')."""
NO_OBJECTS = 'no /drvs/objects messages: the run had no fused tracks (per-camera requests only)'
"""Why a run's tracking block holds no metrics when nothing was fused."""
MOT_METRICS = (
    'num_frames',
    'num_objects',
    'num_matches',
    'num_misses',
    'num_false_positives',
    'num_switches',
    'num_fragmentations',
    'mota',
    'idf1',
)
"""What py-motmetrics computes for each algorithm (and over all of them)."""
KINDS = {'self': 'robot', 'robot': 'robot', 'station': 'station', 'human': 'person', 'obstacle': 'obstacle'}
"""The roles of a world's colour models whose bodies are known: role -> kind of body."""


@dataclass(frozen=True)
class TrackPoint:
    """One object of a ``/drvs/objects`` message: which algorithm, which track, its centroid in ``map``."""

    algorithm: str
    track_id: int
    x: float
    y: float


@dataclass(frozen=True)
class TrackPeriod:
    """One ``/drvs/objects`` message: its stamp (ROS seconds) and every current track."""

    stamp: float
    tracks: tuple[TrackPoint, ...]


@dataclass(frozen=True)
class TruthClass:
    """The bodies one algorithm string is meant to find (by the world's colour models)."""

    algorithm: str
    kind: str  # robot, station, person or obstacle (of the first role that uses the string)
    roles: tuple[str, ...]  # e.g. ('human',), ('robot1.self',)
    bodies: tuple[str, ...]

    @property
    def tagged(self) -> bool:
        """Its tracks come from tags (the algorithm is ``apriltag``)."""
        return self.algorithm.split(':', 1)[0] == 'apriltag'


def centroid(outline: Sequence[tuple[float, float]]) -> tuple[float, float]:
    """Where a track is: its outline's centroid (of its area; of its points for a degenerate one).

    >>> centroid([(0.0, 0.0), (2.0, 0.0), (2.0, 1.0), (0.0, 1.0)])
    (1.0, 0.5)
    """
    if len(outline) >= 3:
        polygon = Polygon(outline)
        if polygon.is_valid and polygon.area > 0:
            return polygon.centroid.x, polygon.centroid.y
    if not outline:
        return math.nan, math.nan
    x, y = np.mean(np.asarray(outline, dtype=float), axis=0)
    return float(x), float(y)


def truth_classes(world: World) -> dict[str, TruthClass]:
    """Algorithm string -> the bodies it is meant to find, from the world's colour models.

    ``self`` finds its robot, ``station`` its station, ``robot`` every robot, ``human`` the
    humans, ``obstacle`` the static objects. One string used for several roles finds all of
    their bodies; the kind is that of its first role.
    """
    humans = tuple(o.name for o in world.objects if o.kind == 'human')
    statics = tuple(o.name for o in world.objects if o.kind == 'static')
    robots = tuple(r.name for r in world.robots)
    classes: dict[str, TruthClass] = {}

    def add(algorithm: str, role: str, label: str, bodies: tuple[str, ...]) -> None:
        known = classes.get(algorithm)
        if known is None:
            classes[algorithm] = TruthClass(algorithm, KINDS[role], (label,), bodies)
        elif label not in known.roles:
            merged = known.bodies + tuple(b for b in bodies if b not in known.bodies)
            classes[algorithm] = TruthClass(algorithm, known.kind, (*known.roles, label), merged)

    for robot in world.robots:
        models = robot.colour_models
        own = f'{robot.name}.' if len(world.robots) > 1 else ''
        add(models['self'], 'self', f'{own}self', (robot.name,))
        add(models['station'], 'station', f'{own}station', (robot.station.name,))
    shared = world.robots[0].colour_models
    for role, bodies in (('human', humans), ('obstacle', statics), ('robot', robots)):
        if role in shared:
            add(shared[role], role, role, bodies)
    return classes


def truth_at(
    truth: Mapping[str, Sequence[tuple[float, float, float]]],
    fixed: Mapping[str, tuple[float, float]],
    names: Sequence[str],
    stamps: Sequence[float],
) -> np.ndarray:
    """Where each body of ``names`` was at each stamp: an array (stamps, names, 2).

    ``truth``: the moving bodies' recorded (t, x, y), in time order, interpolated linearly
    (before the first and after the last sample, the nearest one); ``fixed``: where the
    bodies that never move stand. A body in neither is NaN.
    """
    result = np.full((len(stamps), len(names), 2), np.nan)
    at = np.asarray(stamps, dtype=float)
    for j, name in enumerate(names):
        samples = truth.get(name)
        if samples:
            t, x, y = np.asarray(samples, dtype=float).T
            result[:, j, 0] = np.interp(at, t, x)
            result[:, j, 1] = np.interp(at, t, y)
        elif name in fixed:
            result[:, j] = fixed[name]
    return result


def duplicates(bodies: np.ndarray, tracks: np.ndarray, gate: float = GATE) -> int:
    """Tracks too many in one period: each track within ``gate`` of a body counts for the nearest
    body; a body with n > 1 such tracks is n - 1 duplicates (one real object reported n times).

    >>> duplicates(np.array([[0.0, 0.0], [3.0, 0.0]]), np.array([[0.1, 0.0], [-0.1, 0.0], [3.0, 0.2]]))
    1
    """
    if not len(bodies) or not len(tracks):
        return 0
    distance = np.linalg.norm(tracks[:, None, :] - bodies[None, :, :], axis=2)
    near = distance.min(axis=1) <= gate
    counts = np.bincount(distance.argmin(axis=1)[near], minlength=len(bodies))
    return int(np.maximum(counts - 1, 0).sum())


def _rounded(value: float | None, digits: int = 3) -> float | None:
    if value is None or not math.isfinite(value):
        return None
    return round(float(value), digits)


@dataclass
class _Counts:
    """What motmetrics does not count, for one algorithm or over all."""

    periods: int = 0
    duplicates: int = 0
    periods_with_duplicates: int = 0
    track_seconds: float = 0.0
    tracks: int = 0


def _lifetimes(spans: Mapping[int, list[float]]) -> float:
    """Track-seconds: each track's last stamp minus its first, summed."""
    return sum(last - first for first, last in spans.values())


def evaluate(
    world: World,
    truth: Mapping[str, Sequence[tuple[float, float, float]]],
    periods: Iterable[TrackPeriod],
    gate: float = GATE,
) -> dict:
    """The tracking block of ``summary.json``: per algorithm, per kind and over all, with the targets.

    ``truth``: each moving body's (t, x, y) samples in time order (the robots and humans; the
    others stand where the world file puts them); ``periods``: every ``/drvs/objects`` message.
    An algorithm is measured over the periods from its first track to its last (before, nobody
    had asked for it; after, nobody asks any more), and only if the world says which bodies it
    finds; the others are listed under ``not_measured``.
    """
    import motmetrics  # here: it imports pandas, which the report needs only with fused tracks

    periods = sorted(periods, key=lambda p: p.stamp)
    if not periods:
        return {'measured': False, 'reason': NO_OBJECTS, 'gate': gate}
    classes = truth_classes(world)
    spans: dict[str, list[float]] = {}
    for period in periods:
        for track in period.tracks:
            spans.setdefault(track.algorithm, [period.stamp, period.stamp])[1] = period.stamp
    not_measured = {}
    for algorithm in spans.keys() - classes.keys():
        ids = {t.track_id for p in periods for t in p.tracks if t.algorithm == algorithm}
        not_measured[algorithm] = f'{len(ids)} track(s): no role of the world file uses this algorithm'
    measured = [a for a in spans if a in classes]
    if not measured:
        return {
            'measured': False,
            'reason': 'no track of an algorithm the world file names: nothing to compare with ground truth',
            'gate': gate,
            'periods': len(periods),
            'not_measured': not_measured,
        }
    fixed = {body.name: body.position for body in world.objects if not body.moving}
    fixed |= {robot.station.name: robot.station.position for robot in world.robots}
    names = sorted({name for a in measured for name in classes[a].bodies})
    index = {name: j for j, name in enumerate(names)}
    where = truth_at(truth, fixed, names, [p.stamp for p in periods])

    accumulators, counts = {}, {}
    for algorithm in measured:
        bodies_of = classes[algorithm].bodies
        columns = [index[name] for name in bodies_of]
        accumulator = accumulators[algorithm] = motmetrics.MOTAccumulator(auto_id=False)
        count = counts[algorithm] = _Counts()
        lifetimes: dict[int, list[float]] = {}
        first, last = spans[algorithm]
        for frame, period in enumerate(periods):
            if not first <= period.stamp <= last:
                continue
            seen: dict[int, TrackPoint] = {}
            for track in period.tracks:
                if track.algorithm == algorithm:
                    seen.setdefault(track.track_id, track)
            bodies = where[frame, columns]
            tracks = np.array([(t.x, t.y) for t in seen.values()]).reshape(-1, 2)
            distance = np.sqrt(motmetrics.distances.norm2squared_matrix(bodies, tracks, max_d2=gate**2))
            # Ids are numbers to py-motmetrics: a body is its place in the world's list of names.
            accumulator.update(columns, list(seen), distance, frameid=frame)
            count.periods += 1
            extra = duplicates(bodies, tracks, gate)
            count.duplicates += extra
            count.periods_with_duplicates += extra > 0
            for track_id in seen:
                lifetimes.setdefault(track_id, [period.stamp, period.stamp])[1] = period.stamp
        count.track_seconds, count.tracks = _lifetimes(lifetimes), len(lifetimes)
    block = {
        'measured': True,
        'gate': gate,
        'periods': len(periods),
        'span': round(periods[-1].stamp - periods[0].stamp, 2),
        **_metrics_block(accumulators, counts, classes),
        'not_measured': not_measured,
    }
    block['targets'] = targets(block)
    return block


def kind_of(truth_class: TruthClass) -> str:
    """Where a class's position errors are pooled: people, tagged robots, robots, stations or obstacles."""
    if truth_class.kind == 'robot':
        return 'tagged robots' if truth_class.tagged else 'robots'
    return {'person': 'people', 'station': 'stations', 'obstacle': 'obstacles'}[truth_class.kind]


def _errors(errors: np.ndarray) -> dict:
    """Position errors (metres) of the matched tracks: mean, p50 and p95 (None without any)."""
    if not len(errors):
        return {'position_error_mean': None, 'position_error_p50': None, 'position_error_p95': None}
    return {
        'position_error_mean': _rounded(float(errors.mean())),
        'position_error_p50': _rounded(float(np.percentile(errors, 50))),
        'position_error_p95': _rounded(float(np.percentile(errors, 95))),
    }


def _metrics_block(accumulators: dict, counts: dict[str, _Counts], classes: dict[str, TruthClass]) -> dict:
    """``overall``, ``kinds`` (position errors pooled per kind) and ``algorithms`` (a row each)."""
    import motmetrics

    names = list(accumulators)
    table = motmetrics.metrics.create().compute_many(
        list(accumulators.values()), metrics=list(MOT_METRICS), names=names, generate_overall=len(names) > 1
    )
    errors = {}
    for algorithm, accumulator in accumulators.items():
        events = accumulator.mot_events
        errors[algorithm] = events.loc[events['Type'].isin(('MATCH', 'SWITCH')), 'D'].to_numpy(dtype=float)
    rows = []
    for algorithm in names:
        truth_class = classes[algorithm]
        rows.append(
            {
                'algorithm': algorithm,
                'kind': kind_of(truth_class),
                'roles': list(truth_class.roles),
                'bodies': list(truth_class.bodies),
                **_row(table.loc[algorithm], counts[algorithm]),
                **_errors(errors[algorithm]),
            }
        )
    total = _Counts(
        periods=max(c.periods for c in counts.values()),
        duplicates=sum(c.duplicates for c in counts.values()),
        periods_with_duplicates=sum(c.periods_with_duplicates for c in counts.values()),
        track_seconds=sum(c.track_seconds for c in counts.values()),
        tracks=sum(c.tracks for c in counts.values()),
    )
    overall = table.loc['OVERALL'] if len(names) > 1 else table.loc[names[0]]
    kinds: dict[str, list[np.ndarray]] = {}
    for row in rows:
        kinds.setdefault(row['kind'], []).append(errors[row['algorithm']])
    return {
        'overall': {**_row(overall, total), **_errors(np.concatenate(list(errors.values())))},
        'kinds': {
            kind: {'matches': int(sum(len(e) for e in pooled)), **_errors(np.concatenate(pooled))}
            for kind, pooled in sorted(kinds.items())
        },
        'algorithms': rows,
    }


def _row(mot, count: _Counts) -> dict:
    """One row of figures: motmetrics' and this module's counts."""
    switches = int(mot['num_switches'])
    seconds = count.track_seconds
    return {
        'periods': count.periods,
        'objects': int(mot['num_objects']),
        'matches': int(mot['num_matches']),
        'misses': int(mot['num_misses']),
        'false_positives': int(mot['num_false_positives']),
        'mota': _rounded(mot['mota']),
        'idf1': _rounded(mot['idf1']),
        'switches': switches,
        'fragmentations': int(mot['num_fragmentations']),
        'duplicates': count.duplicates,
        'periods_with_duplicates': count.periods_with_duplicates,
        'tracks': count.tracks,
        'track_seconds': round(seconds, 2),
        'switches_per_100_track_seconds': _rounded(100.0 * switches / seconds) if seconds > 0 else None,
    }


def targets(block: dict) -> dict[str, dict]:
    """Issue 25's targets on a measured block: name -> {value, target, met, at_most}.

    The position targets take the errors pooled over the rows of tagged robots (an ``apriltag``
    algorithm finding robots) and of people; a value is None when the run had none (``met`` false).
    """
    overall, kinds = block['overall'], block['kinds']
    values = {
        'duplicates': overall['duplicates'],
        'idf1': overall['idf1'],
        'switches_per_100_track_seconds': overall['switches_per_100_track_seconds'],
        'position_error_p50_tagged_robots': kinds.get('tagged robots', {}).get('position_error_p50'),
        'position_error_p50_people': kinds.get('people', {}).get('position_error_p50'),
    }
    result = {}
    for name, (limit, sense) in TARGETS.items():
        value = values[name]
        at_most = sense == 'at most'
        met = value is not None and (value <= limit if at_most else value >= limit)
        result[name] = {'value': value, 'target': limit, 'met': bool(met), 'at_most': at_most}
    return result
