"""The blind robot's map building: the vision systems' obstacle outlines -> its cost grid.

Each control tick :meth:`MapBuilder.update` takes the outlines every source (one obstacle role
seen by one vision system) last reported, leaves out what the robot can drive under
(:func:`headroom`), merges them per role, cuts the robot's own body, its recent trail and its
station (and, from what ``elevation`` and ``foreground`` report, the other robots) out of them,
and rasterises them into the
:class:`~drvs.robot.occupancy.CostGrid` the planner reads; it says which cells changed and
whether ``~map`` is due. No ROS here; the threads that call it are in docs/architecture.md.
"""

from __future__ import annotations

import collections
import math
import threading
from collections.abc import Collection, Sequence
from dataclasses import dataclass

from shapely.geometry import Point, Polygon
from shapely.ops import unary_union

from drvs.robot.occupancy import Cell, CostGrid, GridSpec, MapPublishing, ObstacleMemory, Source
from drvs.robot.perception import (
    FLEET_ROLE,
    STATIC_ROLES,
    Box,
    Fix,
    Level,
    cut_bodies,
    exclude_bodies,
    merge_outlines,
)
from drvs.robot.traffic import Mover, MoverTracker, swept
from drvs.sim.world import box_footprint

__all__ = [
    'BODY_MARGIN',
    'HEADROOM',
    'SAME_TOP',
    'headroom',
    'MAX_CELLS',
    'OWN_TRAIL',
    'MapBuilder',
    'MapUpdate',
    'OwnTrail',
    'grid_resolution',
    'own_body',
]

MAX_CELLS = 40_000
"""Cells of the default grid at most: D* Lite's first search over a 24 x 14 m warehouse at 0.05 m
(134,400 cells) holds the control loop, and with it the callbacks, for seconds on a loaded machine."""
BODY_MARGIN = 0.08
"""Metres around the robot's body (placed by its tag) within which moving regions are the robot itself."""
XY = tuple[float, float]
MOVER_AREA = 0.3
"""Of the robot's own footprint: a piece of the fleet role's outlines at least this large is another robot
(it moves, keeps clear); smaller ones (the edge of this robot's own blob) are plain obstacles."""
OWN_SHARE = 0.1
"""A moving outline of one camera's this much inside the robot's own body, trail or station is no mover
(it is not swept): the robot's own motion, or its ghost, seen by a ``motion`` or background model."""
OWN_BODY_SHARE = 0.5
"""A fused track that covers this much of the robot's body where it is now is no mover. For fused
roles (tracks of colour models, with velocities) neither the trail nor :data:`OWN_SHARE` count: a
person walking across the floor the robot has just left stays a person. (With them, a walker in the
crossing world vanished from the map as it stepped onto the robot's trail, and the robot drove into
it.)"""
MAX_AGE = 1.0
"""Seconds: something moving seen longer ago than this is swept as if seen this long ago."""
OWN_TRAIL = 4.0
"""Seconds of the robot's own past positions whose moving regions are ghosts of itself, not obstacles;
and of the other robots' outlines (the fleet's ``robot`` role) cut out of ``elevation``'s and
``foreground``'s static regions (a region of a robot that drove on stands until its camera reports
again)."""
HEADROOM = 0.05
"""Metres: an obstacle counts unless the room under it (its clearance) is at least the robot's
height plus this (the clearance is measured from below, at most 1 cm too high in the unit tests
of ``elevation``; the rest is for a robot that rocks)."""
SAME_TOP = 0.05
"""Metres: two cameras' outlines of one object have tops this close (an outline that is higher is
of something else as well, merged with it)."""
UNDER_MARGIN = 0.05
"""Metres around an outline the robot can drive under that are cut from the other cameras' outlines
of it: theirs are a few centimetres off, and a rim left along its edge would bar the way under it."""
PROOF_KEEP = 30.0
"""Seconds an outline the robot can drive under still cuts, from the outlines of it that hold the
robot: a camera that saw floor under a shelf sees the robot under it (or in front of it) as part of
it, standing on the floor, for as long as it is there."""


def headroom(
    found: Sequence[tuple[Polygon, XY | None, Level]],
    head: float,
    proofs: Sequence[tuple[Polygon, float]] = (),
    own: Polygon | None = None,
) -> tuple[list[tuple[Polygon, XY | None]], list[tuple[Polygon, float]]]:
    """Of one role's outlines (each with its velocity and its (top, clearance)), those that count for
    a robot that needs ``head`` metres of room, and those it can drive under (with their tops).

    An outline with at least ``head`` of clearance is left out, and cut (grown by
    :data:`UNDER_MARGIN`) from the outlines of the same object that other cameras, which saw only its
    top (clearance 0: unknown), report: those it intersects whose top is within :data:`SAME_TOP` of
    its own. ``proofs``: outlines found passable before (:data:`PROOF_KEEP`), with their tops, which
    cut only the outlines that overlap the robot itself (``own``): the camera sees it under them.
    """
    passable = [(o, top) for o, _, (top, clearance) in found if clearance >= head]
    counted: list[tuple[Polygon, XY | None]] = []
    for outline, velocity, (top, clearance) in found:
        if clearance >= head:
            continue
        over = [p for p, p_top in passable if abs(p_top - top) <= SAME_TOP and p.intersects(outline)]
        if own is not None and proofs and outline.intersects(own):
            over += [p for p, p_top in proofs if abs(p_top - top) <= SAME_TOP and p.intersects(outline)]
        if not over:
            counted.append((outline, velocity))
            continue
        counted.extend(
            (piece, velocity) for piece in cut_bodies([outline], [p.buffer(UNDER_MARGIN) for p in over])
        )
    return counted, passable


def grid_resolution(floor_size: Sequence[float]) -> float:
    """The default cell size: 0.05 m, or the next centimetre that keeps the grid within MAX_CELLS.

    >>> grid_resolution((7.0, 5.5)), grid_resolution((24.0, 14.0))
    (0.05, 0.1)
    """
    width, height = floor_size
    return max(0.05, math.ceil(math.sqrt(width * height / MAX_CELLS) * 100) / 100)


def own_body(fix: Fix | None, size: Sequence[float]) -> Polygon | None:
    """The robot's body where its tag says, grown by :data:`BODY_MARGIN`; None without a heading.

    A tag is smaller than the robot: the body around it is not an obstacle (motion finds the
    robot moving), with a margin for the time between the frames.
    """
    if fix is None or fix.heading is None:
        return None
    return Polygon(box_footprint(fix.position, size, fix.heading)).buffer(BODY_MARGIN)


class OwnTrail:
    """Where the robot stood in the last ``keep`` seconds, grown by ``radius``.

    A background model that took the robot in while it stood still reports the floor it uncovers
    as "moving" for a while (a ghost of itself), which must not block it.
    """

    def __init__(self, radius: float, keep: float = OWN_TRAIL):
        self.radius = radius
        self.keep = keep
        self._points: collections.deque = collections.deque()  # (time, position) of recent fixes
        self._shape = Polygon()  # their union, grown by radius

    def update(self, now: float, fix: Fix | None) -> Polygon:
        """Add ``fix`` (if new), forget what is older than ``keep``; the trail now."""
        points = self._points
        changed = False
        if fix is not None and (not points or points[-1][1] != fix.position):
            points.append((now, fix.position))
            changed = True
        while points and now - points[0][0] > self.keep:
            points.popleft()
            changed = True
        if changed:  # new fixes come a few times a second; the control loop ticks faster
            self._shape = unary_union([Point(position).buffer(self.radius) for _, position in points])
        return self._shape


@dataclass(frozen=True)
class MapUpdate:
    """What one :meth:`MapBuilder.update` changed."""

    changes: list[tuple[Cell, float]]  # cells whose cost changed, with their new cost (for D* Lite)
    publish: bool  # whether ``~map`` is due now (:class:`~drvs.robot.occupancy.MapPublishing`)


class MapBuilder:
    """Obstacle outlines per source -> the robot's cost grid.

    :param floor_size: the floor (x, y) in metres; the grid covers it.
    :param robot_size: the robot's footprint (x, y), to cut its body out where its tag says.
    :param robot_radius: inflation of obstacles in the grid.
    :param obstacle_roles: the roles whose outlines are obstacles.
    :param ttl: a source not heard from for this long is forgotten
        (:class:`~drvs.robot.occupancy.ObstacleMemory`).
    :param linger: an empty report keeps a source's outlines this long more.
    :param map_period: at most one ``~map`` per period while the map changes.
    :param resolution: the cell size (default :func:`grid_resolution`).
    :param clearance: metres other robots (the fleet role) are kept clear by, beyond ``robot_radius``.
    :param horizon: seconds of the other robots' motion whose floor the map holds (:func:`swept`).
    :param caution: metres beyond ``robot_radius`` where cells cost more (:class:`CostGrid`).
    :param fused: the roles DRVS fuses (one object each already); the outlines of the others
        from every source are merged into objects (:func:`merge_outlines`).
    :param cut_roles: the obstacle roles whose outlines have the robot's body and station cut out,
        not dropped when they overlap them: the fleet's ``robot`` and the class-agnostic
        algorithms' (:data:`~drvs.robot.perception.CLASS_AGNOSTIC`), whose region around the robot
        may be a real obstacle merged with it; the class-agnostic ones lose the other robots (the
        fleet's outlines) too.
    :param robot_height: metres; an outline with at least this plus :data:`HEADROOM` of clearance
        is not an obstacle (:func:`headroom`). Default: infinite, everything counts.
    """

    def __init__(
        self,
        floor_size: tuple[float, float],
        robot_size: tuple[float, float],
        robot_radius: float,
        obstacle_roles: Sequence[str],
        ttl: float,
        linger: float,
        map_period: float,
        resolution: float | None = None,
        clearance: float = 0.0,
        horizon: float = 0.0,
        fused: Collection[str] = (),
        caution: float = 0.0,
        cut_roles: Collection[str] = (FLEET_ROLE,),
        robot_height: float = math.inf,
    ):
        self.robot_size = robot_size
        self.obstacle_roles = tuple(obstacle_roles)
        self.cut_roles = frozenset(cut_roles)
        self.linger = linger
        spec = GridSpec(floor_size, resolution or grid_resolution(floor_size))
        self.grid = CostGrid(spec, robot_radius, caution)
        self.trail = OwnTrail(robot_radius + BODY_MARGIN)
        self.publishing = MapPublishing(map_period)
        self.obstacles = 0  # obstacle outlines in the current grid
        self.clearance, self.horizon = clearance, horizon
        self.trackers = {role: MoverTracker() for role in self.obstacle_roles if role not in STATIC_ROLES}
        self.movers: list[Mover] = []  # the other robots at the last update, with their velocities
        self.people: list[Mover] = []  # whatever else moves (people), likewise
        self.min_mover = MOVER_AREA * robot_size[0] * robot_size[1]
        self.fused = frozenset(fused)
        self.head = robot_height + HEADROOM
        self.passable = 0  # outlines left out at the last update: the robot can drive under them
        self._proofs: dict[str, list[tuple[float, Polygon, float]]] = {}  # role -> (when, outline, top)
        self._others: collections.deque = collections.deque()  # (when, the other robots' outlines)
        self._memory_lock = (
            threading.Lock()
        )  # guards the fields below: callbacks observe, the control loop reads
        self._memory = ObstacleMemory(ttl)
        self._velocities: dict[
            Source, dict[int, Point]
        ] = {}  # source -> id(outline) -> its velocity, if given
        self._heard: dict[str, float] = {}  # role -> when a vision system last reported it

    def _kept_clear(self, mover: Mover, now: float) -> Polygon:
        """The floor something moving holds: its outline, swept from when it was seen to the
        horizon beyond ``now``, grown by the clearance."""
        age = min(max(now - mover.seen, 0.0), MAX_AGE) if mover.seen is not None else 0.0
        area = swept(mover.outline, mover.velocity, self.horizon + age)
        return area.buffer(self.clearance, 8) if self.clearance > 0 else area

    def observe(
        self,
        role: str,
        vision_system: str,
        outlines: Sequence[Polygon],
        now: float,
        region: Box | None = None,
        velocities: Sequence[XY | None] | None = None,
        seen: float | None = None,
        levels: Sequence[Level] | None = None,
    ) -> None:
        """What ``vision_system`` sees of ``role`` now (nothing: the outlines linger a while) in
        ``region``, the region the robot asked it about: a static role's outlines it reported
        before outside that region stay. ``velocities``: each outline's, when DRVS tracked them;
        ``seen``: when the frames were taken (default ``now``); ``levels``: each outline's top and
        clearance (default unknown, (0, 0))."""
        region = region if role in STATIC_ROLES else None
        source = (role, vision_system)
        with self._memory_lock:
            self._heard[role] = max(self._heard.get(role, -math.inf), now if seen is None else seen)
            if outlines or not self.linger:  # (a report of nothing keeps the outlines that linger)
                given = zip(outlines, velocities or (), strict=False)
                self._velocities[source] = {id(o): v for o, v in given if v is not None}
            self._memory.observe(source, outlines, now, linger=self.linger, region=region, facts=levels)

    def update(
        self, now: float, fix: Fix | None, station: Fix | None, position: XY | None = None
    ) -> MapUpdate:
        """Rebuild the grid from the outlines standing at ``now``, without the robot (``fix``, its
        trail, its body, and where it believes it is, ``position``: a fix may be late) and its
        ``station``."""
        with self._memory_lock:
            sources = self._memory.entries(now)
            velocities = {source: dict(self._velocities.get(source, {})) for source in sources}
            heard = dict(self._heard)
        bodies = [f.outline for f in (fix, station) if f is not None]
        body = own_body(fix, self.robot_size)
        if body is not None:
            bodies.append(body)
        trail = self.trail.update(now, fix)
        bodies.append(trail)
        if position is not None:
            bodies.append(Point(position).buffer(self.trail.radius))
        own = unary_union(bodies)
        # Where the robot and its station are now, without its trail (for the fused roles).
        here = [b for b in bodies if b is not trail]
        # elevation's and foreground's regions lose the robot and station grown by the margin: their
        # outline of them, a frame older or inset by half a cell, would leave a rim.
        grown = [*bodies, *(f.outline.buffer(BODY_MARGIN) for f in (fix, station) if f is not None)]
        self.passable = 0
        found_by_role = {
            role: self._counted(role, sources, velocities, now, own) for role in self.obstacle_roles
        }
        # elevation and foreground find the other robots too, and keep where a robot stood until
        # their camera reports again: the fleet's outlines of them (and where they were) are cut out.
        others = self._other_robots(now, found_by_role.get(FLEET_ROLE), bodies)
        objects: list[Polygon] = []
        moving_people: dict[str, list[Mover]] = {}
        for role in self.obstacle_roles:
            found = found_by_role[role]
            if role not in self.fused:  # one vision system's outlines each: one polygon per object
                found = [(o, None) for o in merge_outlines(o for o, _ in found)]
            if role in self.cut_roles:
                # The fleet's model (and elevation, foreground) finds this robot too, as one blob with
                # another robot or an obstacle it touches: its own body is cut out, not the blob dropped.
                cut = bodies if role == FLEET_ROLE else [*grown, *others]
                pieces = [(piece, v) for o, v in found for piece in cut_bodies([o], cut)]
            else:
                pieces = [
                    (o, v) for o, v in found if exclude_bodies([o], here if role in self.fused else bodies)
                ]
            if role in STATIC_ROLES:
                objects.extend(piece for piece, _ in pieces)
                continue
            # Whatever moves (pieces a robot's size at least) keeps ``clearance`` more, over the
            # floor it sweeps within ``horizon``; not what overlaps this robot (its own motion, seen
            # by a ``motion`` model: moving with it, swept ahead of it, it would block its way).
            big: list[tuple[Polygon, XY | None]] = []
            plain: list[tuple[Polygon, XY | None]] = []
            for piece, v in pieces:
                if role in self.fused:  # a track: not the robot unless it covers the robot now
                    mine = any(piece.intersection(b).area >= OWN_BODY_SHARE * b.area for b in here)
                else:
                    mine = piece.intersection(own).area >= OWN_SHARE * piece.area
                mover = piece.area >= self.min_mover and not mine
                (big if mover else plain).append((piece, v))
            movers = self.trackers[role].update(
                heard.get(role, -math.inf), [p for p, _ in big], [v for _, v in big]
            )
            objects.extend(piece for piece, _ in plain)
            objects.extend(self._kept_clear(mover, now) for mover in movers)
            if role == FLEET_ROLE:
                self.movers = movers
            else:
                moving_people[role] = movers
        self.people = [mover for movers in moving_people.values() for mover in movers]
        self.obstacles = len(objects)
        changes = self.grid.apply(objects)
        return MapUpdate(changes, self.publishing.due(now, bool(changes)))

    def _counted(
        self,
        role: str,
        sources: dict[Source, list[tuple[Polygon, Level | None]]],
        velocities: dict[Source, dict[int, XY]],
        now: float,
        own: Polygon,
    ) -> list[tuple[Polygon, XY | None]]:
        """``role``'s outlines from every source, each with its velocity, without what the robot can
        drive under (:func:`headroom`); those are kept :data:`PROOF_KEEP` seconds as proofs."""
        found = [
            (o, velocities[source].get(id(o)), level or (0.0, 0.0))
            for source, outlines in sources.items()
            if source[0] == role
            for o, level in outlines
        ]
        proofs = [(when, o, top) for when, o, top in self._proofs.get(role, ()) if now - when <= PROOF_KEEP]
        counted, passable = headroom(found, self.head, [(o, top) for _, o, top in proofs], own)
        self.passable += len(passable)
        if passable or proofs:
            self._proofs[role] = [(when, o, top) for when, o, top in proofs if not _renewed(o, passable)] + [
                (now, o, top) for o, top in passable
            ]
        return counted

    def _other_robots(
        self, now: float, found: list[tuple[Polygon, XY | None]] | None, bodies: list[Polygon]
    ) -> list[Polygon]:
        """The other robots as the fleet's role finds them now and found them in the last
        :data:`OWN_TRAIL` seconds (pieces a robot's size at least, without this robot), the current
        ones grown by :data:`BODY_MARGIN`."""
        if found is None:
            return []
        pieces = cut_bodies(merge_outlines(o for o, _ in found), bodies)
        robots = [piece for piece in pieces if piece.area >= self.min_mover]
        trail = self._others
        if robots:
            trail.append((now, robots))
        while trail and now - trail[0][0] > OWN_TRAIL:
            trail.popleft()
        return [*(robot.buffer(BODY_MARGIN) for robot in robots), *(o for _, seen in trail for o in seen)]


def _renewed(outline: Polygon, passable: Sequence[tuple[Polygon, float]]) -> bool:
    """Whether a proof ``outline`` is replaced by one of the ``passable`` outlines found now."""
    return any(outline.intersects(p) for p, _ in passable)
