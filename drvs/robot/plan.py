"""The robot's plan as a polyline: D* Lite's grid path smoothed into straight segments, and the
geometry of following it (the nearest point on it, the point a lookahead further on).

A grid path runs from cell centre to cell centre in 8 directions: a route at any other angle
is a staircase, and steering along it weaves. :func:`shortcut` replaces each stretch of free
cells by the fewest straight segments whose cells are all free (line-of-sight shortcutting);
:func:`densify` puts points back every cell along them, so that distances to the plan stay
vertex distances. How the robot follows it: docs/nodes/blind_robot.md ("Following the plan").
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from drvs.robot.dstar_lite import FREE

__all__ = ['Box', 'corridor', 'densify', 'line_is_free', 'nearest_on_path', 'point_along', 'shortcut']

Point = tuple[float, float]
Box = tuple[float, float, float, float]
SAMPLES_PER_CELL = 4
"""Points per cell length at which a segment is checked (and the cells around each point)."""
CLEARANCE = 1.0
"""Cells: a shortcut keeps this far from any cell that is not free (the grid path's cell centres keep
half a cell at least)."""


def line_is_free(
    a: Point, b: Point, costs: np.ndarray, resolution: float, clearance: float = CLEARANCE
) -> bool:
    """Whether every cell within ``clearance`` cells of the segment ``a``-``b`` (metres) is
    ``FREE``; a point off the grid counts as its nearest edge cell, as
    :class:`~drvs.robot.occupancy.GridSpec` does."""
    rows, cols = costs.shape
    a_cells = np.asarray(a, float) / resolution
    b_cells = np.asarray(b, float) / resolution
    n = max(2, int(math.ceil(np.abs(b_cells - a_cells).max() * SAMPLES_PER_CELL)) + 1)
    t = np.linspace(0.0, 1.0, n)[:, None]
    points = a_cells[None, :] + t * (b_cells - a_cells)[None, :]
    for dx, dy in (
        (-clearance, -clearance),
        (-clearance, clearance),
        (clearance, -clearance),
        (clearance, clearance),
    ):
        col = np.clip(np.floor(points[:, 0] + dx).astype(int), 0, cols - 1)
        row = np.clip(np.floor(points[:, 1] + dy).astype(int), 0, rows - 1)
        if not (costs[row, col] == FREE).all():
            return False
    return True


def shortcut(
    points: Sequence[Point], free: Sequence[bool], costs: np.ndarray, resolution: float
) -> list[Point]:
    """``points`` (a path, metres) with every run of free points (``free``) cut into the fewest
    straight segments over free cells, found greedily: from each corner, the farthest point of
    the run that it sees (by doubling, then halving the step; the segment found is checked).

    Points that are not free (leaving the margin the robot starts in, entering the one around
    its goal) stay as they are.

    >>> costs = np.ones((4, 8))
    >>> staircase = [(0.5, 0.5), (1.5, 0.5), (2.5, 1.5), (3.5, 1.5), (4.5, 2.5), (5.5, 2.5)]
    >>> shortcut(staircase, [True] * 6, costs, 1.0)
    [(0.5, 0.5), (5.5, 2.5)]
    """
    if len(points) != len(free):
        raise ValueError(f'free: expected {len(points)} flags, one per point, got {len(free)}')
    result: list[Point] = []
    i, n = 0, len(points)
    while i < n:
        result.append(points[i])
        if not free[i] or i + 1 == n or not free[i + 1]:
            i += 1
            continue
        end = i + 1  # the run of free points from i
        while end + 1 < n and free[end + 1]:
            end += 1
        i = _farthest_seen(points, i, end, costs, resolution)
    return _deduplicated(result)


def _farthest_seen(points: Sequence[Point], i: int, end: int, costs: np.ndarray, resolution: float) -> int:
    """The farthest index in (i, end] whose point ``points[i]`` sees over free cells (at least i + 1)."""
    step, seen = 1, i + 1
    while seen + step <= end and line_is_free(points[i], points[seen + step], costs, resolution):
        seen += step
        step *= 2
    while step > 1:
        step //= 2
        if seen + step <= end and line_is_free(points[i], points[seen + step], costs, resolution):
            seen += step
    return seen


def _deduplicated(points: list[Point]) -> list[Point]:
    return [p for k, p in enumerate(points) if k == 0 or p != points[k - 1]]


def densify(points: Sequence[Point], spacing: float) -> list[Point]:
    """The polyline through ``points`` with a point at most every ``spacing`` metres along it.

    >>> densify([(0.0, 0.0), (1.0, 0.0)], 0.4)
    [(0.0, 0.0), (0.3333333333333333, 0.0), (0.6666666666666666, 0.0), (1.0, 0.0)]
    """
    if not spacing > 0:
        raise ValueError(f'spacing: must be positive, got {spacing}')
    result: list[Point] = [tuple(points[0])] if points else []  # type: ignore[list-item]
    for a, b in zip(points, points[1:], strict=False):
        steps = max(1, math.ceil(math.dist(a, b) / spacing - 1e-9))
        result += [
            (a[0] + (b[0] - a[0]) * k / steps, a[1] + (b[1] - a[1]) * k / steps) for k in range(1, steps + 1)
        ]
    return result


def nearest_on_path(path: Sequence[Point], position: Point, first: int = 0) -> tuple[int, float]:
    """The segment of ``path`` (from vertex ``first`` on) nearest ``position``: (its first vertex,
    the fraction along it of the nearest point)."""
    points = np.asarray(path[first:], float)
    if len(points) < 2:
        return first, 0.0
    a, b = points[:-1], points[1:]
    ab = b - a
    lengths = (ab**2).sum(axis=1)
    p = np.asarray(position, float)
    u = np.clip(((p - a) * ab).sum(axis=1) / np.where(lengths > 0, lengths, 1.0), 0.0, 1.0)
    distances = np.hypot(*(a + u[:, None] * ab - p).T)
    k = int(np.argmin(distances))
    return first + k, float(u[k])


def point_along(path: Sequence[Point], segment: int, fraction: float, distance: float) -> Point:
    """The point ``distance`` metres along ``path`` from the point ``fraction`` along its segment
    ``segment``; the path's end when it is shorter."""
    a, b = path[segment], path[min(segment + 1, len(path) - 1)]
    left = distance + fraction * math.dist(a, b)
    for k in range(segment, len(path) - 1):
        a, b = path[k], path[k + 1]
        length = math.dist(a, b)
        if left <= length and length > 0:
            return (a[0] + (b[0] - a[0]) * left / length, a[1] + (b[1] - a[1]) * left / length)
        left -= length
    return tuple(path[-1])  # type: ignore[return-value]


def corridor(path: Sequence[Point], margin: float) -> Box:
    """The box the plan ``path`` spans, grown by ``margin``: the floor it must know about.

    >>> corridor([(1.0, 2.0), (3.0, 1.0)], 0.5)
    (0.5, 0.5, 3.5, 2.5)
    """
    xs, ys = [p[0] for p in path], [p[1] for p in path]
    return (min(xs) - margin, min(ys) - margin, max(xs) + margin, max(ys) + margin)
