"""A spatial index of field-of-view polygons that stays fast while cameras come, go and move.

A hierarchical uniform grid (no rebuilds: insert, remove and move in O(1)), with an exact
test in plain Python where it is certain and GEOS's relate (:func:`interiors_intersect`,
the matching rule) where it is not. Thread-safe (one internal lock). The design, the
matching rule and why: docs/design.md ("Matching"); ``bench/registry.py`` measures it.
"""

from __future__ import annotations

import logging
import math
import struct
import threading
from array import array
from collections.abc import Hashable, Iterator, Sequence
from typing import Any

from shapely.errors import ShapelyError
from shapely.geometry import LineString, Point, Polygon
from shapely.geometry.base import BaseGeometry
from shapely.prepared import prep

logger = logging.getLogger('rosout.' + __name__)

__all__ = ['FieldOfViewIndex', 'interiors_intersect']

_KEY = object()  # insert()'s default value: the key
SPAN = 1
"""A polygon's bounding box is at most SPAN cells of its level wide and high.

1 was measured faster than 2 or 3 at 100,000 cameras: a visited cell costs more
than the few more bounding boxes scanned in larger ones."""
MIN_LEVEL = -6
"""The finest cells are 2**MIN_LEVEL m (1.6 cm); smaller polygons share them."""
SHORTEST = 1e-100
"""Shorter edges (far from any camera) go to GEOS: their products could fall below floats' full precision."""
TINY = 1e-150
"""A coordinate this close to zero, but not zero, sends its shape to GEOS: products of such values
fall below floats' range, where GEOS's answers do not always follow its own rule; the index then
gives the same answers as GEOS."""
TOLERANCE = 1e-12
"""Relative to the largest coordinate: a separating-axis overlap closer to zero goes to GEOS."""


def interiors_intersect(field_of_view: BaseGeometry, region: BaseGeometry) -> bool:
    """True if the interiors of the two geometries share at least one point.

    GEOS's relate is not robust for every valid input (a region corner on a
    vertex rounded to float32 can raise "side location conflict"); then the
    answer falls back to intersection (prepared geometry, another algorithm),
    and at last to overlapping bounds. Both may also count touching edges: a
    request forwarded to one camera too many costs little, a lost request costs
    a robot its answer.
    """
    try:
        return field_of_view.relate_pattern(region, 'T********')
    except ShapelyError as error:
        logger.warning('relate failed (%s); matching by intersection instead', error)
    try:
        return prep(field_of_view).intersects(region)
    except ShapelyError as error:
        logger.warning('intersection failed too (%s); matching by bounds', error)
        return _boxes_overlap(field_of_view.bounds, region.bounds)


def _boxes_overlap(a: tuple, b: tuple) -> bool:
    return a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]


def _box_geometry(bounds: Sequence[float]) -> BaseGeometry:
    """The region (min_x, min_y, max_x, max_y) as shapely sees it: rectangle, segment or point."""
    min_x, min_y, max_x, max_y = bounds
    if min_x == max_x and min_y == max_y:
        return Point(min_x, min_y)
    if min_x == max_x or min_y == max_y:
        return LineString([(min_x, min_y), (max_x, max_y)])
    return Polygon([(min_x, min_y), (max_x, min_y), (max_x, max_y), (min_x, max_y)])


def separating_axes(vertices: Sequence[tuple[float, float]]) -> array | None:
    """The outward edge normals of a convex polygon and how far it reaches along each.

    Returns ``nx, ny, |nx|, |ny|, reach`` for each edge, one after the other: the
    unit normal pointing out of the polygon, its absolute components, and the
    projection of the edge (the polygon's farthest point) on it. None (use GEOS)
    if the polygon is not surely convex: an edge shorter than :data:`SHORTEST`,
    a turn too close to straight to tell its side, turns that do not all go one
    way, or an outline that winds more than once.
    """
    n = len(vertices)
    if n < 3:
        return None
    hypot, atan2 = math.hypot, math.atan2
    x1, y1 = vertices[0]
    x0, y0 = vertices[-1]
    pdx, pdy = x1 - x0, y1 - y0
    plength = hypot(pdx, pdy)
    if not SHORTEST < plength < math.inf:
        return None
    edges, left, turning = [], None, 0.0
    for i in range(n):
        x2, y2 = vertices[i + 1] if i + 1 < n else vertices[0]
        dx, dy = x2 - x1, y2 - y1
        length = hypot(dx, dy)
        if not SHORTEST < length < math.inf:
            return None
        cross = pdx * dy - pdy * dx
        straight = 1e-9 * plength * length  # a turn this close to straight has no sure side
        if cross > straight:
            if left is False:
                return None
            left = True
        elif cross < -straight:
            if left:
                return None
            left = False
        else:
            return None
        turning += atan2(cross, pdx * dx + pdy * dy)
        edges.append((dx / length, dy / length, x1, y1))
        pdx, pdy, plength, x1, y1 = dx, dy, length, x2, y2
    if abs(abs(turning) - 2 * math.pi) > 1.0:  # a star: turns one way, but twice round
        return None
    axes = array('d')
    for ux, uy, x, y in edges:
        nx, ny = (uy, -ux) if left else (-uy, ux)  # outward: right of a counter-clockwise edge
        axes.extend((nx, ny, abs(nx), abs(ny), nx * x + ny * y))
    return axes


def _vertices(geometry: BaseGeometry) -> list[tuple[float, float]] | None:
    """The outline of a polygon without holes (no repeated last vertex), else None."""
    if geometry.geom_type != 'Polygon' or len(geometry.interiors) > 0:
        return None
    return [(float(x), float(y)) for x, y in geometry.exterior.coords[:-1]]


_BOX = struct.Struct('4d')
_boxes = _BOX.iter_unpack
_vertices_of = struct.Struct('2d').iter_unpack
_axes_of = struct.Struct('5d').iter_unpack


class _Cell:
    """The polygons of one cell: their bounding boxes packed side by side, and their entries.

    Packed into a ``bytes`` (whose data lies in the object itself, unlike an
    array's), a cell's boxes cost one or two cache misses to scan; rewriting it
    on each change costs less than that saves.
    """

    __slots__ = ('boxes', 'entries')

    def __init__(self) -> None:
        self.boxes = b''  # min_x, min_y, max_x, max_y of each entry as doubles, in entry order
        # (key, geometry, its vertices x, y, ... or None, separating_axes() or None, its tolerance,
        # value), the vertices and the axes as packed doubles (bytes)
        self.entries: list[tuple] = []


class _Level:
    """The cells of one size, by row (y index) then column (x index)."""

    __slots__ = ('scale', 'rows', 'cells', 'reach')

    def __init__(self, level: int):
        self.scale = 2.0**-level  # cell index = floor(coordinate * scale), exact for a power of two
        self.rows: dict[int, dict[int, _Cell]] = {}
        self.cells = 0  # occupied cells
        self.reach = 0.0  # in cells: the widest or highest bounding box ever put in (at most SPAN)

    def visit(self, min_x: float, min_y: float, max_x: float, max_y: float) -> Iterator[_Cell]:
        """The occupied cells that may hold a polygon whose bounding box meets the given one."""
        scale, rows, floor = self.scale, self.rows, math.floor
        # A polygon meets the box only if its lower-left corner is at most ``reach`` to the left of and
        # below the box. In cell units (exact: a power of two), less a margin for the subtraction's rounding.
        left, bottom = min_x * scale - self.reach, min_y * scale - self.reach
        ix0, ix1 = floor(left - 1e-15 * abs(left) - 1e-300), floor(max_x * scale)
        iy0, iy1 = floor(bottom - 1e-15 * abs(bottom) - 1e-300), floor(max_y * scale)
        if (ix1 - ix0 + 1) * (iy1 - iy0 + 1) <= self.cells:
            for iy in range(iy0, iy1 + 1):
                row = rows.get(iy)
                if row is not None:
                    for ix in range(ix0, ix1 + 1):
                        cell = row.get(ix)
                        if cell is not None:
                            yield cell
        else:  # a region far bigger than these cells: visit the occupied ones
            for iy, row in rows.items():
                if iy0 <= iy <= iy1:
                    for ix, cell in row.items():
                        if ix0 <= ix <= ix1:
                            yield cell


class FieldOfViewIndex:
    """Polygons by key; :meth:`query_box` answers those whose interior meets a region.

    Queries answer each polygon's value (given to :meth:`insert`; by default its key).
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._levels: dict[int, _Level] = {}
        self._where: dict[Hashable, list] = {}  # key -> [level, row, column, cell, slot in the cell]

    def __len__(self) -> int:
        return len(self._where)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._where

    def get(self, key: Hashable) -> BaseGeometry | None:
        with self._lock:
            place = self._where.get(key)
            return place[3].entries[place[4]][1] if place is not None else None

    # -- changes -----------------------------------------------------------------------------
    def insert(
        self,
        key: Hashable,
        geometry: BaseGeometry,
        vertices: Sequence[Sequence[float]] | None = None,
        value: object = _KEY,
    ) -> None:
        """Add ``key`` or replace its polygon (a move).

        :param vertices: the polygon's outline if the caller has it (``geometry``
            must be ``Polygon(vertices)``): it spares reading it back from GEOS.
        :param value: what queries answer for it (default: ``key``). The registry
            gives its entry, so that a match need not look each one up again.
        """
        if vertices is None:
            outline = _vertices(geometry) or []
        else:
            outline = [(float(point[0]), float(point[1])) for point in vertices]
            if len(outline) > 1 and outline[0] == outline[-1]:
                outline.pop()
        box: tuple[float, ...]
        if outline:
            values = [v for point in outline for v in point]
            xs, ys = values[0::2], values[1::2]
            box = (min(xs), min(ys), max(xs), max(ys))
        else:
            values, box = [], tuple(geometry.bounds)
        min_x, min_y, max_x, max_y = box
        tolerance = TOLERANCE * max(1.0, abs(min_x), abs(min_y), abs(max_x), abs(max_y))
        if (
            values
            and min(max_x - min_x, max_y - min_y) > tolerance
            and (min(abs(v) for v in values) >= TINY or not any(0 < abs(v) < TINY for v in values))
        ):
            corners: bytes | None = array('d', values).tobytes()
            axis_array = separating_axes(outline)
            axes = axis_array.tobytes() if axis_array is not None else None
        else:  # no outline, thinner than the tolerance, or TINY values (none of them everyday): GEOS
            corners = axes = None
        entry = (key, geometry, corners, axes, tolerance, key if value is _KEY else value)
        extent = max(max_x - min_x, max_y - min_y) * (1 + 1e-9)  # rounding never makes it smaller
        level = max(MIN_LEVEL, math.frexp(extent / SPAN)[1])  # 2**level > extent / SPAN
        with self._lock:
            self._remove(key)
            cells = self._levels.get(level)
            if cells is None:
                cells = self._levels[level] = _Level(level)
            if extent * cells.scale > cells.reach:
                cells.reach = extent * cells.scale
            iy, ix = math.floor(min_y * cells.scale), math.floor(min_x * cells.scale)
            row = cells.rows.get(iy)
            if row is None:
                row = cells.rows[iy] = {}
            cell = row.get(ix)
            if cell is None:
                cell = row[ix] = _Cell()
                cells.cells += 1
            cell.boxes += _BOX.pack(*box)
            cell.entries.append(entry)
            self._where[key] = [level, iy, ix, cell, len(cell.entries) - 1]

    def set_value(self, key: Hashable, value: object) -> bool:
        """What queries answer for ``key`` from now on (its polygon stays); False if it is not there."""
        with self._lock:
            place = self._where.get(key)
            if place is None:
                return False
            entries, slot = place[3].entries, place[4]
            entries[slot] = entries[slot][:5] + (value,)
            return True

    def remove(self, key: Hashable) -> bool:
        """Remove ``key``; False if it was not there."""
        with self._lock:
            return self._remove(key)

    def _remove(self, key: Hashable) -> bool:
        """Called with the lock held: the cell's last entry takes the removed one's slot."""
        place = self._where.pop(key, None)
        if place is None:
            return False
        level, iy, ix, cell, slot = place
        entries, boxes, size = cell.entries, cell.boxes, _BOX.size
        last = len(entries) - 1
        if slot != last:
            entries[slot] = entries[last]
            self._where[entries[slot][0]][4] = slot
            cell.boxes = boxes[: size * slot] + boxes[size * last :] + boxes[size * (slot + 1) : size * last]
        else:
            cell.boxes = boxes[: size * last]
        del entries[last]
        if not entries:
            cells = self._levels[level]
            row = cells.rows[iy]
            del row[ix]
            cells.cells -= 1
            if not row:
                del cells.rows[iy]
                if not cells.rows:
                    del self._levels[level]
        return True

    # -- queries -----------------------------------------------------------------------------
    def candidates(self, bounds: Sequence[float]) -> list[Any]:
        """The values of the polygons whose bounding box meets ``bounds`` (min_x, min_y, max_x, max_y)."""
        with self._lock:
            return [entry[5] for entry in self._candidates(bounds)]

    def query(self, region: BaseGeometry) -> list[Any]:
        """The values of the polygons whose interior meets that of any geometry ``region`` (GEOS)."""
        with self._lock:
            entries = self._candidates(region.bounds)
        return [entry[5] for entry in entries if interiors_intersect(entry[1], region)]

    def _candidates(self, bounds: Sequence[float]) -> list[tuple]:
        """Called with the lock held: the entries whose bounding box meets ``bounds``."""
        qx0, qy0, qx1, qy1 = bounds
        return [
            cell.entries[slot]
            for cells in self._levels.values()
            for cell in cells.visit(qx0, qy0, qx1, qy1)
            for slot, (x0, y0, x1, y1) in enumerate(_boxes(cell.boxes))
            if x0 <= qx1 and qx0 <= x1 and y0 <= qy1 and qy0 <= y1
        ]

    def query_box(self, bounds: Sequence[float]) -> list[Any]:
        """The values of the polygons whose interior meets the region (min_x, min_y, max_x, max_y).

        The region is a rectangle, or a segment or a point when it has no width
        or height (as :func:`drvs.common.validation.region_geometry` makes it). The same
        answers as :func:`interiors_intersect` on each polygon.
        """
        qx0, qy0, qx1, qy1 = bounds
        cx, cy, hx, hy = (qx0 + qx1) * 0.5, (qy0 + qy1) * 0.5, (qx1 - qx0) * 0.5, (qy1 - qy0) * 0.5
        tolerance = TOLERANCE * max(1.0, abs(qx0), abs(qy0), abs(qx1), abs(qy1))
        # A segment, a point, thinner than the tolerance (GEOS itself errs on a box 1e-162 high), or
        # with TINY values: GEOS decides, as it always did.
        geos = (
            qx1 - qx0 <= tolerance
            or qy1 - qy0 <= tolerance
            or 0 < abs(qx0) < TINY
            or 0 < abs(qy0) < TINY
            or 0 < abs(qx1) < TINY
            or 0 < abs(qy1) < TINY
        )
        found, unsure = [], []
        with self._lock:
            for cells in self._levels.values():
                for cell in cells.visit(qx0, qy0, qx1, qy1):
                    entries = cell.entries
                    for slot, (x0, y0, x1, y1) in enumerate(_boxes(cell.boxes)):
                        if x0 > qx1 or qx0 > x1 or y0 > qy1 or qy0 > y1:
                            continue
                        entry = entries[slot]
                        _, _, corners, axes, limit, value = entry
                        if geos or corners is None:
                            unsure.append(entry)
                            continue
                        # Interiors can only meet where the bounding boxes overlap by a positive length.
                        if x0 == qx1 or qx0 == x1 or y0 == qy1 or qy0 == y1:
                            continue
                        for x, y in _vertices_of(corners):
                            if qx0 < x < qx1 and qy0 < y < qy1:
                                found.append(value)  # a vertex inside the region: the interior comes close
                                break
                        else:
                            if axes is None:
                                unsure.append(entry)
                                continue
                            # The separating-axis test on the polygon's outward normals (the region's,
                            # x and y, were the bounding boxes'): it must reach past the region's
                            # nearest corner on each, by more than the rounding can explain.
                            if limit < tolerance:
                                limit = tolerance
                            verdict = True
                            for nx, ny, ax, ay, reach in _axes_of(axes):
                                margin = reach - nx * cx - ny * cy + ax * hx + ay * hy
                                if margin <= limit:
                                    if margin < -limit:
                                        verdict = False
                                        break
                                    verdict = None  # too close to call: GEOS, unless another normal separates
                            if verdict:
                                found.append(value)
                            elif verdict is None:
                                unsure.append(entry)
        if unsure:
            region = _box_geometry(bounds)
            found.extend(entry[5] for entry in unsure if interiors_intersect(entry[1], region))
        return found
