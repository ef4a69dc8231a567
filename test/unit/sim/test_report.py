"""The scenario report: hindsight shortest route, summary keys and rows, figures, and the picture."""

import dataclasses
import doctest
import math

import numpy as np
import pytest
import yaml
from matplotlib.colors import to_hex

import drvs.sim.report
from drvs.sim.report import (
    CAMERA_COLOURS,
    HUMAN_COLOURS,
    ROBOT_COLOURS,
    TRAJECTORY_COLOUR,
    RobotRecord,
    RunRecord,
    best_lengths,
    collision_failure,
    draw,
    figures_table,
    hindsight_shortest_length,
    picture,
    summary,
    trace,
)
from drvs.sim.tracking import NO_OBJECTS, TrackPeriod, TrackPoint
from drvs.sim.world import Body, FleetRobot
from drvs.sim.world_file import load_world

MODELS = {
    'self': 'colour:0,150,0,80,255,80',
    'station': 'colour:0,0,150,80,80,255',
    'obstacle': 'colour:40,40,40,90,90,90',
    'human': 'colour:150,0,0,255,80,80',
}


def make_world(tmp_path, objects, cameras=None):
    data = {
        'floor': {'size': [6.0, 4.0]},
        'robot': {'position': [1.0, 2.0], 'size': [0.2, 0.2, 0.2], 'colour': [0, 200, 0], 'speed': 0.4},
        'station': {'position': [5.0, 2.0], 'size': [0.4, 0.3, 0.1], 'colour': [0, 0, 220]},
        'objects': objects,
        'vision_systems': cameras or [{'name': 'vs1', 'position': [3.0, 2.0, 4.0], 'fov_deg': 60}],
        'colour_models': MODELS,
    }
    path = tmp_path / 'world.yaml'
    path.write_text(yaml.safe_dump(data))
    return load_world(path)


def test_hindsight_route_is_straight_without_obstacles(tmp_path):
    assert hindsight_shortest_length(make_world(tmp_path, []), radius=0.1) == pytest.approx(4.0)


def test_hindsight_route_goes_round_a_wall_by_its_nearer_end(tmp_path):
    # A wall from y=0.5 to y=3.0 at x=3 (0.2 thick): the route passes above it, at y = 3.0 + radius.
    wall = {
        'name': 'wall',
        'kind': 'static',
        'position': [3.0, 1.75],
        'size': [0.2, 2.5, 0.5],
        'colour': [60, 60, 60],
    }
    world = make_world(tmp_path, [wall])
    radius = 0.1
    corner_y = 3.0 + radius
    left, right = (3.0 - 0.1 - radius, corner_y), (3.0 + 0.1 + radius, corner_y)
    expected = math.dist((1.0, 2.0), left) + math.dist(left, right) + math.dist(right, (5.0, 2.0))
    assert hindsight_shortest_length(world, radius) == pytest.approx(expected, abs=0.01)


def test_hindsight_route_is_infinite_when_the_station_is_walled_off(tmp_path):
    wall = {
        'name': 'wall',
        'kind': 'static',
        'position': [3.0, 2.0],
        'size': [0.2, 4.0, 0.5],
        'colour': [60, 60, 60],
    }
    assert hindsight_shortest_length(make_world(tmp_path, [wall]), radius=0.1) == math.inf


PAPER_KEYS = {
    'world',
    'reached',
    'state',
    'reason',
    'elapsed',
    'driven_length',
    'best_length',
    'replans',
    'collisions',
    'vision_systems',
    'cpu',
}
"""The summary's keys before fleets: a single-robot world keeps every one."""


def test_a_single_robot_summary_keeps_the_paper_keys_and_has_its_row(tmp_path):
    world = make_world(tmp_path, [])
    robot = RobotRecord(
        'robot',
        reached=True,
        elapsed=12.5,
        state='arrived',
        replans=1,
        requests=40,
        watch_calls=4,
        callbacks=90,
        callback_bytes=12000,
        travelled=3.0,
        trajectory=[(0.0, 1.0, 2.0), (1.0, 3.0, 2.0), (2.0, 3.0, 3.0)],
        plans=[(0.0, [(1.0, 2.0), (5.0, 2.0)]), (1.0, [(3.0, 2.0), (3.0, 3.0), (5.0, 2.0)])],
        replan_points=[(3.0, 2.0)],
    )
    record = RunRecord(
        world=world,
        robots={'robot': robot},
        fields_of_view={'/vs1/detect_object_boundary': [(0.0, 0.0), (6.0, 0.0), (6.0, 4.0), (0.0, 4.0)]},
        grid=np.zeros((80, 120), np.int8),
        vision_systems={'vs1': {'requests': 4, 'callbacks': 2, 'callback_bytes': 300}},
        server={'requests': 3, 'watch_requests': 4, 'forwards': 7},
        wall_seconds=13.25,
    )
    result = summary(record, best_length={'robot': 4.0})
    assert PAPER_KEYS <= set(result)
    assert result['driven_length'] == pytest.approx(3.0)
    assert result['vision_systems']['vs1']['callback_bytes'] == 300
    (row,) = result['robots']
    assert {key: row[key] for key in ('reached', 'state', 'elapsed', 'replans', 'driven_length')} == {
        key: result[key] for key in ('reached', 'state', 'elapsed', 'replans', 'driven_length')
    }
    assert row == {
        'name': 'robot',
        'reached': True,
        'state': 'arrived',
        'reason': '',
        'collided': '',
        'collisions': 0,
        'elapsed': 12.5,
        'arrival': 12.5,
        'driven_length': 3.0,
        'best_length': 4.0,
        'replans': 1,
        'requests': 40,
        'watch_calls': 4,
        'callbacks': 90,
        'callback_bytes': 12000,
    }
    assert result['server'] == {
        'requests': 3,
        'watch_requests': 4,
        'refused': 0,
        'forwards': 7,
        'watch_forwards': 0,
        'fallback_forwards': 0,
        'forward_failures': 0,
    }
    assert (result['real_time_factor'], result['wall_seconds']) == (1.0, 13.25)
    assert trace(record)['plans'] == trace(record)['robots']['robot']['plans'] == [p for _, p in robot.plans]
    picture = tmp_path / 'run.png'
    draw(record, picture)
    assert picture.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def fleet_world(tmp_path, objects=()):
    """make_world's world with a second robot (robot2, from the right to the left) and its station."""
    world = make_world(tmp_path, list(objects))
    body = Body('robot2', (5.0, 0.8), (0.4, 0.4, 0.2), (200, 200, 0), speed=0.4)
    station = Body('robot2_station', (1.0, 0.8), (0.4, 0.3, 0.1), (0, 200, 200))
    return dataclasses.replace(world, robots=(*world.robots, FleetRobot('robot2', body, station, {})))


def two_robots(world):
    return RunRecord(
        world=world,
        robots={
            'robot': RobotRecord(
                'robot', reached=True, elapsed=10.0, state='arrived', replans=1, collisions=1, requests=8
            ),
            'robot2': RobotRecord(
                'robot2', elapsed=30.0, state='failed', reason='no route', replans=2, trajectory=[(0, 5, 0.8)]
            ),
        },
    )


def test_a_fleet_summary_has_a_row_per_robot_and_the_totals(tmp_path):
    world = fleet_world(tmp_path)
    result = summary(two_robots(world), best_length=best_lengths(world))
    assert [row['name'] for row in result['robots']] == ['robot', 'robot2']
    first, second = result['robots']
    assert (first['reached'], first['arrival'], first['best_length']) == (True, 10.0, pytest.approx(4.0))
    assert (second['reached'], second['arrival'], second['state'], second['reason']) == (
        False,
        None,
        'failed',
        'no route',
    )
    assert second['best_length'] == pytest.approx(4.0)
    # The totals: every robot reached? the last one done, re-plans and collisions of all.
    assert (result['reached'], result['elapsed'], result['replans'], result['collisions']) == (
        False,
        30.0,
        3,
        1,
    )
    assert not {'state', 'driven_length', 'best_length'} & set(result)
    assert result['reason'] == (
        "robot collided once (...): a collision fails a blind robot's mission; robot2 did not reach "
        'its station (failed: no route)'
    )
    assert set(trace(two_robots(world))) == {'robots', 'humans', 'fields_of_view'}


def test_a_collision_fails_the_run_even_when_every_robot_reached_its_station(tmp_path):
    world = fleet_world(tmp_path)
    touches = [('robot2', 9.31, 3.84), ('robot2', 11.94, 4.78), ('robot2', 9.33, 3.81)]
    record = RunRecord(
        world=world,
        robots={
            'robot': RobotRecord('robot', reached=True, state='arrived', collisions=3, touches=touches),
            'robot2': RobotRecord('robot2', reached=True, state='arrived', collisions=3),
        },
    )
    result = summary(record, best_length={})
    collided = (
        'robot collided 3 times (robot2 at (9.3, 3.8), robot2 at (11.9, 4.8), robot2 at (9.3, 3.8)): '
        "a collision fails a blind robot's mission"
    )
    assert (result['reached'], result['success'], result['collisions']) == (True, False, 6)
    # robot2's touches fell between two ground truths the recorder saw: the count stands alone.
    lost = "robot2 collided 3 times (...): a collision fails a blind robot's mission"
    assert result['reason'] == f'{collided}; {lost}'
    assert collision_failure(result) == f'{collided}; {lost}'


def test_a_run_without_collisions_is_no_collision_failure(tmp_path):
    record = two_robots(fleet_world(tmp_path))
    record.robots['robot'].collisions = 0
    result = summary(record, best_length={})
    assert collision_failure(result) == ''
    assert (result['success'], result['reason']) == (
        False,
        'robot2 did not reach its station (failed: no route)',
    )
    record.robots['robot2'] = RobotRecord('robot2', reached=True, state='arrived')
    assert (summary(record, best_length={})['success'], collision_failure({})) == (True, '')


def test_best_lengths_are_each_robots_own_route_for_its_own_clearance(tmp_path):
    # A wall across the lower half: robot2 (0.4 m square) goes round its top end, robot passes above.
    wall = {
        'name': 'wall',
        'kind': 'static',
        'position': [3.0, 0.75],
        'size': [0.2, 1.5, 0.5],
        'colour': [60, 60, 60],
    }
    lengths = best_lengths(fleet_world(tmp_path, [wall]))
    radius = math.hypot(0.4, 0.4) / 2
    left, right = (3.0 - 0.1 - radius, 1.5 + radius), (3.0 + 0.1 + radius, 1.5 + radius)
    expected = math.dist((5.0, 0.8), right) + math.dist(right, left) + math.dist(left, (1.0, 0.8))
    assert lengths == {'robot': pytest.approx(4.0), 'robot2': pytest.approx(expected, abs=0.01)}


def test_the_figures_table_has_a_row_per_robot_the_server_and_a_row_per_camera(tmp_path):
    world = fleet_world(tmp_path)
    record = two_robots(world)
    record.vision_systems = {'vs1': {'requests': 5, 'watch_calls': 2, 'renders': 9, 'callbacks': 7}}
    record.server = {'requests': 5, 'watch_requests': 2}
    record.cpu = {'/robot': {'seconds': 1.5, 'percent': 10.0}, '/vs1': {'seconds': 3.25, 'percent': 20.0}}
    record.wall_seconds = 61.0
    lines = figures_table(summary(record, best_lengths(world))).splitlines()
    assert [line.split() for line in lines] == [
        'robot reached arrival s requests watch calls callbacks callback bytes re-plans cpu s'.split(),
        'robot yes 10.0 8 0 0 0 1 1.5'.split(),
        'robot2 no - 0 0 0 0 2 -'.split(),
        'server: requests 5, watch requests 2, refused 0, forwards 0, watch forwards 0,'.split()
        + 'fallback forwards 0, forward failures 0'.split(),
        'camera requests watch calls renders callbacks watch evaluations cpu s'.split(),
        'vs1 5 2 9 7 0 3.2'.split(),
        'time: 30.0 s elapsed in ROS time (real-time factor 1.0), 61.0 s on the wall clock'.split(),
        f'tracking: not measured: {NO_OBJECTS}'.split(),
    ]
    # Columns line up: every row of the robots' table as long as its header.
    assert len({len(line) for line in lines[:3]}) == 1


def test_the_picture_legend_names_every_camera_the_human_and_where_the_robot_ended(tmp_path):
    cameras = [
        {'name': name, 'position': [x, 2.0, 4.0], 'fov_deg': 60}
        for name, x in (('vs1', 4.5), ('vs2', 1.5), ('vs3', 3.0))
    ]
    world = make_world(tmp_path, [], cameras)
    robot = RobotRecord(
        'robot',
        reached=True,
        trajectory=[(0.0, 1.0, 2.0), (1.0, 3.0, 2.0), (2.0, 4.8, 2.0)],
        plans=[(0.0, [(1.0, 2.0), (5.0, 2.0)])],
    )
    record = RunRecord(
        world=world,
        robots={'robot': robot},
        humans={'walker': [(2.0, 0.5), (2.5, 1.0), (3.0, 1.2)]},
        fields_of_view={
            '/vs1/detect_object_boundary': [(3.5, 1.0), (5.5, 1.0), (5.5, 3.0), (3.5, 3.0)],
            '/vs2/detect_object_boundary': [(0.5, 1.0), (2.5, 1.0), (2.5, 3.0), (0.5, 3.0)],
        },
    )
    figure = picture(record)
    axes = figure.axes[0]
    handles, labels = axes.get_legend_handles_labels()  # the artists behind the legend's entries
    assert [text.get_text() for text in axes.get_legend().get_texts()] == labels
    entries = dict(zip(labels, handles, strict=True))
    assert list(entries) == [
        'vs1 field of view',
        'vs2 field of view',
        'vs3: no field of view registered',
        'camera',
        'human walker: walk and last position',
        'charging station',
        'first plan',
        'driven trajectory',
        'start',
        'robot at the end',
    ]
    # Each camera's own colour, dashed; the human's walk not in the trajectory's colour.
    for i, name in enumerate(('vs1', 'vs2')):
        patch = entries[f'{name} field of view']
        assert patch.get_linestyle() == '--'
        assert to_hex(patch.get_edgecolor()) == to_hex(CAMERA_COLOURS[i])
    walk = entries['human walker: walk and last position']
    assert (walk.get_linestyle(), walk.get_marker()) == (':', 'o')
    assert to_hex(walk.get_color()) == to_hex(HUMAN_COLOURS[0])
    assert to_hex(entries['driven trajectory'].get_color()) == to_hex(TRAJECTORY_COLOUR)
    assert len({to_hex(c) for c in (*CAMERA_COLOURS, *HUMAN_COLOURS, TRAJECTORY_COLOUR)}) == (
        len(CAMERA_COLOURS) + len(HUMAN_COLOURS) + 1
    )
    # The final position is the trajectory's last point.
    (end,) = [line for line in axes.get_lines() if line.get_label() == 'robot at the end']
    assert (list(end.get_xdata()), list(end.get_ydata())) == ([4.8], [2.0])


def test_the_fleet_picture_draws_each_robot_in_its_own_colour_and_names_it(tmp_path):
    record = two_robots(fleet_world(tmp_path))
    record.robots['robot'].trajectory = [(0.0, 1.0, 2.0), (1.0, 4.9, 2.0)]
    record.robots['robot2'].trajectory = [(0.0, 5.0, 0.8), (1.0, 1.1, 0.8)]
    record.robots['robot2'].plans = [(0.0, [(5.0, 0.8), (1.0, 0.8)]), (0.5, [(3.0, 0.8), (1.0, 0.8)])]
    axes = picture(record).axes[0]
    handles, labels = axes.get_legend_handles_labels()
    entries = dict(zip(labels, handles, strict=True))
    assert list(entries) == [
        'vs1: no field of view registered',
        "charging stations, edged in their robot's colour",
        'robot: driven trajectory',
        'start',
        'robot at the end',
        'first plan',
        're-plans',
        'robot2: driven trajectory',
    ]
    colours = [to_hex(entries[f'{name}: driven trajectory'].get_color()) for name in ('robot', 'robot2')]
    assert colours == [to_hex(c) for c in ROBOT_COLOURS[:2]]
    # Each station edged in its robot's colour.
    stations = [p for p in axes.patches if p.get_linewidth() == 2.5]
    assert [to_hex(p.get_edgecolor()) for p in stations] == colours
    assert len({to_hex(c) for c in (*CAMERA_COLOURS, *HUMAN_COLOURS, *ROBOT_COLOURS)}) == (
        len(CAMERA_COLOURS) + len(HUMAN_COLOURS) + len(ROBOT_COLOURS)
    )
    assert (
        axes.get_title()
        == 'world: 1 of 2 robots reached their stations in 30.0 s, 3 re-plan(s), 1 collision(s)'
    )


def test_doctests():
    assert doctest.testmod(drvs.sim.report).failed == 0


def test_the_summary_measures_the_fused_tracks_and_the_table_prints_them(tmp_path):
    walker = {
        'name': 'walker',
        'kind': 'human',
        'position': [2.0, 1.0],
        'size': [0.3, 0.3, 1.7],
        'colour': [220, 0, 0],
        'waypoints': [[2.0, 1.0], [2.0, 3.0]],
        'speed': 0.5,
    }
    record = RunRecord(world=make_world(tmp_path, [walker]))
    record.truth = {'walker': [(10.0, 2.0, 1.0), (12.0, 2.0, 2.0)]}
    record.track_periods = [
        TrackPeriod(t, (TrackPoint(MODELS['human'], 4, 2.05, 1.0 + (t - 10.0) / 2),))
        for t in (10.0, 11.0, 12.0)
    ]

    block = summary(record, best_lengths(record.world))['tracking']

    assert block['measured'] and block['periods'] == 3 and block['span'] == 2.0
    (row,) = block['algorithms']
    assert (row['kind'], row['bodies'], row['mota'], row['idf1']) == ('people', ['walker'], 1.0, 1.0)
    assert row['position_error_p50'] == pytest.approx(0.05)
    lines = figures_table(summary(record, best_lengths(record.world))).splitlines()
    assert lines[-5].startswith('tracking: 3 periods of /drvs/objects over 2.0 s')
    assert lines[-3].split()[:4] == [MODELS['human'], 'people', '1.000', '1.000']
    assert lines[-1].startswith('tracking targets: duplicates 0 (≤ 0: met), idf1 1 (≥ 0.9: met)')
