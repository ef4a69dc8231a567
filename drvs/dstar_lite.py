"""D* Lite (Koenig and Likhachev, 2002) on an 8-connected grid of cell costs.

The search runs backwards from the goal, so when the robot moves only the key
modifier ``km`` changes, and when cells change only the vertices whose
``rhs`` depends on them are updated and :meth:`DStarLite.compute_shortest_path`
repairs the search from there (the optimised version, Figure 4 of the paper)
instead of starting again.

Costs. Each cell has a cost >= 1 (``FREE`` = 1) or ``math.inf`` (impassable).
Moving from cell ``a`` to a neighbour ``b`` costs the step length (1 straight,
sqrt 2 diagonal, in cells) times the cost of entering ``b``; a diagonal step
also pays the dearer of the two cells beside it, and is impossible when either
is impassable, so no path cuts the corner of an obstacle. The cost of the cell
a path starts in is never paid: a robot that finds itself on an expensive cell
leaves it by the cheapest way. The heuristic is the octile distance, which is
consistent because every cost is at least 1.

Exact arithmetic. D* Lite breaks ties between keys on their second component,
and its correctness depends on it: with floating-point sums, two mathematically
equal keys can differ in the last bit and the search stops one vertex early with
a wrong ``rhs`` at the start. So costs are fixed-point integers: a straight step
is ``SCALE`` units and a diagonal ``round(sqrt 2 * SCALE)`` (relative error below
1e-6); Python integers add exactly. Results are given back in cells (floats).

Cells are ``(row, col)`` pairs; internally a flat index ``row * cols + col``.

>>> planner = DStarLite([[1, 1, 1], [1, math.inf, 1], [1, 1, 1]], start=(0, 0), goal=(2, 2))
>>> planner.compute_shortest_path()
>>> planner.path()
[(0, 0), (0, 1), (0, 2), (1, 2), (2, 2)]
>>> planner.path_cost()
4.0
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections.abc import Iterable, Sequence

import numpy as np

FREE = 1.0
SQRT2 = math.sqrt(2.0)
INF = math.inf
SCALE = 1 << 20  # fixed-point units per cell of straight travel
STRAIGHT = SCALE
DIAGONAL = round(SQRT2 * SCALE)

Cell = tuple[int, int]


class PlanningError(ValueError):
    """Bad planner input (cell outside the grid, cost below 1); the message says which."""


def octile(a: Cell, b: Cell) -> float:
    """Octile distance between two cells: the cost of the best 8-connected path on free cells."""
    dr, dc = abs(a[0] - b[0]), abs(a[1] - b[1])
    return max(dr, dc) + (SQRT2 - 1.0) * min(dr, dc)


Key = tuple[int | float, int | float]


class _Queue:
    """A priority queue of vertices with lazy deletion: stale heap entries are skipped on read."""

    def __init__(self):
        self._heap: list[tuple[int | float, int | float, int, int]] = []
        self._key: dict[int, Key] = {}
        self._tie = itertools.count()

    def __contains__(self, vertex: int) -> bool:
        return vertex in self._key

    def __len__(self) -> int:
        return len(self._key)

    def push(self, vertex: int, key: Key) -> None:
        """Insert ``vertex`` or change its key."""
        self._key[vertex] = key
        heapq.heappush(self._heap, (key[0], key[1], next(self._tie), vertex))

    def remove(self, vertex: int) -> None:
        self._key.pop(vertex, None)

    def _clean(self) -> None:
        heap = self._heap
        while heap:
            k1, k2, _, vertex = heap[0]
            if self._key.get(vertex) == (k1, k2):
                return
            heapq.heappop(heap)

    def top(self) -> tuple[Key, int] | None:
        """The smallest (key, vertex), or None when empty."""
        self._clean()
        if not self._heap:
            return None
        k1, k2, _, vertex = self._heap[0]
        return (k1, k2), vertex


class DStarLite:
    """Incremental shortest paths from a moving start to a fixed goal on a grid of cell costs.

    :param costs: 2-D array-like (rows, cols) of cell costs, each >= 1 or inf.
    """

    def __init__(self, costs, start: Cell, goal: Cell):
        costs = np.asarray(costs, dtype=float)
        if costs.ndim != 2 or costs.size == 0:
            raise PlanningError(f'costs: expected a non-empty 2-D grid, got shape {costs.shape}')
        if np.isnan(costs).any() or (costs < FREE).any():
            raise PlanningError('costs: every cell cost must be >= 1 or inf')
        self.rows, self.cols = costs.shape
        self._cost: list[float] = costs.ravel().tolist()
        self._goal = self._index(goal, 'goal')
        self._start = self._index(start, 'start')
        self._last = self._start
        n = self.rows * self.cols
        self.g: list[int | float] = [INF] * n  # fixed-point costs to the goal, inf = unknown
        self.rhs: list[int | float] = [INF] * n
        self.km = 0
        self.queue = _Queue()
        self.expansions = 0  # vertices expanded since construction (for benchmarks and tests)
        self.rhs[self._goal] = 0
        self.queue.push(self._goal, self.calculate_key(self._goal))
        self._neighbours = self._neighbour_table()

    # -- grid helpers ----------------------------------------------------------------------
    def _index(self, cell: Cell, what: str) -> int:
        row, col = int(cell[0]), int(cell[1])
        if not (0 <= row < self.rows and 0 <= col < self.cols):
            raise PlanningError(f'{what}: cell {tuple(cell)} is outside the {self.rows}x{self.cols} grid')
        return row * self.cols + col

    def _cell(self, index: int) -> Cell:
        return divmod(index, self.cols)

    def _neighbour_table(self) -> list[tuple[tuple[int, float, int, int], ...]]:
        """Per vertex: (neighbour, step length, side cell 1, side cell 2); sides -1 for straight steps."""
        rows, cols = self.rows, self.cols
        table = []
        for index in range(rows * cols):
            row, col = divmod(index, cols)
            entries = []
            for dr in (-1, 0, 1):
                for dc in (-1, 0, 1):
                    if (dr or dc) and 0 <= row + dr < rows and 0 <= col + dc < cols:
                        other = index + dr * cols + dc
                        if dr and dc:
                            entries.append((other, DIAGONAL, index + dr * cols, index + dc))
                        else:
                            entries.append((other, STRAIGHT, -1, -1))
            table.append(tuple(entries))
        return table

    def cost(self, cell: Cell) -> float:
        return self._cost[self._index(cell, 'cell')]

    def _edge(self, step: int, target: int, side1: int, side2: int) -> int | float:
        """Cost (fixed-point) of moving into ``target``; a diagonal step also pays its two side cells."""
        cost = self._cost
        c = cost[target]
        if side1 >= 0:
            c = max(c, cost[side1], cost[side2])
        if c == FREE:
            return step
        return INF if c == INF else round(step * c)

    def _heuristic(self, a: int, b: int) -> int:
        ar, ac = divmod(a, self.cols)
        br, bc = divmod(b, self.cols)
        dr, dc = abs(ar - br), abs(ac - bc)
        if dr < dc:
            dr, dc = dc, dr
        return dr * STRAIGHT + dc * (DIAGONAL - STRAIGHT)

    # -- the algorithm ---------------------------------------------------------------------
    def calculate_key(self, s: int) -> tuple[int | float, int | float]:
        m = min(self.g[s], self.rhs[s])
        return (m + self._heuristic(self._start, s) + self.km, m)

    def update_vertex(self, u: int) -> None:
        if self.g[u] != self.rhs[u]:
            self.queue.push(u, self.calculate_key(u))
        else:
            self.queue.remove(u)

    def _best_successor_cost(self, u: int) -> int | float:
        """min over successors s' of c(u, s') + g(s'): the rhs value of ``u``."""
        g = self.g
        best = INF
        for other, step, side1, side2 in self._neighbours[u]:
            if g[other] == INF:
                continue
            value = self._edge(step, other, side1, side2) + g[other]
            if value < best:
                best = value
        return best

    def compute_shortest_path(self) -> None:
        """Expand vertices until the start is locally consistent and no key below it remains."""
        g, rhs, queue, start = self.g, self.rhs, self.queue, self._start
        neighbours, goal = self._neighbours, self._goal
        while True:
            top = queue.top()
            if top is None:
                break
            k_old, u = top
            if not (k_old < self.calculate_key(start) or rhs[start] > g[start]):
                break
            self.expansions += 1
            k_new = self.calculate_key(u)
            if k_old < k_new:
                queue.push(u, k_new)
            elif g[u] > rhs[u]:
                g[u] = rhs[u]
                queue.remove(u)
                # The graph is undirected in its neighbours; edge costs depend on the
                # target cell, so c(s, u) is the cost of entering u from s.
                for s, step, side1, side2 in neighbours[u]:
                    if s != goal:
                        value = self._edge(step, u, side1, side2) + g[u]
                        if value < rhs[s]:
                            rhs[s] = value
                    self.update_vertex(s)
            else:
                g[u] = INF
                for s in (u, *(entry[0] for entry in neighbours[u])):
                    if s != goal:
                        rhs[s] = self._best_successor_cost(s)
                    self.update_vertex(s)

    def set_start(self, cell: Cell) -> None:
        """The robot moved: keep the search, raise ``km`` by the heuristic distance moved."""
        index = self._index(cell, 'start')
        if index == self._start:
            return
        self._start = index
        self.km += self._heuristic(self._last, self._start)
        self._last = self._start

    def update_cells(self, changes: Iterable[tuple[Cell, float]]) -> int:
        """Apply new cell costs and repair the affected ``rhs`` values; return how many changed.

        A cell's cost enters every edge into it and every diagonal edge beside it;
        all of those start at the cell or one of its neighbours, so those are the
        vertices whose ``rhs`` is recomputed. Call :meth:`compute_shortest_path` next.
        """
        touched: set[int] = set()
        changed = 0
        for cell, cost in changes:
            index = self._index(cell, 'cell')
            cost = float(cost)
            if math.isnan(cost) or cost < FREE:
                raise PlanningError(f'cell {tuple(cell)}: cost must be >= 1 or inf, got {cost}')
            if self._cost[index] == cost:
                continue
            self._cost[index] = cost
            changed += 1
            touched.add(index)
            touched.update(entry[0] for entry in self._neighbours[index])
        for u in touched:
            if u != self._goal:
                self.rhs[u] = self._best_successor_cost(u)
            self.update_vertex(u)
        return changed

    # -- results ---------------------------------------------------------------------------
    def path_cost(self) -> float:
        """Cost of the best path from the start in cells (inf when the goal is unreachable)."""
        value = min(self.g[self._start], self.rhs[self._start])
        return INF if value == INF else value / SCALE

    def path(self) -> list[Cell]:
        """Cells from start to goal following the cheapest successors; [] when unreachable."""
        if self.path_cost() == INF:
            return []
        cells = [self._start]
        current = self._start
        visited = {current}
        while current != self._goal:
            best, best_value = -1, INF
            for other, step, side1, side2 in self._neighbours[current]:
                value = self._edge(step, other, side1, side2) + self.g[other]
                if value < best_value:
                    best, best_value = other, value
            if best < 0 or best in visited:
                # Only possible if compute_shortest_path() was not called after a change.
                raise PlanningError('path: the search is not up to date; call compute_shortest_path()')
            visited.add(best)
            cells.append(best)
            current = best
        return [self._cell(i) for i in cells]

    @property
    def start(self) -> Cell:
        return self._cell(self._start)

    @property
    def goal(self) -> Cell:
        return self._cell(self._goal)


def path_cost(costs, path: Sequence[Cell]) -> float:
    """The cost of following ``path`` on ``costs`` with the planner's edge costs (for checks)."""
    costs = np.asarray(costs, dtype=float)
    total = 0.0
    for (r0, c0), (r1, c1) in itertools.pairwise(path):
        dr, dc = r1 - r0, c1 - c0
        if max(abs(dr), abs(dc)) != 1:
            raise PlanningError(f'path: cells {(r0, c0)} and {(r1, c1)} are not neighbours')
        c = costs[r1, c1]
        if dr and dc:
            c = max(c, costs[r0 + dr, c0], costs[r0, c0 + dc])
            total += SQRT2 * c
        else:
            total += c
    return total
