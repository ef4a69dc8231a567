"""D* Lite against plain Dijkstra on seeded random grids, incremental repair, edge cases."""

import heapq
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import drvs.robot.dstar_lite as dstar_lite
from drvs.robot.dstar_lite import INF, SCALE, SQRT2, DStarLite, PlanningError, octile, path_cost


def dijkstra(costs: np.ndarray, start, goal) -> float:
    """Reference: textbook Dijkstra with the planner's edge rule, written independently."""
    rows, cols = costs.shape
    dist = {start: 0.0}
    heap = [(0.0, start)]
    done = set()
    while heap:
        d, (r, c) = heapq.heappop(heap)
        if (r, c) in done:
            continue
        done.add((r, c))
        if (r, c) == goal:
            return d
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                nr, nc = r + dr, c + dc
                if (dr, dc) == (0, 0) or not (0 <= nr < rows and 0 <= nc < cols):
                    continue
                if dr and dc:
                    step = SQRT2 * max(costs[nr, nc], costs[r + dr, c], costs[r, c + dc])
                else:
                    step = costs[nr, nc]
                if step == INF:
                    continue
                if d + step < dist.get((nr, nc), INF):
                    dist[(nr, nc)] = d + step
                    heapq.heappush(heap, (d + step, (nr, nc)))
    return INF


def random_grid(rng, rows, cols, density, expensive=0.0):
    costs = np.ones((rows, cols))
    costs[rng.random((rows, cols)) < density] = INF
    if expensive:
        costs[rng.random((rows, cols)) < expensive] = 5.0
    return costs


def random_free_cell(rng, costs):
    free = np.argwhere(costs < INF)
    return tuple(int(v) for v in free[rng.integers(len(free))])


def plan(costs, start, goal):
    planner = DStarLite(costs, start, goal)
    planner.compute_shortest_path()
    return planner


@pytest.mark.parametrize('seed', range(12))
def test_same_cost_as_dijkstra_on_random_grids(seed):
    rng = np.random.default_rng(seed)
    costs = random_grid(rng, 25, 30, density=0.3, expensive=0.1 if seed % 2 else 0.0)
    start, goal = random_free_cell(rng, costs), random_free_cell(rng, costs)
    planner = plan(costs, start, goal)
    expected = dijkstra(costs, start, goal)
    assert planner.path_cost() == pytest.approx(expected)
    path = planner.path()
    if expected == INF:
        assert path == []
    else:
        assert path[0] == start and path[-1] == goal
        assert path_cost(costs, path) == pytest.approx(expected)


@pytest.mark.parametrize('seed', range(6))
def test_the_benchmarks_a_star_agrees_exactly(seed):
    """bench/planner.py compares D* Lite's repair with its A*: same moves, same fixed-point costs."""
    from bench.planner import astar, astar_path

    rng = np.random.default_rng(200 + seed)
    costs = random_grid(rng, 25, 30, density=0.25, expensive=0.1)
    costs[rng.random(costs.shape) < 0.05] = 1e6  # the inflated margin's cost
    start, goal = random_free_cell(rng, costs), random_free_cell(rng, costs)
    planner = plan(costs, start, goal)
    cols = costs.shape[1]
    cost, parent, _ = astar(
        costs.ravel().tolist(), *costs.shape, start[0] * cols + start[1], goal[0] * cols + goal[1]
    )
    assert cost / SCALE == planner.path_cost()
    if cost != INF:
        path = [
            divmod(i, cols) for i in astar_path(parent, start[0] * cols + start[1], goal[0] * cols + goal[1])
        ]
        assert path[0] == start and path[-1] == goal
        assert path_cost(costs, path) == pytest.approx(planner.path_cost())


@pytest.mark.parametrize('seed', range(10))
def test_incremental_repair_after_random_changes_equals_a_fresh_plan(seed):
    rng = np.random.default_rng(100 + seed)
    costs = random_grid(rng, 30, 30, density=0.2)
    start, goal = random_free_cell(rng, costs), random_free_cell(rng, costs)
    planner = plan(costs, start, goal)
    for _ in range(6):
        # the robot moves a few cells along its path, then the world changes
        path = planner.path()
        if len(path) > 3:
            start = path[3]
            planner.set_start(start)
        changes = []
        for _ in range(int(rng.integers(1, 40))):
            cell = (int(rng.integers(30)), int(rng.integers(30)))
            if cell not in (start, goal):
                value = INF if rng.random() < 0.5 else float(rng.choice([1.0, 3.0]))
                costs[cell] = value
                changes.append((cell, value))
        planner.update_cells(changes)
        planner.compute_shortest_path()
        fresh = plan(costs, start, goal)
        assert planner.path_cost() == pytest.approx(fresh.path_cost())
        assert planner.path_cost() == pytest.approx(dijkstra(costs, start, goal))
        if planner.path_cost() < INF:
            assert path_cost(costs, planner.path()) == pytest.approx(fresh.path_cost())


def block_ahead(planner, costs, steps_moved, steps_ahead):
    """Move the robot along its path, then drop a 5x3 block on the path a few cells ahead of it."""
    path = planner.path()
    start, ahead = path[steps_moved], path[steps_moved + steps_ahead]
    planner.set_start(start)
    changes = []
    for dr in range(-2, 3):
        for dc in range(-1, 2):
            cell = (ahead[0] + dr, ahead[1] + dc)
            if 0 <= cell[0] < costs.shape[0] and 0 <= cell[1] < costs.shape[1] and cell != start:
                costs[cell] = INF
                changes.append((cell, INF))
    return start, changes


@pytest.mark.parametrize('seed', range(4))
def test_repair_near_the_robot_is_exact_and_cheaper_than_a_fresh_search(seed):
    """The case where float keys once stopped the search early (seed 1): equal keys must tie-break."""
    rng = np.random.default_rng(seed)
    costs = random_grid(rng, 80, 80, density=0.25)
    goal = (40, 79)
    costs[40, 0] = costs[goal] = 1.0
    planner = plan(costs, (40, 0), goal)
    if planner.path_cost() == INF:
        pytest.skip('no path in this random grid')
    start, changes = block_ahead(planner, costs, len(planner.path()) // 3, 4)
    before = planner.expansions
    planner.update_cells(changes)
    planner.compute_shortest_path()
    fresh = plan(costs, start, goal)
    assert planner.path_cost() == pytest.approx(dijkstra(costs, start, goal))
    assert planner.path_cost() == pytest.approx(fresh.path_cost())
    assert planner.expansions - before < fresh.expansions


def test_diagonal_steps_cost_sqrt2_and_never_cut_corners():
    costs = np.ones((3, 3))
    assert plan(costs, (0, 0), (2, 2)).path_cost() == pytest.approx(2 * SQRT2)
    costs[0, 1] = INF  # blocks the corner beside the diagonal (0,0) -> (1,1)
    planner = plan(costs, (0, 0), (1, 1))
    assert planner.path() == [(0, 0), (1, 0), (1, 1)]
    assert planner.path_cost() == pytest.approx(2.0)


def test_two_cells_touching_at_a_corner_are_a_wall():
    costs = np.ones((2, 2))
    costs[0, 1] = costs[1, 0] = INF
    planner = plan(costs, (0, 0), (1, 1))
    assert planner.path_cost() == INF
    assert planner.path() == []


@pytest.mark.parametrize(
    'wall, door',
    [
        ([(r, 5) for r in range(10)], (7, 5)),  # a straight wall
        ([(r, r) for r in range(10)], (3, 3)),  # a diagonal line of cells: no corner to cut
    ],
    ids=['straight', 'diagonal'],
)
def test_unreachable_goal_gives_no_path_until_a_door_opens(wall, door):
    costs = np.ones((10, 10))
    for cell in wall:
        costs[cell] = INF
    planner = plan(costs, (9, 0), (0, 9))
    assert planner.path_cost() == INF
    assert planner.path() == []
    costs[door] = 1.0
    planner.update_cells([(door, 1.0)])
    planner.compute_shortest_path()
    assert planner.path_cost() == pytest.approx(dijkstra(costs, (9, 0), (0, 9)))
    assert planner.path_cost() < INF


def test_goal_on_an_impassable_cell_is_unreachable():
    costs = np.ones((5, 5))
    costs[4, 4] = INF
    assert plan(costs, (0, 0), (4, 4)).path() == []


def test_start_on_an_expensive_or_blocked_cell_leaves_by_the_cheapest_way():
    costs = np.ones((7, 7))
    costs[2:5, 2:5] = 1000.0  # the start sits in the middle of a costly patch
    costs[3, 3] = INF  # even its own cell is impassable
    costs[3, 4] = 1.0  # a cheap exit to the east
    planner = plan(costs, (3, 3), (3, 6))
    assert planner.path() == [(3, 3), (3, 4), (3, 5), (3, 6)]
    assert planner.path_cost() == pytest.approx(3.0)


def test_moving_start_uses_km_and_keeps_the_search():
    costs = np.ones((20, 20))
    planner = plan(costs, (0, 0), (19, 19))
    planner.set_start((5, 5))
    assert planner.km / SCALE == pytest.approx(octile((0, 0), (5, 5)))
    planner.compute_shortest_path()
    assert planner.path_cost() == pytest.approx(14 * SQRT2)
    assert planner.path()[0] == (5, 5)


@pytest.mark.parametrize(
    'kwargs, message',
    [
        ({'costs': [[1, 1]], 'start': (0, 0), 'goal': (1, 0)}, 'goal: cell (1, 0) is outside the 1x2 grid'),
        (
            {'costs': [[1, 1]], 'start': (0, -1), 'goal': (0, 0)},
            'start: cell (0, -1) is outside the 1x2 grid',
        ),
        (
            {'costs': [[1, 0.5]], 'start': (0, 0), 'goal': (0, 1)},
            'costs: every cell cost must be >= 1 or inf',
        ),
        (
            {'costs': [1, 1], 'start': (0, 0), 'goal': (0, 1)},
            'costs: expected a non-empty 2-D grid, got shape (2,)',
        ),
    ],
)
def test_bad_input_is_refused(kwargs, message):
    with pytest.raises(PlanningError) as error:
        DStarLite(**kwargs)
    assert str(error.value) == message


def test_bad_cell_update_is_refused():
    planner = plan(np.ones((3, 3)), (0, 0), (2, 2))
    with pytest.raises(PlanningError) as error:
        planner.update_cells([((1, 1), 0.0)])
    assert str(error.value) == 'cell (1, 1): cost must be >= 1 or inf, got 0.0'


def test_octile_distance():
    assert octile((0, 0), (3, 5)) == pytest.approx(2 + 3 * math.sqrt(2))


# -- update_cells: the numpy repair of a blob of changes against the per-vertex one ---------------
PALETTES = (
    (1.0, 1.0, 1.0, 3.0, 1e6, INF),  # integral costs: no rounding needed
    (1.0, 1.0, 1.0, 1.5, 2.25, 3.0, 1e6, INF),  # non-integral ones exercise the rounding
)


def exact_distances(costs: np.ndarray, goal) -> list[int | float]:
    """Fixed-point cost of the best path from every cell to ``goal`` (Dijkstra backwards, integers)."""
    rows, cols = costs.shape
    flat = costs.ravel().tolist()
    dist: list[int | float] = [INF] * (rows * cols)
    start = goal[0] * cols + goal[1]
    dist[start] = 0
    heap = [(0, start)]
    while heap:
        d, v = heapq.heappop(heap)
        if d > dist[v]:
            continue
        row, col = divmod(v, cols)
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                if not (dr or dc) or not (0 <= row + dr < rows and 0 <= col + dc < cols):
                    continue
                u = v + dr * cols + dc  # the edge u -> v enters v; a diagonal pays its two sides
                c = max(flat[v], flat[u - dr * cols], flat[u - dc]) if dr and dc else flat[v]
                if c == INF:
                    continue
                step = dstar_lite.DIAGONAL if dr and dc else dstar_lite.STRAIGHT
                value = d + (step if c == 1.0 else round(step * c))
                if value < dist[u]:
                    dist[u] = value
                    heapq.heappush(heap, (value, u))
    return dist


@st.composite
def change_runs(draw):
    """A grid, start and goal, then a few rounds of (new start, changes): a blob (a rectangle of new
    costs, often large enough for the numpy repair, clipped by the grid's edge) plus scattered cells."""
    rows, cols = draw(st.integers(3, 22)), draw(st.integers(3, 22))
    cell = st.tuples(st.integers(0, rows - 1), st.integers(0, cols - 1))
    cost = st.sampled_from(draw(st.sampled_from(PALETTES)))
    costs = np.array(draw(st.lists(cost, min_size=rows * cols, max_size=rows * cols)))
    rounds = []
    for _ in range(draw(st.integers(1, 4))):
        top, left = draw(cell)
        height, width = draw(st.integers(1, 8)), draw(st.integers(1, 8))
        fill = draw(st.lists(cost, min_size=height * width, max_size=height * width))
        changes = [
            ((r, c), fill[(r - top) * width + (c - left)])
            for r in range(top, min(top + height, rows))
            for c in range(left, min(left + width, cols))
        ]
        changes += draw(st.lists(st.tuples(cell, cost), max_size=6))
        rounds.append((draw(cell), changes))
    return costs.reshape(rows, cols), draw(cell), draw(cell), rounds


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(change_runs())
def test_update_cells_in_bulk_matches_vertex_by_vertex_and_a_fresh_plan(run):
    """update_cells repairs a blob of changes with numpy (_update_box); the state must be exactly
    the per-vertex repair's (same g, rhs, queue), rhs must be the one-step lookahead of g on the new
    costs everywhere, and after the search the cost, the path and g along it must be a fresh plan's."""
    costs, start, goal, rounds = run
    costs = costs.copy()
    bulk, single = DStarLite(costs, start, goal), DStarLite(costs, start, goal)
    for planner in (bulk, single):
        planner.compute_shortest_path()
    for start, changes in rounds:
        for cell, value in changes:
            costs[cell] = value
        bulk.set_start(start)
        bulk.update_cells(changes)
        single.set_start(start)
        limit = dstar_lite.BATCH_MIN_CELLS
        dstar_lite.BATCH_MIN_CELLS = 10**9  # this planner repairs vertex by vertex
        try:
            single.update_cells(changes)
        finally:
            dstar_lite.BATCH_MIN_CELLS = limit
        assert bulk.g == single.g and bulk.rhs == single.rhs
        assert bulk.queue._key == single.queue._key
        lookahead = DStarLite(costs, start, goal)._procedures  # fresh costs, and this g
        lookahead.__self__.g = bulk.g
        best_successor_cost = lookahead()[1]
        goal_index = goal[0] * costs.shape[1] + goal[1]
        for u in range(costs.size):
            assert bulk.rhs[u] == (0 if u == goal_index else best_successor_cost(u)), u
            assert (u in bulk.queue) == (bulk.g[u] != bulk.rhs[u]), u
        for planner in (bulk, single):
            planner.compute_shortest_path()
        assert bulk.g == single.g and bulk.rhs == single.rhs and bulk.path() == single.path()
        fresh = plan(costs, start, goal)
        distance = exact_distances(costs, goal)
        cols = costs.shape[1]
        assert bulk.path_cost() == fresh.path_cost()
        assert bulk.path_cost() == (
            INF
            if distance[start[0] * cols + start[1]] == INF
            else distance[start[0] * cols + start[1]] / SCALE
        )
        path = bulk.path()
        assert path == fresh.path()
        for r, c in path[1:]:  # the start's own g may be left behind its rhs (Figure 4: rhs > g stops)
            assert bulk.g[r * cols + c] == distance[r * cols + c] == fresh.g[r * cols + c]


def test_a_change_the_search_has_not_reached_needs_nothing_but_the_new_cost():
    """Start and goal close together in one corner of a large open grid: the search never reaches
    the far corner, so a blob of changes there leaves g, rhs and the queue as they were."""
    costs = np.ones((60, 60))
    planner = plan(costs, (2, 2), (2, 8))
    far = [((r, c), INF) for r in range(50, 58) for c in range(50, 58)]
    assert all(planner.g[r * 60 + c] == INF for (r, c), _ in far)  # the premise
    g, rhs, keys = list(planner.g), list(planner.rhs), dict(planner.queue._key)
    assert planner.update_cells(far) == len(far)
    assert (planner.g, planner.rhs, planner.queue._key) == (g, rhs, keys)
    assert planner.cost((53, 53)) == INF
    # ... and a wall across the way does: the repaired plan is a fresh plan's
    for r in range(0, 6):
        costs[r, 5] = INF
    planner.update_cells([((r, 5), INF) for r in range(0, 6)])
    planner.compute_shortest_path()
    costs[50:58, 50:58] = INF
    assert (
        planner.path_cost()
        == plan(costs, (2, 2), (2, 8)).path_cost()
        == pytest.approx(dijkstra(costs, (2, 2), (2, 8)))
    )


@pytest.mark.parametrize('seed', range(3))
def test_a_copy_plans_exactly_as_the_original_and_apart_from_it(seed):
    rng = np.random.default_rng(300 + seed)
    costs = random_grid(rng, 40, 40, density=0.2, expensive=0.1)
    start, goal = random_free_cell(rng, costs), random_free_cell(rng, costs)
    planner = plan(costs, start, goal)
    twin = planner.copy()
    changes = [((int(rng.integers(40)), int(rng.integers(40))), INF) for _ in range(30)]
    changes = [(cell, value) for cell, value in changes if cell not in (start, goal)]
    for p in (planner, twin):
        p.update_cells(changes)
        p.compute_shortest_path()
    assert (twin.g, twin.rhs, twin.queue._key, twin.expansions) == (
        planner.g,
        planner.rhs,
        planner.queue._key,
        planner.expansions,
    )
    assert twin.path() == planner.path()
    twin.update_cells([(goal, INF)])  # the original does not see the copy's changes
    assert planner.cost(goal) != INF and twin.cost(goal) == INF
