"""The blind robot's map building: the vision systems' obstacle outlines -> its cost grid.

Each control tick :meth:`MapBuilder.update` takes the outlines every source (one obstacle role
seen by one vision system) last reported, merges them per role, cuts the robot's own body, its
recent trail and its station out of them, and rasterises them into the
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

from drvs.robot.occupancy import Cell, CostGrid, GridSpec, MapPublishing, ObstacleMemory
from drvs.robot.perception import FLEET_ROLE, Fix, cut_bodies, exclude_bodies, merge_outlines
from drvs.sim.world import box_footprint

__all__ = [
    'BODY_MARGIN',
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
OWN_TRAIL = 4.0
"""Seconds of the robot's own past positions whose moving regions are ghosts of itself, not obstacles."""


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
    :param cut_roles: those of them whose outlines have the robot's body and station cut out, not
        dropped when mostly covered by them: the fleet's ``robot`` and the class-agnostic
        algorithms' (:data:`~drvs.robot.perception.CLASS_AGNOSTIC`), whose region around the robot
        may be a real obstacle merged with it.
    :param ttl: a source not heard from for this long is forgotten
        (:class:`~drvs.robot.occupancy.ObstacleMemory`).
    :param linger: an empty report keeps a source's outlines this long more.
    :param map_period: at most one ``~map`` per period while the map changes.
    :param resolution: the cell size (default :func:`grid_resolution`).
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
        cut_roles: Collection[str] = (FLEET_ROLE,),
    ):
        self.robot_size = robot_size
        self.obstacle_roles = tuple(obstacle_roles)
        self.cut_roles = frozenset(cut_roles)
        self.linger = linger
        self.grid = CostGrid(GridSpec(floor_size, resolution or grid_resolution(floor_size)), robot_radius)
        self.trail = OwnTrail(robot_radius + BODY_MARGIN)
        self.publishing = MapPublishing(map_period)
        self.obstacles = 0  # obstacle outlines in the current grid
        self._memory_lock = threading.Lock()  # guards _memory: callbacks observe, the control loop reads
        self._memory = ObstacleMemory(ttl)

    def observe(self, role: str, vision_system: str, outlines: Sequence[Polygon], now: float) -> None:
        """What ``vision_system`` sees of ``role`` now (nothing: the outlines linger a while)."""
        with self._memory_lock:
            self._memory.observe((role, vision_system), outlines, now, linger=self.linger)

    def update(self, now: float, fix: Fix | None, station: Fix | None) -> MapUpdate:
        """Rebuild the grid from the outlines standing at ``now``, without the robot (``fix``, its
        trail, its body) and its ``station``."""
        with self._memory_lock:
            sources = self._memory.current(now)
        bodies = [f.outline for f in (fix, station) if f is not None]
        body = own_body(fix, self.robot_size)
        if body is not None:
            bodies.append(body)
        bodies.append(self.trail.update(now, fix))
        # elevation's and foreground's regions lose the robot and station grown by the margin: their
        # outline of them, a frame older or inset by half a cell, would leave a rim.
        grown = [*bodies, *(f.outline.buffer(BODY_MARGIN) for f in (fix, station) if f is not None)]
        objects = []
        for role in self.obstacle_roles:
            merged = merge_outlines(o for (r, _), outlines in sources.items() if r == role for o in outlines)
            # The fleet's model (and elevation, foreground) finds this robot too, as one blob with
            # another robot or an obstacle it touches: its own body is cut out, not the blob dropped.
            objects.extend(
                cut_bodies(merged, bodies if role == FLEET_ROLE else grown)
                if role in self.cut_roles
                else exclude_bodies(merged, bodies)
            )
        self.obstacles = len(objects)
        changes = self.grid.apply(objects)
        return MapUpdate(changes, self.publishing.due(now, bool(changes)))
