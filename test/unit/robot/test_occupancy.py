"""Occupancy grid: rasterising outlines, inflation, changed-cell diffs, TTL memory, margin crossing."""

import doctest

import numpy as np
import pytest
from shapely.geometry import Point, box

from drvs.robot import occupancy
from drvs.robot.dstar_lite import FREE, DStarLite
from drvs.robot.occupancy import (
    CAUTION,
    INFLATED,
    LETHAL,
    CostGrid,
    GridSpec,
    MapPublishing,
    ObstacleMemory,
    OccupancyError,
    crosses_margin,
)

SPEC = GridSpec((2.0, 1.0), 0.05)  # 40 columns x 20 rows


def test_grid_layout_follows_occupancy_grid_conventions():
    assert (SPEC.rows, SPEC.cols) == (20, 40)
    assert SPEC.cell_of((0.0, 0.0)) == (0, 0)
    assert SPEC.cell_of((0.07, 0.52)) == (10, 1)
    assert SPEC.cell_of((5.0, -1.0)) == (0, 39)  # clamped to the floor
    assert SPEC.centre_of((10, 1)) == pytest.approx((0.075, 0.525))
    assert GridSpec((7.0, 5.5), 0.05).rows == 110  # no float rounding up to an extra row


def test_outline_cells_are_lethal_and_the_margin_is_inflated_by_the_radius():
    grid = CostGrid(SPEC, robot_radius=0.2)
    grid.apply([box(0.9, 0.4, 1.1, 0.6)])
    centre = SPEC.cell_of((1.0, 0.5))
    assert grid.costs[centre] == LETHAL
    assert grid.costs[SPEC.cell_of((1.0 + 0.1 + 0.15, 0.5))] == INFLATED  # 0.15 m from the edge
    assert grid.costs[SPEC.cell_of((1.0 + 0.1 + 0.27, 0.5))] == FREE  # 0.27 m from the edge
    # every marked cell is within the radius of the box, give or take the cell the edge crosses
    half_cell_diagonal = 0.05 * 2**0.5 / 2
    for cell in np.argwhere(grid.costs > FREE):
        distance = box(0.9, 0.4, 1.1, 0.6).distance(Point(SPEC.centre_of(tuple(cell))))
        assert distance <= 0.2 + half_cell_diagonal
    occupancy = grid.occupancy()
    assert occupancy[centre] == 100
    assert set(np.unique(occupancy)) == {0, 99, 100}


def test_cells_a_little_beyond_the_margin_cost_more_and_plans_may_still_cross_them():
    grid = CostGrid(SPEC, robot_radius=0.2, caution=0.1)
    grid.apply([box(0.9, 0.4, 1.1, 0.6)])
    assert grid.costs[SPEC.cell_of((1.0 + 0.1 + 0.27, 0.5))] == CAUTION  # 0.27 m from the edge
    assert grid.costs[SPEC.cell_of((1.0 + 0.1 + 0.37, 0.5))] == FREE
    assert grid.occupancy()[SPEC.cell_of((1.0 + 0.1 + 0.27, 0.5))] == 0
    row, col = SPEC.cell_of((1.0, 0.5))[0], 35
    through = [(row, col), SPEC.cell_of((1.375, 0.5)), (row, col)]
    assert grid.costs[through[1]] == CAUTION and grid.costs[(row, col)] == FREE
    assert not crosses_margin(through, grid.costs)  # a plan may pass there
    assert crosses_margin([(row, col), SPEC.cell_of((1.25, 0.5)), (row, col)], grid.costs)


def test_a_sliver_thinner_than_a_cell_still_blocks():
    grid = CostGrid(SPEC, robot_radius=0.0)
    grid.apply([box(1.0, 0.0, 1.01, 1.0)])  # a 1 cm wall across the floor
    planner = DStarLite(grid.costs, SPEC.cell_of((0.2, 0.5)), SPEC.cell_of((1.8, 0.5)))
    planner.compute_shortest_path()
    assert planner.path() == []


def test_apply_reports_exactly_the_changed_cells():
    grid = CostGrid(SPEC, robot_radius=0.1)
    first = grid.apply([box(0.5, 0.4, 0.7, 0.6)])
    before = grid.costs.copy()
    changes = grid.apply([box(0.6, 0.4, 0.8, 0.6)])  # the obstacle moved 10 cm
    changed = {cell for cell, _ in changes}
    assert first and changes
    assert changed == {tuple(c) for c in np.argwhere(before != grid.costs)}
    assert all(grid.costs[cell] == cost for cell, cost in changes)
    assert grid.apply([box(0.6, 0.4, 0.8, 0.6)]) == []


def test_a_moved_obstacle_leaves_no_ghost():
    grid = CostGrid(SPEC, robot_radius=0.1)
    grid.apply([box(0.5, 0.4, 0.7, 0.6)])
    grid.apply([box(1.5, 0.4, 1.7, 0.6)])
    assert grid.costs[SPEC.cell_of((0.6, 0.5))] == FREE
    assert grid.costs[SPEC.cell_of((1.6, 0.5))] == LETHAL


def test_obstacle_memory_forgets_a_source_after_its_ttl():
    memory = ObstacleMemory(ttl=1.0)
    memory.observe(('obstacle', '/vs1'), [box(0, 0, 1, 1)], now=10.0)
    memory.observe(('human', '/vs2'), [box(2, 2, 3, 3)], now=10.5)
    assert set(memory.current(10.9)) == {('obstacle', '/vs1'), ('human', '/vs2')}
    assert set(memory.current(11.2)) == {('human', '/vs2')}  # vs1 silent for 1.2 s
    memory.observe(('human', '/vs2'), [], now=11.3)  # an answer with nothing replaces the outlines
    assert memory.current(11.4) == {('human', '/vs2'): []}


def test_a_report_of_nothing_may_let_the_outlines_linger_but_never_beyond_their_ttl():
    memory = ObstacleMemory(ttl=10.0)
    human = [box(2, 2, 3, 3)]
    memory.observe(('human', '/vs2'), human, now=10.0)
    memory.observe(('human', '/vs2'), [], now=11.0, linger=1.5)  # gone: kept 1.5 s more
    assert memory.current(12.4) == {('human', '/vs2'): human}
    assert memory.current(12.6) == {}
    memory.observe(('human', '/vs2'), human, now=20.0)
    memory.observe(('human', '/vs2'), [], now=29.5, linger=1.5)  # the ttl ends first
    assert memory.current(29.9) == {('human', '/vs2'): human}
    assert memory.current(30.1) == {}
    memory.observe(('human', '/vs2'), [], now=31.0, linger=1.5)  # nothing to keep: nothing, heard
    assert memory.current(31.1) == {('human', '/vs2'): []}


def test_a_report_about_a_region_keeps_what_the_source_saw_before_outside_it():
    memory = ObstacleMemory(ttl=10.0)
    west, east = box(1, 1, 2, 2), box(5, 1, 6, 2)
    memory.observe(('obstacle', '/vs1'), [west, east], now=10.0)
    # Asked about the west only: the east box is still there; a box across the edge keeps its east part.
    memory.observe(('obstacle', '/vs1'), [], now=11.0, region=(0, 0, 4, 3))
    ((source, (kept,)),) = memory.current(11.0).items()
    assert source == ('obstacle', '/vs1') and kept.equals(east)
    memory.observe(('obstacle', '/vs1'), [box(3, 1, 5, 2)], now=12.0, region=(0, 0, 6, 3))
    memory.observe(('obstacle', '/vs1'), [box(3, 1, 4, 2)], now=13.0, region=(0, 0, 4, 3))
    (kept,) = memory.current(13.0).values()
    assert kept[0] == box(3, 1, 4, 2) and kept[1].equals(box(4, 1, 5, 2))


@pytest.mark.parametrize(
    'costs_row, expected',
    [
        ([INFLATED, INFLATED, FREE, FREE, FREE], False),  # leaves the margin it starts in
        ([FREE, FREE, FREE, INFLATED, INFLATED], False),  # the goal stands in a margin
        ([FREE, FREE, INFLATED, FREE, FREE], True),  # squeezes through a gap
        ([INFLATED, INFLATED, INFLATED, INFLATED, INFLATED], False),  # never leaves the margin
    ],
)
def test_crosses_margin(costs_row, expected):
    costs = np.array([costs_row])
    path = [(0, c) for c in range(5)]
    assert crosses_margin(path, costs) is expected


@pytest.mark.parametrize(
    'make, message',
    [
        (lambda: GridSpec((1.0, 1.0), 0.0), 'resolution: expected a positive number of metres, got 0.0'),
        (lambda: GridSpec((1.0, -2.0), 0.05), 'size: expected 2 positive numbers of metres, got (1.0, -2.0)'),
        (lambda: CostGrid(SPEC, -0.1), 'robot_radius: expected a number of metres >= 0, got -0.1'),
        (lambda: ObstacleMemory(0), 'obstacle_ttl: expected a positive number of seconds, got 0'),
    ],
)
def test_bad_settings_are_refused(make, message):
    with pytest.raises(OccupancyError) as error:
        make()
    assert str(error.value) == message


def test_map_publishing_coalesces_changes_within_a_period_and_refreshes():
    publishing = MapPublishing(period=1.0, refresh=5.0)
    assert publishing.due(0.0, changed=True)  # the first change goes out at once
    assert not publishing.due(0.3, changed=True)  # inside the period: held...
    assert not publishing.due(0.9, changed=False)
    assert publishing.due(1.0, changed=False)  # ...and sent once the period is over
    assert not publishing.due(2.5, changed=False)  # nothing new: nothing sent
    assert publishing.due(6.0, changed=False)  # but a refresh every 5 s
    assert publishing.due(7.1, changed=True)


def test_map_publishing_with_period_zero_sends_every_change():
    publishing = MapPublishing(period=0.0)
    assert [publishing.due(t, True) for t in (0.0, 0.0, 0.1)] == [True, True, True]
    assert not publishing.due(0.2, changed=False)


def test_map_publishing_doctest():
    result = doctest.testmod(occupancy)
    assert result.failed == 0 and result.attempted >= 2
