"""What the blind robot knows from DRVS answers: request ids, superseded answers, merged objects.

:class:`RequestBook` names requests, :class:`Perception` turns the callbacks of each role
into fixes and obstacle outlines, and :class:`RegionPolicy` decides where each role is
asked for. How answers are read and regions chosen: docs/design.md ("The blind robot");
what the robot does with them: docs/nodes/blind_robot.md.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass, field

from shapely.geometry import Point as Point2
from shapely.geometry import Polygon
from shapely.ops import unary_union

from drvs.common.roles import FLEET_ROLE as FLEET_ROLE  # re-exported: drvs/robot/mapping.py imports it here
from drvs.common.roles import LOCALISATION_ROLES
from drvs.common.roles import REQUIRED_ROLES as ROLES

MIN_PIECE = 0.01
"""m²: what is left of an outline once the robot's own body is cut out, smaller than this, is
noise (the edge of its own blob in a frame older than its fix), not another body."""
CLASS_AGNOSTIC = ('elevation', 'foreground')
"""Algorithms that find everything standing on the floor, the robot and its station too: the
robot cuts its body and station out of their outlines (:func:`cut_bodies`), as a region that
touches it may be a real obstacle merged with it."""
STATIC_ROLES = ('obstacle',)
"""Obstacle roles whose objects stand still; the others (``human``, ``robot``) move."""
WATCH = 0
"""The sequence number :meth:`RequestBook.parse` gives a watch's id."""

Point = tuple[float, float]
TAG_MATCH = 0.05
"""Metres: a tag's centre this close to (or inside) a merged object belongs to it."""
HIDDEN = 0.8
"""A station outline smaller than this fraction of its fix's, where the fix is, is the station
partly hidden (the robot drives onto it): it keeps the fix."""
Box = tuple[float, float, float, float]
Level = tuple[float, float]
"""An outline's top and the room under it (DetectedObject's height and clearance), metres; 0: unknown."""


class PerceptionError(ValueError):
    """A callback the robot cannot use; the message names the field and the problem."""


def whole_floor(floor_size: tuple[float, float]) -> Box:
    return (0.0, 0.0, float(floor_size[0]), float(floor_size[1]))


def spanned(a: Point, b: Point, margin: float, floor_size: tuple[float, float]) -> Box:
    """The box spanned by points ``a`` and ``b`` (the robot and the station, or a box's corners),
    grown by ``margin``, clipped to the floor.

    >>> spanned((1.0, 2.0), (3.0, 1.0), 0.5, (7.0, 5.5))
    (0.5, 0.5, 3.5, 2.5)
    """
    return (
        max(0.0, min(a[0], b[0]) - margin),
        max(0.0, min(a[1], b[1]) - margin),
        min(float(floor_size[0]), max(a[0], b[0]) + margin),
        min(float(floor_size[1]), max(a[1], b[1]) + margin),
    )


@dataclass(frozen=True)
class Region:
    """A role's region of interest: ``box`` to ask with, and ``needed``, the part of it that must
    stay covered (a watch standing on a box that holds ``needed`` need not move)."""

    box: Box
    needed: Box


@dataclass(frozen=True)
class RegionPolicy:
    """Which region of interest each role is asked with now; see the module docstring."""

    floor_size: tuple[float, float]
    obstacle_roles: tuple[str, ...]
    robot_radius: float
    self_margin: float
    roi_margin: float
    fix_timeout: float

    def regions(
        self,
        now: float,
        fix: Fix | None,
        station: Fix | None,
        position: Point | None,
        velocity: Point = (0.0, 0.0),
        lost: Collection[str] = (),
        corridor: Box | None = None,
    ) -> dict[str, Region]:
        """Role -> region, from the newest fixes, the predicted ``position`` (None: the fix's), the
        commanded ``velocity``, the roles whose vision systems all say they see nothing of it
        (``lost``) and the ``corridor`` of the robot's plan (:attr:`Controller.corridor
        <drvs.robot.controller.Controller.corridor>`), which the obstacle roles must cover."""
        floor, size, margin = whole_floor(self.floor_size), self.floor_size, self.self_margin
        regions = dict.fromkeys(LOCALISATION_ROLES, Region(floor, floor))
        here = position or (fix.position if fix is not None else None)
        speed = math.hypot(*velocity)
        if fix is not None and 'self' not in lost and now - fix.stamp <= self.fix_timeout / 2:
            assert here is not None  # with a fix
            lead = margin / 2 / speed if speed > 0 else 0.0  # the box reaches further where it goes
            ahead = (here[0] + lead * velocity[0], here[1] + lead * velocity[1])
            regions['self'] = Region(
                spanned(ahead, ahead, self.robot_radius + margin, size),
                spanned(here, here, self.robot_radius + margin / 4, size),
            )
        if station is not None and 'station' not in lost:
            low, high = station.outline.bounds[:2], station.outline.bounds[2:]
            regions['station'] = Region(
                spanned(low, high, margin, size), spanned(low, high, margin / 4, size)
            )
        if fix is not None and station is not None:
            assert here is not None  # with a fix
            # Heading away from the station (a detour), the box reaches as far again where it goes.
            lead = self.roi_margin / speed if speed > 0 else 0.0
            heading = (here[0] + lead * velocity[0], here[1] + lead * velocity[1])
            roi = spanned(here, station.position, self.roi_margin, size)
            roi = _union(roi, spanned(heading, station.position, self.roi_margin, size))
            needed = spanned(here, station.position, self.roi_margin / 2, size)
            # Round the robot, one and a half margins at least: a detour round someone near the
            # station is known floor, not a stop to ask (:mod:`drvs.robot.asked`).
            roi = _union(roi, spanned(here, here, 1.5 * self.roi_margin, size))
            needed = _union(needed, spanned(here, here, self.roi_margin, size))
            if corridor is not None and corridor[0] <= corridor[2]:
                needed = _union(needed, corridor)
                low, high = corridor[:2], corridor[2:]
                roi = _union(roi, spanned(low, high, self.roi_margin / 2, size))
            regions.update(dict.fromkeys(self.obstacle_roles, Region(roi, needed)))
        return regions


def _union(a: Box, b: Box) -> Box:
    return (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))


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


def cut_bodies(outlines: Iterable[Polygon], bodies: Iterable[Polygon], min_area: float = MIN_PIECE) -> list:
    """Outlines with ``bodies`` cut out; pieces smaller than ``min_area`` dropped.

    For the fleet's ``robot`` model, which finds this robot too: two robots that
    touch are one blob in a camera's image, and :func:`exclude_bodies` would drop
    that blob whole when this robot's body covers most of it, so neither robot
    would see the other and both would drive on into it (the warehouse deadlock).
    Cutting keeps the other robot's part.
    """
    bodies = [b for b in bodies if b is not None and not b.is_empty]
    if not bodies:
        return list(outlines)
    cut = unary_union(bodies)
    pieces = []
    for outline in outlines:
        if not outline.intersects(cut):
            pieces.append(outline)
            continue
        left = outline.difference(cut)
        for part in getattr(left, 'geoms', [left]):
            if part.geom_type == 'Polygon' and part.area >= min_area:
                pieces.append(part)
    return pieces


def _level(level: Sequence[float]) -> Level:
    """(top, clearance) as reported; a value that is not a number of metres >= 0 is unknown (0)."""
    top, clearance = (
        float(v) if isinstance(v, int | float) and math.isfinite(v) and v >= 0 else 0.0 for v in level
    )
    return (top, clearance)


class RequestBook:
    """Issues request ids (``<role>-<seq>``, and ``<prefix>/<role>`` for watches) and parses the
    ids that callbacks echo."""

    def __init__(self, roles: Sequence[str] = ROLES, prefix: str = ''):
        self._issued = {role: 0 for role in roles}
        self._prefix = prefix
        self._watches: dict[str, str] = {}  # watch id -> role, once issued

    def _check(self, role: str) -> None:
        if role not in self._issued:
            raise PerceptionError(f'role: expected one of {", ".join(self._issued)}, got {role!r}')

    def issue(self, role: str) -> str:
        self._check(role)
        self._issued[role] += 1
        return f'{role}-{self._issued[role]}'

    def watch_id(self, role: str) -> str:
        """The id of ``role``'s watch: the same for every call (new, renewal, cancel)."""
        self._check(role)
        request_id = f'{self._prefix}/{role}'
        self._watches[request_id] = role
        return request_id

    def issued(self, role: str) -> int:
        """How many requests for ``role`` were issued (the newest sequence number)."""
        return self._issued[role]

    def parse(self, request_id: str) -> tuple[str, int]:
        """(role, seq) of an id this book issued; ``seq`` is :data:`WATCH` for a watch's id.

        :raises PerceptionError: for an id of another form, role or a sequence not issued yet.
        """
        if request_id in self._watches:
            return self._watches[request_id], WATCH
        role, _, seq_text = request_id.rpartition('-')
        if role not in self._issued or not seq_text.isdigit():
            raise PerceptionError(
                f'request_id: expected <role>-<number> or a watch {self._prefix}/<role> with a role '
                f'of ours, got {request_id!r}'
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
    seq: int  # the round's request; with watches, counts the fixes made
    vision_systems: tuple[str, ...]
    heading: float | None = None  # radians in map, when the algorithm gives one (a tag)


@dataclass(frozen=True)
class Answer:
    """One accepted callback."""

    role: str
    seq: int  # WATCH for a watch's answer
    vision_system: str
    stamp: float
    outlines: tuple[Polygon, ...]
    poses: tuple[tuple[float, float, float], ...] = ()  # (x, y, yaw) of each tag, for apriltag
    velocities: tuple[Point | None, ...] = ()  # each outline's, when the callback gives them (fused)
    levels: tuple[Level, ...] = ()  # each outline's (top, clearance), metres; (0, 0): unknown


Held = tuple[float, list[Polygon], tuple]
"""One vision system's answer for a localisation role: stamp, outlines, tag poses."""


@dataclass
class _Round:
    seq: int
    answers: dict[str, Held] = field(default_factory=dict)


class Perception:
    """Bookkeeping of requests and answers; not thread-safe (the robot node holds a lock).

    :param algorithms: role -> algorithm string; every role of :data:`ROLES`, maybe more.
    :param watch_prefix: the watch ids' prefix (the node's name).
    :param watch_keep: seconds a watch answer stands at most (the watches' duration).
    :param fused: the roles DRVS fuses (one object each already); the outlines of a round of the
        others (several vision systems) are merged into objects (:func:`merge_outlines`).
    """

    def __init__(
        self,
        algorithms: dict[str, str],
        watch_prefix: str = '',
        watch_keep: float = math.inf,
        fused: Collection[str] = (),
    ):
        missing = [role for role in ROLES if role not in algorithms]
        if missing:
            raise PerceptionError(f'colour_models: missing role(s) {", ".join(missing)}')
        self.algorithms = dict(algorithms)
        self.obstacle_roles = tuple(role for role in self.algorithms if role not in LOCALISATION_ROLES)
        self.cut_roles = tuple(
            role
            for role in self.obstacle_roles
            if role == FLEET_ROLE or self.algorithms[role].split(':', 1)[0] in CLASS_AGNOSTIC
        )
        """The obstacle roles whose outlines have the robot's body cut out (``robot``, and those
        asked with a :data:`CLASS_AGNOSTIC` algorithm)."""
        self.requests = RequestBook(tuple(self.algorithms), watch_prefix)
        self.watch_keep = watch_keep
        self.fused = frozenset(fused)
        self._rounds: dict[str, _Round | None] = {role: None for role in LOCALISATION_ROLES}
        self._views: dict[str, dict[str, Held]] = {role: {} for role in LOCALISATION_ROLES}
        self._fixes: dict[str, Fix | None] = {role: None for role in LOCALISATION_ROLES}
        self._latest: dict[tuple[str, str], int] = {}  # (role, vision system) -> newest seq heard
        self._newest: dict[tuple[str, str], float] = {}  # (role, vision system) -> newest watch stamp
        self.superseded = 0  # answers ignored because a newer one was already in

    def fix(self, role: str) -> Fix | None:
        """The newest fix of ``self`` or ``station``."""
        return self._fixes[role]

    def lost(self, role: str) -> bool:
        """Whether every vision system watching ``self`` or ``station`` says it sees nothing of it now."""
        views = self._views[role]
        return bool(views) and not any(outlines for _, outlines, _ in views.values())

    def accept(
        self,
        algorithm: str,
        request_id: str,
        vision_system: str,
        stamp: float,
        outlines: Iterable[Sequence[Sequence[float]]],
        velocities: Iterable[Point | None] | None = None,
        levels: Iterable[Level] | None = None,
    ) -> Answer | None:
        """Take one callback; return the accepted answer, or None when it was superseded.

        ``velocities``: each outline's (a fused callback's tracks'), in the answer beside its polygon;
        ``levels``: each outline's top and clearance (metres; default (0, 0), unknown), likewise.

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
        given = list(velocities) if velocities is not None else [None] * len(outlines)
        if len(given) != len(outlines):
            raise PerceptionError(f'velocities: expected {len(outlines)}, one per outline, got {len(given)}')
        heights = [_level(level) for level in levels] if levels is not None else [(0.0, 0.0)] * len(outlines)
        if len(heights) != len(outlines):
            raise PerceptionError(f'levels: expected {len(outlines)}, one per outline, got {len(heights)}')
        kept = [
            (p, v, h)
            for p, v, h in zip(map(to_polygon, outlines), given, heights, strict=True)
            if p is not None
        ]
        polygons = tuple(p for p, _, _ in kept)
        poses: tuple[tuple[float, float, float], ...] = ()
        if algorithm.split(':', 1)[0] == 'apriltag':
            from drvs.algorithms.apriltag import tag_pose

            poses = tuple(tag_pose(points) for points in outlines if len(points) == 4)
        answer = Answer(
            role,
            seq,
            vision_system,
            stamp,
            polygons,
            poses,
            tuple(v for _, v, _ in kept),
            tuple(h for *_, h in kept),
        )
        if seq == WATCH:
            return answer if self._watched(answer) else None
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
        stamps = [stamp for stamp, _, _ in current.answers.values()]
        self._make_fix(answer.role, current.answers, current.seq, sum(stamps) / len(stamps))
        return True

    def _watched(self, answer: Answer) -> bool:
        key = (answer.role, answer.vision_system)
        if answer.stamp < self._newest.get(key, -math.inf):
            self.superseded += 1
            return False
        self._newest[key] = answer.stamp
        if answer.role not in LOCALISATION_ROLES:
            return True
        views = self._views[answer.role]
        views[answer.vision_system] = (answer.stamp, list(answer.outlines), answer.poses)
        oldest = max(stamp for stamp, _, _ in views.values()) - self.watch_keep
        for vision_system in [vs for vs, (stamp, _, _) in views.items() if stamp < oldest]:
            del views[vision_system]
        standing = {vs: held for vs, held in views.items() if held[1]}
        if standing:
            previous = self._fixes[answer.role]
            seq = previous.seq + 1 if previous is not None else 1
            self._make_fix(answer.role, standing, seq, max(stamp for stamp, _, _ in standing.values()))
        return True

    def _make_fix(self, role: str, answers: dict[str, Held], seq: int, stamp: float) -> None:
        """The fix of ``role`` from the merged outlines of ``answers`` (vision system -> answer)."""
        outlines = [o for _, found, _ in answers.values() for o in found]
        objects = outlines if role in self.fused else merge_outlines(outlines)
        if not objects:
            return
        previous = self._fixes[role]
        if previous is not None:
            # Several candidates (something else of the same colour): the one nearest the last fix.
            px, py = previous.position
            chosen = min(objects, key=lambda o: math.hypot(o.centroid.x - px, o.centroid.y - py))
        else:
            chosen = max(objects, key=lambda o: o.area)
        if role == 'station' and previous is not None and chosen.area < HIDDEN * previous.outline.area:
            if chosen.intersects(previous.outline):
                return  # the station does not move: less of it in view is it partly hidden
        position, heading = (chosen.centroid.x, chosen.centroid.y), None
        inside = chosen.buffer(TAG_MATCH)
        poses = [p for _, _, found in answers.values() for p in found]
        poses = [p for p in poses if inside.contains(Point2(p[0], p[1]))]
        if poses:
            position = (sum(p[0] for p in poses) / len(poses), sum(p[1] for p in poses) / len(poses))
            heading = math.atan2(sum(math.sin(p[2]) for p in poses), sum(math.cos(p[2]) for p in poses))
        self._fixes[role] = Fix(
            position=position,
            outline=chosen,
            stamp=stamp,
            seq=seq,
            vision_systems=tuple(sorted(answers)),
            heading=heading,
        )
