"""The robot's occupancy grid: obstacle outlines in ``map`` -> cell costs for D* Lite.

Cells are ``LETHAL``, ``INFLATED`` (within ``robot_radius``: very expensive, not
impassable) or ``FREE``; :class:`ObstacleMemory` keeps each source's latest outlines and
forgets a silent one after ``ttl``. The grid is laid out as nav_msgs/OccupancyGrid. Why
the costs are what they are: docs/design.md ("The blind robot").
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from shapely.geometry import Polygon, box

from drvs.robot.dstar_lite import FREE

LETHAL = math.inf
INFLATED = 1e6
CAUTION = 1.25
"""The cost of a cell within ``caution`` of the inflated margin: a quarter more than a free one, so
a plan beside a shelf moves off it where there is room, and still takes a narrow gap."""
SUBPIXEL_BITS = 4  # cv2.fillPoly fixed-point precision: 1/16 of a cell

Cell = tuple[int, int]
Point = tuple[float, float]


class OccupancyError(ValueError):
    """Bad grid settings; the message names the setting and the problem."""


@dataclass(frozen=True)
class GridSpec:
    """The cells covering a floor of ``size`` (x, y) metres at ``resolution`` metres per cell."""

    size: tuple[float, float]
    resolution: float

    def __post_init__(self) -> None:
        if not (self.resolution > 0 and math.isfinite(self.resolution)):
            raise OccupancyError(f'resolution: expected a positive number of metres, got {self.resolution}')
        if len(self.size) != 2 or not all(v > 0 and math.isfinite(v) for v in self.size):
            raise OccupancyError(f'size: expected 2 positive numbers of metres, got {self.size}')

    @property
    def cols(self) -> int:
        return max(1, math.ceil(self.size[0] / self.resolution - 1e-9))

    @property
    def rows(self) -> int:
        return max(1, math.ceil(self.size[1] / self.resolution - 1e-9))

    def cell_of(self, point: Point) -> Cell:
        """The cell containing ``point``; points off the floor go to the nearest edge cell."""
        col = min(max(int(math.floor(point[0] / self.resolution)), 0), self.cols - 1)
        row = min(max(int(math.floor(point[1] / self.resolution)), 0), self.rows - 1)
        return (row, col)

    def centre_of(self, cell: Cell) -> Point:
        return ((cell[1] + 0.5) * self.resolution, (cell[0] + 0.5) * self.resolution)


class CostGrid:
    """Cell costs from obstacle outlines, inflated by the robot radius; reports what changed.

    :param caution: metres beyond ``robot_radius`` within which cells cost ``CAUTION``: passable,
        but a plan keeps off obstacles where there is room.
    """

    def __init__(self, spec: GridSpec, robot_radius: float, caution: float = 0.0):
        if not (robot_radius >= 0 and math.isfinite(robot_radius)):
            raise OccupancyError(f'robot_radius: expected a number of metres >= 0, got {robot_radius}')
        if not (caution >= 0 and math.isfinite(caution)):
            raise OccupancyError(f'caution: expected a number of metres >= 0, got {caution}')
        self.spec = spec
        self.robot_radius = robot_radius
        self.caution = caution
        self.costs = np.full((spec.rows, spec.cols), FREE)

    def _fill(self, mask: np.ndarray, polygon: Polygon) -> None:
        """Mark the cells whose centres lie inside ``polygon`` (and the cells its edges cross)."""
        if polygon.is_empty:
            return
        import cv2  # here, not at the top: the server imports this module's names, not OpenCV (0.4 s)

        parts = getattr(polygon, 'geoms', [polygon])
        scale = (1 << SUBPIXEL_BITS) / self.spec.resolution
        offset = 0.5 * (1 << SUBPIXEL_BITS)
        for part in parts:
            if part.geom_type != 'Polygon' or part.is_empty:
                continue
            exterior = np.asarray(part.exterior.coords)[:, :2] * scale - offset
            cv2.fillPoly(mask, [np.round(exterior).astype(np.int32)], 1, cv2.LINE_8, SUBPIXEL_BITS)

    def rasterise(self, outlines: Iterable[Polygon]) -> np.ndarray:
        """The cost array for ``outlines`` (does not change the grid)."""
        lethal = np.zeros(self.costs.shape, np.uint8)
        inflated = np.zeros(self.costs.shape, np.uint8)
        near = np.zeros(self.costs.shape, np.uint8)
        for outline in outlines:
            self._fill(lethal, outline)
            if self.robot_radius > 0:
                self._fill(inflated, outline.buffer(self.robot_radius, 8))
            if self.caution > 0:
                self._fill(near, outline.buffer(self.robot_radius + self.caution, 8))
        costs = np.full(self.costs.shape, FREE)
        costs[near.astype(bool)] = CAUTION
        costs[inflated.astype(bool)] = INFLATED
        costs[lethal.astype(bool)] = LETHAL
        return costs

    def apply(self, outlines: Iterable[Polygon]) -> list[tuple[Cell, float]]:
        """Replace the grid by the one for ``outlines``; return the changed cells with their new costs."""
        costs = self.rasterise(outlines)
        rows, cols = np.nonzero(costs != self.costs)
        self.costs = costs
        return [((int(r), int(c)), float(costs[r, c])) for r, c in zip(rows, cols, strict=True)]

    def occupancy(self) -> np.ndarray:
        """nav_msgs/OccupancyGrid values, row-major: 0 free, 99 inflated margin, 100 obstacle."""
        values = np.zeros(self.costs.shape, np.int8)
        values[self.costs >= INFLATED] = 99
        values[self.costs == LETHAL] = 100
        return values


def crosses_margin(path: Sequence[Cell], costs: np.ndarray) -> bool:
    """True when ``path`` enters an inflated margin (or an obstacle) between its first and its
    last cell outside one (free, or only ``CAUTION``).

    Leaving the margin the robot starts in, and entering the one its goal stands
    in, are allowed; anything else means the plan squeezes past an obstacle.
    """
    free = [i for i, cell in enumerate(path) if costs[cell] < INFLATED]
    if not free:
        return False
    return any(costs[cell] >= INFLATED for cell in path[free[0] : free[-1] + 1])


MIN_KEPT = 1e-3
"""m²: a piece of an earlier outline outside the region a report is about, smaller than this, is dropped."""


def _polygons(shape) -> list[Polygon]:
    """The polygons of a shapely geometry (a polygon, a collection of them, or nothing)."""
    return [
        part for part in getattr(shape, 'geoms', [shape]) if part.geom_type == 'Polygon' and not part.is_empty
    ]


Source = tuple[str, str]
"""Who reported outlines: (role, vision system)."""


class ObstacleMemory:
    """The latest outlines per source, each forgotten ``ttl`` seconds after it was last heard; each
    outline may carry facts of its own (its top and clearance), which a piece of it keeps."""

    def __init__(self, ttl: float):
        if not ttl > 0:
            raise OccupancyError(f'obstacle_ttl: expected a positive number of seconds, got {ttl}')
        self.ttl = ttl
        self._sources: dict[Source, tuple[float, list[tuple[Polygon, Any]]]] = {}  # -> (until, outlines)

    def observe(
        self,
        source: Source,
        outlines: Sequence[Polygon],
        now: float,
        linger: float = 0.0,
        region: tuple[float, float, float, float] | None = None,
        facts: Sequence[Any] | None = None,
    ) -> None:
        """``source`` reports everything it now sees (in ``region``): its earlier outlines are
        replaced (there).

        :param linger: a report of nothing keeps the outlines it replaces this many seconds
            more (never beyond their ``ttl``): an obstacle that vanishes from one report (a
            person who stopped fades out of a motion model) is not driven into at once.
        :param region: the region the report is about, for obstacles that stand still: what
            the source reported before outside it stays (the robot asked elsewhere, the
            obstacle is still there). None: the report is about everything.
        :param facts: one per outline (default None each), given back by :meth:`entries`.
        """
        given = list(zip(outlines, facts if facts is not None else [None] * len(outlines), strict=True))
        if region is not None and source in self._sources:
            outside = box(*region)
            kept = [
                (piece, fact)
                for before, fact in self._sources[source][1]
                for piece in _polygons(before.difference(outside))
                if piece.area >= MIN_KEPT
            ]
            given = [*given, *kept]
        if not given and linger > 0 and source in self._sources:
            until, before = self._sources[source]
            self._sources[source] = (min(until, now + linger), before)
            return
        self._sources[source] = (now + self.ttl, given)

    def entries(self, now: float) -> dict[Source, list[tuple[Polygon, Any]]]:
        """(outline, its facts) of every source heard within ``ttl``; older sources are forgotten."""
        for source in [s for s, (until, _) in self._sources.items() if now > until]:
            del self._sources[source]
        return {source: list(outlines) for source, (_, outlines) in self._sources.items()}

    def current(self, now: float) -> dict[Source, list[Polygon]]:
        """Outlines of every source heard within ``ttl``; older sources are forgotten."""
        return {source: [o for o, _ in found] for source, found in self.entries(now).items()}


class MapPublishing:
    """When the robot publishes its map: at most once per ``period`` while the map changes, a
    change inside a period at the first update after it ends, and every ``refresh`` seconds
    whatever happens (a late subscriber of a latched topic needs nothing, a recorder does).

    The whole grid goes out each time (a byte a cell: 15,400 B on the 4.2 floor at 0.05 m): on a robot's
    2 Mbit/s link, a map per change took 19-30 % of it. ``period`` 0 publishes every change.

    >>> publishing = MapPublishing(period=1.0, refresh=5.0)
    >>> calls = ((0.0, True), (0.4, True), (0.8, False), (1.1, False))
    >>> [publishing.due(now, changed) for now, changed in calls]
    [True, False, False, True]
    >>> publishing.due(2.5, False), publishing.due(6.2, False)
    (False, True)
    """

    def __init__(self, period: float, refresh: float = 5.0):
        self.period = period
        self.refresh = refresh
        self._last = -math.inf
        self._pending = False

    def due(self, now: float, changed: bool) -> bool:
        """Whether to publish now; ``changed``: the map changed since the last call."""
        self._pending = self._pending or changed
        since = now - self._last
        if (self._pending and since >= self.period) or since >= self.refresh:
            self._last, self._pending = now, False
            return True
        return False
