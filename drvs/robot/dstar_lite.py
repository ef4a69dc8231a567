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

import array
import copy
import heapq
import itertools
import math
from collections.abc import Iterable, Sequence

import numpy as np
from numpy.typing import ArrayLike

FREE = 1.0
SQRT2 = math.sqrt(2.0)
INF = math.inf
SCALE = 1 << 20  # fixed-point units per cell of straight travel
STRAIGHT = SCALE
DIAGONAL = round(SQRT2 * SCALE)
_MOVES = tuple(
    (dr, dc, DIAGONAL if dr and dc else STRAIGHT) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc
)
EXACT = float(1 << 53)  # floating-point integers below this add exactly
BATCH_MIN_CELLS = 16
"""From this many changed cells near the search on, :meth:`DStarLite.update_cells` recomputes with numpy."""
BOX_CELLS_PER_CHANGE = 16
"""...as long as the box around the changes has at most this many cells per changed cell (+ 512)."""

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

    def __init__(self) -> None:
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

    def copy(self) -> _Queue:
        """An independent queue whose new entries order among themselves and the old ones as here."""
        twin = _Queue()
        twin._heap, twin._key = list(self._heap), dict(self._key)
        twin._tie = itertools.count(max((entry[2] for entry in self._heap), default=-1) + 1)
        return twin

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

    def __init__(self, costs: ArrayLike, start: Cell, goal: Cell):
        costs = np.asarray(costs, dtype=float)
        if costs.ndim != 2 or costs.size == 0:
            raise PlanningError(f'costs: expected a non-empty 2-D grid, got shape {costs.shape}')
        if np.isnan(costs).any() or (costs < FREE).any():
            raise PlanningError('costs: every cell cost must be >= 1 or inf')
        self.rows, self.cols = costs.shape
        # One float object per distinct cost: the search reads costs all over the grid, and a few
        # shared objects stay in the CPU's cache where one object per cell would not.
        self._costs_seen: dict[float, float] = {}
        self._cost: list[float] = [self._costs_seen.setdefault(v, v) for v in costs.ravel().tolist()]
        finite = costs[np.isfinite(costs)]
        self._integral = bool((finite == np.floor(finite)).all())  # integral costs so far
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

    def copy(self) -> DStarLite:
        """An independent planner in the same state (costs, start, g, rhs, queue, km).

        The neighbour table, which never changes, is shared. The copy plans exactly
        as this planner would: its queue breaks ties between equal keys in the same
        order. For trying a change without committing to it, and for benchmarks.
        """
        twin = copy.copy(self)
        twin._cost, twin._costs_seen = list(self._cost), dict(self._costs_seen)
        twin.g, twin.rhs = list(self.g), list(self.rhs)
        twin.queue = self.queue.copy()
        return twin

    # -- grid helpers ----------------------------------------------------------------------
    def _index(self, cell: Cell, what: str) -> int:
        row, col = int(cell[0]), int(cell[1])
        if not (0 <= row < self.rows and 0 <= col < self.cols):
            raise PlanningError(f'{what}: cell {tuple(cell)} is outside the {self.rows}x{self.cols} grid')
        return row * self.cols + col

    def _cell(self, index: int) -> Cell:
        return divmod(index, self.cols)

    def _neighbour_table(self) -> list[tuple[tuple[int, int, int, int], ...]]:
        """Per vertex: (neighbour, step length, side cell 1, side cell 2); sides -1 for straight steps."""
        rows, cols = self.rows, self.cols
        ints = list(range(rows * cols))  # one int object per index, shared by the entries
        table = []
        for index in ints:
            row, col = divmod(index, cols)
            entries = []
            for dr in (-1, 0, 1):
                for dc in (-1, 0, 1):
                    if (dr or dc) and 0 <= row + dr < rows and 0 <= col + dc < cols:
                        other = ints[index + dr * cols + dc]
                        if dr and dc:
                            entries.append((other, DIAGONAL, ints[index + dr * cols], ints[index + dc]))
                        else:
                            entries.append((other, STRAIGHT, -1, -1))
            table.append(tuple(entries))
        return table

    def cost(self, cell: Cell) -> float:
        return self._cost[self._index(cell, 'cell')]

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

    def _procedures(self):
        """(update_vertex, best_successor_cost) of the paper, as closures over this planner's lists.

        The search's inner loops call them for every neighbour of every expanded
        vertex: closures over local names, with the key, heuristic and edge cost
        written out, cost much less than methods calling methods (the repair of a
        small map change was mostly that overhead). ``update_vertex`` does not push
        a vertex already queued with the key it would get: its heap entry stands,
        so the queue's order is the same with fewer stale entries. Valid while the
        start and ``km`` stay as they are (make new ones after :meth:`set_start`).
        """
        g, rhs, cost, neighbours, cols, km = (
            self.g,
            self.rhs,
            self._cost,
            self._neighbours,
            self.cols,
            self.km,
        )
        keys, heap, tie, push = self.queue._key, self.queue._heap, self.queue._tie, heapq.heappush
        start_row, start_col = divmod(self._start, cols)
        diagonal_extra = DIAGONAL - STRAIGHT

        def update_vertex(u: int) -> None:
            gu, ru = g[u], rhs[u]
            if gu == ru:
                keys.pop(u, None)
                return
            m = gu if gu < ru else ru
            row, col = divmod(u, cols)
            dr, dc = abs(row - start_row), abs(col - start_col)
            h = dr * STRAIGHT + dc * diagonal_extra if dr >= dc else dc * STRAIGHT + dr * diagonal_extra
            k1 = m + h + km
            if keys.get(u) != (k1, m):
                keys[u] = (k1, m)
                push(heap, (k1, m, next(tie), u))

        def best_successor_cost(u: int) -> int | float:
            """min over successors s' of c(u, s') + g(s'): the rhs value of ``u``."""
            best = INF
            for other, step, side1, side2 in neighbours[u]:
                g_other = g[other]
                if g_other == INF:
                    continue
                c = cost[other]
                if side1 >= 0:
                    c = max(c, cost[side1], cost[side2])
                if c == FREE:
                    value = step + g_other
                elif c == INF:
                    continue
                else:
                    value = round(step * c) + g_other
                if value < best:
                    best = value
            return best

        return update_vertex, best_successor_cost

    def update_vertex(self, u: int) -> None:
        self._procedures()[0](u)

    def compute_shortest_path(self) -> None:
        """Expand vertices until the start is locally consistent and no key below it remains."""
        g, rhs, cost, start, km = self.g, self.rhs, self._cost, self._start, self.km
        neighbours, cols = self._neighbours, self.cols
        keys, heap, tie, push, pop = (
            self.queue._key,
            self.queue._heap,
            self.queue._tie,
            heapq.heappush,
            heapq.heappop,
        )
        update_vertex, best_successor_cost = self._procedures()
        start_row, start_col = divmod(start, cols)
        diagonal_extra = DIAGONAL - STRAIGHT
        expansions = 0
        while True:
            while heap:  # the queue's top: stale heap entries are dropped
                k1, k2, _, u = heap[0]
                if keys.get(u) == (k1, k2):
                    break
                pop(heap)
            else:
                break
            g_start, rhs_start = g[start], rhs[start]
            m = g_start if g_start < rhs_start else rhs_start
            if not ((k1, k2) < (m + km, m) or rhs_start > g_start):  # calculate_key(start): h = 0
                break
            expansions += 1
            gu, ru = g[u], rhs[u]
            m = gu if gu < ru else ru
            row, col = divmod(u, cols)
            dr, dc = abs(row - start_row), abs(col - start_col)
            h = dr * STRAIGHT + dc * diagonal_extra if dr >= dc else dc * STRAIGHT + dr * diagonal_extra
            k_new = (m + h + km, m)  # calculate_key(u)
            if (k1, k2) < k_new:
                keys[u] = k_new
                push(heap, (k_new[0], m, next(tie), u))
            elif gu > ru:
                g[u] = ru
                del keys[u]
                # The graph is undirected in its neighbours; edge costs depend on the
                # target cell, so c(s, u) is the cost of entering u from s.
                # rhs(s) = min(rhs(s), c(s, u) + g(u)): only possible when rhs(s) > step + g(u),
                # as every cost is at least 1 (and never for the goal, whose rhs is 0).
                cost_u = cost[u]
                for s, step, side1, side2 in neighbours[u]:
                    rs = rhs[s]
                    if rs <= step + ru:
                        continue
                    c = max(cost_u, cost[side1], cost[side2]) if side1 >= 0 else cost_u
                    if c == INF:
                        continue
                    value = (step if c == FREE else round(step * c)) + ru
                    if value >= rs:
                        continue  # rhs(s) stands, so does s's place in the queue
                    rhs[s] = value
                    gs = g[s]  # update_vertex(s), written out: this loop is the search's hottest
                    if gs == value:
                        if s in keys:
                            del keys[s]
                        continue
                    m = gs if gs < value else value
                    row, col = divmod(s, cols)
                    dr, dc = abs(row - start_row), abs(col - start_col)
                    h = (
                        dr * STRAIGHT + dc * diagonal_extra
                        if dr >= dc
                        else dc * STRAIGHT + dr * diagonal_extra
                    )
                    k1 = m + h + km
                    if keys.get(s) != (k1, m):
                        keys[s] = (k1, m)
                        push(heap, (k1, m, next(tie), s))
            else:
                # Figure 4 of the paper: of u's predecessors, only those whose rhs came through u
                # can change (an exact test: costs are integers); rhs(u) does not depend on g(u).
                # (Again rhs(s) >= step + g(u) is needed, and the goal's rhs is 0.)
                g[u] = INF
                update_vertex(u)
                cost_u = cost[u]
                for s, step, side1, side2 in neighbours[u]:
                    rs = rhs[s]
                    if rs < step + gu:
                        continue
                    c = max(cost_u, cost[side1], cost[side2]) if side1 >= 0 else cost_u
                    if c == INF or rs != (step if c == FREE else round(step * c)) + gu:
                        continue
                    value = best_successor_cost(s)
                    if value == rs:
                        continue  # another successor offers the same: s stands
                    rhs[s] = value
                    gs = g[s]  # update_vertex(s), written out
                    if gs == value:
                        if s in keys:
                            del keys[s]
                        continue
                    m = gs if gs < value else value
                    row, col = divmod(s, cols)
                    dr, dc = abs(row - start_row), abs(col - start_col)
                    h = (
                        dr * STRAIGHT + dc * diagonal_extra
                        if dr >= dc
                        else dc * STRAIGHT + dr * diagonal_extra
                    )
                    k1 = m + h + km
                    if keys.get(s) != (k1, m):
                        keys[s] = (k1, m)
                        push(heap, (k1, m, next(tie), s))
        self.expansions += expansions

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
        vertices whose ``rhs`` is recomputed (``g`` does not change here), and
        those whose ``rhs`` changed go through ``update_vertex``. An edge counts in
        its source's ``rhs`` only through ``g`` of its target, and the edges a
        cell's cost enters end at the cell or at one of its four straight
        neighbours: a change where all of those have ``g = inf`` (far from the
        search so far) needs nothing more than the new cost. Call
        :meth:`compute_shortest_path` next. A bad change raises
        :class:`PlanningError`; the changes before it are applied.
        """
        count = 0
        relevant: list[int] = []  # changed cells near the search
        own, seen, g, rows, cols = self._cost, self._costs_seen, self.g, self.rows, self.cols
        last_row, last_col = rows - 1, cols - 1
        try:
            for cell, cost in changes:
                row, col = int(cell[0]), int(cell[1])
                if not (0 <= row < rows and 0 <= col < cols):
                    self._index(cell, 'cell')  # raises, naming the cell
                index = row * cols + col
                cost = float(cost)
                if not cost >= FREE:  # NaN too
                    raise PlanningError(f'cell {tuple(cell)}: cost must be >= 1 or inf, got {cost}')
                if own[index] == cost:
                    continue
                if cost in seen:
                    cost = seen[cost]
                else:
                    if len(seen) < 256:
                        seen[cost] = cost
                    if cost != INF and not cost.is_integer():
                        self._integral = False
                own[index] = cost
                count += 1
                if (
                    g[index] != INF
                    or (row and g[index - cols] != INF)
                    or (row < last_row and g[index + cols] != INF)
                    or (col and g[index - 1] != INF)
                    or (col < last_col and g[index + 1] != INF)
                ):
                    relevant.append(index)
        finally:
            if relevant and (len(relevant) < BATCH_MIN_CELLS or not self._update_box(relevant)):
                self._update_each(relevant)
        return count

    def _update_each(self, indices: list[int]) -> None:
        """:meth:`update_cells`' repair, one vertex at a time (few or scattered changes)."""
        neighbours = self._neighbours
        touched = set(indices)
        for index in indices:
            touched.update([entry[0] for entry in neighbours[index]])
        touched.discard(self._goal)  # rhs(goal) stays 0
        update_vertex, best_successor_cost = self._procedures()
        rhs = self.rhs
        for u in touched:
            value = best_successor_cost(u)
            if value != rhs[u]:
                rhs[u] = value
                update_vertex(u)

    def _window(self, values: list, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """Rows ``r0:r1`` and columns ``c0:c1`` of a per-vertex list as a float array, inf off the grid.

        Lists become arrays fastest through array.array; integers above 2**53 lose
        precision here (:meth:`_update_box` checks for them).
        """
        cols = self.cols
        top, bottom, left, right = max(r0, 0), min(r1, self.rows), max(c0, 0), min(c1, cols)
        flat: list = []
        for row in range(top * cols, bottom * cols, cols):
            flat += values[row + left : row + right]
        window = np.frombuffer(array.array('d', flat)).reshape(bottom - top, right - left)
        if (top, bottom, left, right) == (r0, r1, c0, c1):
            return window
        full = np.full((r1 - r0, c1 - c0), INF)  # at the grid's edge
        full[top - r0 : bottom - r0, left - c0 : right - c0] = window
        return full

    def _update_box(self, indices: list[int]) -> bool:
        """:meth:`update_cells`' repair with numpy over the box around the changed cells ``indices``.

        A map change is usually one compact blob (an obstacle moved), whose few
        hundred vertices cost a microsecond or two each in Python. Here the ``rhs``
        of every vertex of the box is computed at once, as ``best_successor_cost``
        does it, with the same ``round(step * c)`` (numpy's ``rint`` also rounds half
        to even), in floating point: exact while every value is an integer below
        2**53. Returns False, having changed nothing, when the box is much larger
        than the change (scattered cells) or a value is too large to be exact; the
        caller then goes vertex by vertex.
        """
        cols = self.cols
        r, c = np.divmod(np.array(indices), cols)
        r0, c0 = int(r.min()) - 2, int(c.min()) - 2  # the box: the changed cells, their
        r1, c1 = int(r.max()) + 3, int(c.max()) + 3  # neighbours and theirs; r1, c1 exclusive
        height, width = r1 - r0, c1 - c0
        if height * width > BOX_CELLS_PER_CHANGE * len(indices) + 512:
            return False
        C = self._window(self._cost, r0, r1, c0, c1)  # inf off the grid: no edge leaves it
        G = self._window(self.g, r0, r1, c0, c1)

        def at(array, dr, dc):  # array[row + dr, col + dc] for the vertices (row, col) of the inner box
            return array[1 + dr : height - 1 + dr, 1 + dc : width - 1 + dc]

        # best_successor_cost for every vertex at once. Straight steps: c(u, v) = cost(v).
        integral = self._integral  # integral costs times integral steps need no rounding
        value = C * STRAIGHT
        if not integral:
            np.rint(value, out=value)
        value += G
        best = at(value, -1, 0).copy()
        for dr, dc in ((1, 0), (0, -1), (0, 1)):
            np.minimum(best, at(value, dr, dc), out=best)
        # Diagonals: the dearest of the target and the two side cells. pair[i, j] is
        # max(cost[i, j], cost[i, j + 1]): the target and the side in its row are one pair.
        pair = np.maximum(C[:, :-1], C[:, 1:])
        for dr, dc in ((-1, -1), (-1, 1), (1, -1), (1, 1)):
            value = (
                pair[1 + dr : height - 1 + dr, 0 : width - 2]
                if dc < 0
                else pair[1 + dr : height - 1 + dr, 1 : width - 1]
            )
            value = np.maximum(value, at(C, 0, dc))
            value *= DIAGONAL
            if not integral:
                np.rint(value, out=value)
            value += at(G, dr, dc)
            np.minimum(best, value, out=best)
        old = self._window(self.rhs, r0 + 1, r1 - 1, c0 + 1, c1 - 1)
        both = np.concatenate((best, old))
        if ((both >= EXACT) & (both < INF)).any():
            return False
        # The vertices to update: the changed cells and their neighbours (a 3x3 dilation), on the
        # grid, but not the goal (its rhs stays 0)...
        changed = np.zeros((height, width), dtype=bool)
        changed[r - r0, c - c0] = True
        across = changed[:, :-2] | changed[:, 1:-1] | changed[:, 2:]
        touched = across[:-2] | across[1:-1] | across[2:]
        if r0 < -1 or c0 < -1 or r1 > self.rows + 1 or c1 > cols + 1:  # not off the grid
            touched[: max(0, -1 - r0)] = False  # inner row i is grid row r0 + 1 + i
            touched[self.rows - 1 - r0 :] = False
            touched[:, : max(0, -1 - c0)] = False
            touched[:, cols - 1 - c0 :] = False
        goal_row, goal_col = divmod(self._goal, cols)
        if r0 < goal_row < r1 - 1 and c0 < goal_col < c1 - 1:
            touched[goal_row - r0 - 1, goal_col - c0 - 1] = False
        # ... whose rhs changed: the others keep their place in the queue (or out of it).
        select = touched & (best != old)
        ys, xs = np.nonzero(select)
        vertices = ((ys + (r0 + 1)) * cols + (xs + (c0 + 1))).tolist()
        rhs = self.rhs
        update_vertex = self._procedures()[0]
        for u, value in zip(vertices, best[select].tolist(), strict=True):
            rhs[u] = INF if value == INF else int(value)
            update_vertex(u)
        return True

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
        g, cost, neighbours = self.g, self._cost, self._neighbours
        while current != self._goal:
            best, best_value = -1, INF
            for other, step, side1, side2 in neighbours[current]:  # c(current, other) + g(other)
                g_other = g[other]
                if g_other == INF:
                    continue
                c = max(cost[other], cost[side1], cost[side2]) if side1 >= 0 else cost[other]
                if c == INF:
                    continue
                value = (step if c == FREE else round(step * c)) + g_other
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


def path_cost(costs: ArrayLike, path: Sequence[Cell]) -> float:
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
