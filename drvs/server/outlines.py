"""Outlines as the fusion tracker handles them: checked once, with centroid, area and bounds.

An outline that cannot be a floor shape (fewer than 3 points, no area, a coordinate that is not
a finite number within :data:`LIMIT` metres) is refused here, so the tracker never sees it.
Overlap areas go to shapely (GEOS) only after the bounding boxes overlap. The method:
docs/fusion-tracking.md.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from shapely.affinity import translate
from shapely.errors import ShapelyError
from shapely.geometry import Polygon
from shapely.geometry.polygon import orient
from shapely.ops import unary_union

__all__ = ['LIMIT', 'MIN_AREA', 'Shape', 'clean', 'combine', 'contains', 'overlap_area', 'union_outline']

LIMIT = 1e6
"""Metres: a coordinate farther from the origin is refused (no map is that big; products of such
values would overflow)."""
MIN_AREA = 1e-6
"""Square metres: an outline with less area (1 mm x 1 mm) is refused as degenerate."""

Point = tuple[float, float]
Box = tuple[float, float, float, float]


@dataclass(eq=False)
class Shape:
    """One checked outline: ``points`` (n x 2), its centroid, area and bounds (min_x, min_y, max_x, max_y)."""

    points: np.ndarray
    centroid: Point
    area: float
    bounds: Box
    convex: bool = False
    """Every corner turns the same way."""
    _polygon: Polygon | None = field(default=None, repr=False)

    def polygon(self) -> Polygon:
        """The outline as a valid shapely polygon (a self-intersecting outline is repaired)."""
        if self._polygon is None:
            polygon = Polygon(self.points)
            if not polygon.is_valid:
                polygon = polygon.buffer(0)
                if polygon.geom_type != 'Polygon':
                    polygon = polygon.convex_hull
            self._polygon = polygon
        return self._polygon

    @property
    def radius(self) -> float:
        """Half the diagonal of the bounds: the outline's size."""
        return 0.5 * math.hypot(self.bounds[2] - self.bounds[0], self.bounds[3] - self.bounds[1])


def clean(outline: Sequence[Sequence[float]]) -> Shape | None:
    """The outline checked, or None when it is no floor shape (see the module docstring).

    >>> clean([(0, 0), (2, 0), (2, 1), (0, 1)]).centroid
    (1.0, 0.5)
    >>> clean([(0, 0), (1, 1), (2, 2)]) is None, clean([(0, 0), (1, float('nan')), (0, 1)]) is None
    (True, True)
    """
    try:
        points = np.asarray(outline, dtype=float)
    except (TypeError, ValueError):
        return None
    if points.ndim != 2 or points.shape[0] < 3 or points.shape[1] != 2:
        return None
    if not np.all(np.isfinite(points)) or np.abs(points).max() > LIMIT:
        return None
    # Shoelace about the first point (keeps precision far from the origin); either orientation.
    here = points - points[0]
    after = np.concatenate((here[1:], here[:1]))
    cross = here[:, 0] * after[:, 1] - after[:, 0] * here[:, 1]
    twice_area = float(cross.sum())
    if abs(twice_area) < 2 * MIN_AREA:
        return None
    cx, cy = ((here + after) * cross[:, None]).sum(axis=0) / (3 * twice_area) + points[0]
    edges = after - here
    following = np.concatenate((edges[1:], edges[:1]))
    turns = edges[:, 0] * following[:, 1] - edges[:, 1] * following[:, 0]
    convex = bool((turns >= -1e-12).all() or (turns <= 1e-12).all())
    low, high = points.min(axis=0), points.max(axis=0)
    bounds = (float(low[0]), float(low[1]), float(high[0]), float(high[1]))
    return Shape(points, (float(cx), float(cy)), abs(twice_area) / 2, bounds, convex=convex)


def _from_polygon(polygon: Polygon) -> Shape | None:
    polygon = orient(polygon, 1.0)
    shape = clean(list(polygon.exterior.coords)[:-1])
    if shape is not None:
        shape._polygon = polygon
    return shape


def combine(shapes: Sequence[Shape]) -> Shape:
    """One camera's pieces of one object (blobs it split) as one: the outline is their union, or its
    convex hull when they do not touch; the centroid is the area-weighted mean of the pieces'."""
    if len(shapes) == 1:
        return shapes[0]
    area = sum(s.area for s in shapes)
    cx = sum(s.centroid[0] * s.area for s in shapes) / area
    cy = sum(s.centroid[1] * s.area for s in shapes) / area
    try:
        union = unary_union([s.polygon() for s in shapes])
        if union.geom_type != 'Polygon':
            union = union.convex_hull
        merged = _from_polygon(union)
    except (ShapelyError, ValueError):
        merged = None
    if merged is None:  # cannot happen for clean pieces; the largest piece then stands for them
        merged = max(shapes, key=lambda s: s.area)
    return Shape(merged.points, (cx, cy), merged.area, merged.bounds, merged.convex, merged._polygon)


def overlap_area(a: Shape, b: Shape, offset: Point = (0.0, 0.0)) -> float:
    """Area shared by ``a`` and ``b`` moved by ``offset``; 0 when their bounds do not overlap."""
    dx, dy = offset
    if (
        a.bounds[2] <= b.bounds[0] + dx
        or b.bounds[2] + dx <= a.bounds[0]
        or a.bounds[3] <= b.bounds[1] + dy
        or b.bounds[3] + dy <= a.bounds[1]
    ):
        return 0.0
    mine = a.polygon()
    if dx or dy:  # a moved back rather than b moved on: the same area
        mine = translate(mine, -dx, -dy)
    try:
        return float(mine.intersection(b.polygon()).area)
    except ShapelyError:
        return 0.0


def union_outline(shapes: Sequence[tuple[Shape, Point]]) -> tuple[Point, ...]:
    """The union of ``shapes``, each moved by its offset, as a counter-clockwise outline.

    When every shape is convex (the usual blob of one object seen by several cameras), their convex
    hull stands for the union: never smaller, larger only by the slivers between offset views, and
    no GEOS call. A union in pieces becomes its convex hull too.
    """
    if len(shapes) == 1:
        shape, (dx, dy) = shapes[0]
        points = shape.points + (dx, dy)
        if _signed_area(points) < 0:
            points = points[::-1]
        return tuple((float(x), float(y)) for x, y in points)
    moved = [shape.points + offset for shape, offset in shapes]
    if all(shape.convex for shape, _ in shapes):
        return _hull(np.concatenate(moved))
    try:
        union = unary_union([Polygon(p) if Polygon(p).is_valid else Polygon(p).buffer(0) for p in moved])
    except (ShapelyError, ValueError):
        return _hull(np.concatenate(moved))
    if union.geom_type != 'Polygon':
        return _hull(np.concatenate(moved))
    union = orient(union, 1.0)
    return tuple((float(x), float(y)) for x, y in list(union.exterior.coords)[:-1])


def _hull(points: np.ndarray) -> tuple[Point, ...]:
    """The convex hull of ``points``, counter-clockwise (Andrew's monotone chain).

    >>> _hull(np.array([(0, 0), (2, 0), (1, 1), (2, 2), (0, 2)]))
    ((0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0))
    """
    unique = sorted({(float(x), float(y)) for x, y in points.tolist()})
    if len(unique) < 3:
        return tuple(unique)

    def chain(ordered: Sequence[Point]) -> list[Point]:
        kept: list[Point] = []
        for p in ordered:
            while len(kept) >= 2:
                (ax, ay), (bx, by) = kept[-2], kept[-1]
                if (bx - ax) * (p[1] - ay) - (by - ay) * (p[0] - ax) > 0:
                    break
                kept.pop()
            kept.append(p)
        return kept

    lower, upper = chain(unique), chain(unique[::-1])
    return tuple(lower[:-1] + upper[:-1])


def _signed_area(points: np.ndarray) -> float:
    x, y = points[:, 0], points[:, 1]
    return 0.5 * float((x[:-1] * y[1:] - x[1:] * y[:-1]).sum() + x[-1] * y[0] - x[0] * y[-1])


def contains(polygon: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Which of ``points`` (m x 2) lie inside ``polygon`` (n x 2), by ray casting (vectorised).

    >>> contains(np.array([(0, 0), (2, 0), (2, 2), (0, 2)]), np.array([(1, 1), (3, 1)])).tolist()
    [True, False]
    """
    x, y = points[:, 0:1], points[:, 1:2]
    x1, y1 = polygon[:, 0], polygon[:, 1]
    x2, y2 = np.roll(x1, -1), np.roll(y1, -1)
    crosses = (y1 > y) != (y2 > y)
    with np.errstate(divide='ignore', invalid='ignore'):
        at = x1 + (y - y1) * (x2 - x1) / (y2 - y1)
    return np.logical_and(crosses, x < at).sum(axis=1) % 2 == 1
