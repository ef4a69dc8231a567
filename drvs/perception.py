"""What the blind robot knows from DRVS answers: request ids, superseded answers, merged objects.

The robot asks DRVS with one colour model per role (``self``, ``station``,
``obstacle``, ``human``, as in the paper's Algorithm 3) and gets zero or more
callbacks per request, one from each vision system that found something, in any
order, possibly late or twice. This module turns them into facts:

- Request ids are ``<role>-<seq>``, ``seq`` counting up per role, so a callback
  names its role and how recent its question was (:class:`RequestBook`).
- Localisation (``self``, ``station``): the answers to the newest request that
  has any answer form one *round*; the outlines of a round are merged (the same
  object seen by two cameras is one object) and the object's centroid is the
  fix. An answer to an older request than the current round is superseded and
  ignored; a repeated answer replaces its first copy instead of counting twice.
  When a role is asked with ``apriltag``, each object is a tag's four corners in
  a fixed order: the fix is the tag's centre and it has a *heading* (the tag's
  yaw, :func:`drvs.algorithms.apriltag.tag_pose`, averaged over the cameras that
  saw it); other algorithms give no heading.
- Obstacles (``obstacle``, ``human``): each vision system's newest answer per
  role replaces its earlier ones (a late answer to an older request is
  ignored); the robot keeps them in a :class:`drvs.occupancy.ObstacleMemory`.
  :func:`merge_outlines` unions overlapping outlines of one role, and
  :func:`exclude_bodies` drops outlines that are really the robot or the station.

Region-of-interest policy (paper, section 4.3): localisation requests cover the
whole floor (:func:`whole_floor`); obstacle requests only the box spanned by the
robot and the station plus a margin (:func:`obstacle_roi`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from shapely.geometry import Point as Point2
from shapely.geometry import Polygon
from shapely.ops import unary_union

ROLES = ('self', 'station', 'obstacle', 'human')
LOCALISATION_ROLES = ('self', 'station')
OBSTACLE_ROLES = ('obstacle', 'human')

Point = tuple[float, float]
TAG_MATCH = 0.05
"""Metres: a tag's centre this close to (or inside) a merged object belongs to it."""
Box = tuple[float, float, float, float]


class PerceptionError(ValueError):
    """A callback the robot cannot use; the message names the field and the problem."""


def whole_floor(floor_size: tuple[float, float]) -> Box:
    return (0.0, 0.0, float(floor_size[0]), float(floor_size[1]))


def obstacle_roi(robot: Point, station: Point, margin: float, floor_size: tuple[float, float]) -> Box:
    """The box spanned by the robot and the station, grown by ``margin``, clipped to the floor.

    >>> obstacle_roi((1.0, 2.0), (3.0, 1.0), 0.5, (7.0, 5.5))
    (0.5, 0.5, 3.5, 2.5)
    """
    return (
        max(0.0, min(robot[0], station[0]) - margin),
        max(0.0, min(robot[1], station[1]) - margin),
        min(float(floor_size[0]), max(robot[0], station[0]) + margin),
        min(float(floor_size[1]), max(robot[1], station[1]) + margin),
    )


def to_polygon(points: Sequence[Sequence[float]]) -> Polygon | None:
    """An outline as a valid shapely polygon, or None when it has no area."""
    if len(points) < 3:
        return None
    polygon = Polygon([(float(p[0]), float(p[1])) for p in points])
    if not polygon.is_valid:
        polygon = polygon.buffer(0)
    if polygon.is_empty or polygon.area <= 0:
        return None
    if polygon.geom_type == 'MultiPolygon':
        polygon = max(polygon.geoms, key=lambda part: part.area)
    return polygon


def merge_outlines(outlines: Iterable[Polygon]) -> list[Polygon]:
    """Union overlapping (or touching) outlines: one polygon per object, however many cameras saw it."""
    outlines = [o for o in outlines if not o.is_empty]
    if not outlines:
        return []
    merged = unary_union(outlines)
    parts = merged.geoms if hasattr(merged, 'geoms') else [merged]
    return [part for part in parts if part.geom_type == 'Polygon' and part.area > 0]


def exclude_bodies(outlines: Iterable[Polygon], bodies: Iterable[Polygon], fraction: float = 0.5) -> list:
    """Outlines minus those mostly covered (more than ``fraction`` of their area) by one of ``bodies``.

    The robot and the station are never obstacles, even if an obstacle colour
    model happens to match them.
    """
    bodies = [b for b in bodies if b is not None and not b.is_empty]
    return [
        outline
        for outline in outlines
        if not any(outline.intersection(body).area > fraction * outline.area for body in bodies)
    ]


class RequestBook:
    """Issues request ids ``<role>-<seq>`` and parses the ids that callbacks echo."""

    def __init__(self):
        self._issued = {role: 0 for role in ROLES}

    def issue(self, role: str) -> str:
        if role not in self._issued:
            raise PerceptionError(f'role: expected one of {", ".join(ROLES)}, got {role!r}')
        self._issued[role] += 1
        return f'{role}-{self._issued[role]}'

    def issued(self, role: str) -> int:
        """How many requests for ``role`` were issued (the newest sequence number)."""
        return self._issued[role]

    def parse(self, request_id: str) -> tuple[str, int]:
        """(role, seq) of an id this book issued.

        :raises PerceptionError: for an id of another form, role or a sequence not issued yet.
        """
        role, _, seq_text = request_id.rpartition('-')
        if role not in self._issued or not seq_text.isdigit():
            raise PerceptionError(
                f'request_id: expected <role>-<number> with a role of ours, got {request_id!r}'
            )
        seq = int(seq_text)
        if not 1 <= seq <= self._issued[role]:
            raise PerceptionError(f'request_id: {request_id!r} was never issued by this robot')
        return role, seq


@dataclass(frozen=True)
class Fix:
    """Where one object (the robot or its station) was, from one round of answers."""

    position: Point
    outline: Polygon
    stamp: float  # when the frames were captured (mean over the round's answers)
    seq: int
    vision_systems: tuple[str, ...]
    heading: float | None = None  # radians in map, when the algorithm gives one (a tag)


@dataclass(frozen=True)
class Answer:
    """One accepted callback."""

    role: str
    seq: int
    vision_system: str
    stamp: float
    outlines: tuple[Polygon, ...]
    poses: tuple[tuple[float, float, float], ...] = ()  # (x, y, yaw) of each tag, for apriltag


@dataclass
class _Round:
    seq: int
    answers: dict[str, tuple[float, list[Polygon], tuple]] = field(default_factory=dict)


class Perception:
    """Bookkeeping of requests and answers; not thread-safe (the robot node holds a lock)."""

    def __init__(self, algorithms: dict[str, str]):
        missing = [role for role in ROLES if role not in algorithms]
        if missing:
            raise PerceptionError(f'colour_models: missing role(s) {", ".join(missing)}')
        self.algorithms = dict(algorithms)
        self.requests = RequestBook()
        self._rounds: dict[str, _Round | None] = {role: None for role in LOCALISATION_ROLES}
        self._fixes: dict[str, Fix | None] = {role: None for role in LOCALISATION_ROLES}
        self._latest: dict[tuple[str, str], int] = {}  # (role, vision system) -> newest seq heard
        self.superseded = 0  # answers ignored because a newer one was already in

    def fix(self, role: str) -> Fix | None:
        """The newest fix of ``self`` or ``station``."""
        return self._fixes[role]

    def accept(
        self,
        algorithm: str,
        request_id: str,
        vision_system: str,
        stamp: float,
        outlines: Iterable[Sequence[Sequence[float]]],
    ) -> Answer | None:
        """Take one callback; return the accepted answer, or None when it was superseded.

        :raises PerceptionError: for an id this robot never issued, or an
            algorithm that is not the one the id's role asks with.
        """
        role, seq = self.requests.parse(request_id)
        if algorithm != self.algorithms[role]:
            raise PerceptionError(
                f'algorithm: {request_id!r} asked with {self.algorithms[role]!r}, '
                f'the answer says {algorithm!r}'
            )
        outlines = [list(points) for points in outlines]
        polygons = tuple(p for p in (to_polygon(points) for points in outlines) if p is not None)
        poses = ()
        if algorithm.split(':', 1)[0] == 'apriltag':
            from drvs.algorithms.apriltag import tag_pose

            poses = tuple(tag_pose(points) for points in outlines if len(points) == 4)
        answer = Answer(role, seq, vision_system, stamp, polygons, poses)
        if role in LOCALISATION_ROLES:
            return answer if self._localise(answer) else None
        key = (role, vision_system)
        if seq < self._latest.get(key, 0):
            self.superseded += 1
            return None
        self._latest[key] = seq
        return answer

    def _localise(self, answer: Answer) -> bool:
        current = self._rounds[answer.role]
        if current is not None and answer.seq < current.seq:
            self.superseded += 1
            return False
        if current is None or answer.seq > current.seq:
            current = self._rounds[answer.role] = _Round(answer.seq)
        current.answers[answer.vision_system] = (answer.stamp, list(answer.outlines), answer.poses)
        objects = merge_outlines(o for _, outlines, _ in current.answers.values() for o in outlines)
        if not objects:
            return True
        previous = self._fixes[answer.role]
        if previous is not None:
            # Several candidates (something else of the same colour): the one nearest the last fix.
            px, py = previous.position
            chosen = min(objects, key=lambda o: math.hypot(o.centroid.x - px, o.centroid.y - py))
        else:
            chosen = max(objects, key=lambda o: o.area)
        stamps = [stamp for stamp, _, _ in current.answers.values()]
        position, heading = (chosen.centroid.x, chosen.centroid.y), None
        inside = chosen.buffer(TAG_MATCH)
        poses = [p for _, _, found in current.answers.values() for p in found]
        poses = [p for p in poses if inside.contains(Point2(p[0], p[1]))]
        if poses:
            position = (sum(p[0] for p in poses) / len(poses), sum(p[1] for p in poses) / len(poses))
            heading = math.atan2(sum(math.sin(p[2]) for p in poses), sum(math.cos(p[2]) for p in poses))
        self._fixes[answer.role] = Fix(
            position=position,
            outline=chosen,
            stamp=sum(stamps) / len(stamps),
            seq=current.seq,
            vision_systems=tuple(sorted(current.answers)),
            heading=heading,
        )
        return True
