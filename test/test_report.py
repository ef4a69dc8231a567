"""The scenario report: hindsight shortest route, summary keys, and the picture."""

import math

import numpy as np
import pytest
import yaml
from matplotlib.colors import to_hex

from drvs.report import (
    CAMERA_COLOURS,
    HUMAN_COLOURS,
    TRAJECTORY_COLOUR,
    RunRecord,
    draw,
    hindsight_shortest_length,
    path_length,
    picture,
    summary,
)
from drvs.world import load_world

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


def test_summary_has_the_promised_keys_and_picture_is_written(tmp_path):
    world = make_world(tmp_path, [])
    record = RunRecord(
        world=world,
        reached=True,
        elapsed=12.5,
        state='reached',
        replans=1,
        trajectory=[(0.0, 1.0, 2.0), (1.0, 3.0, 2.0), (2.0, 3.0, 3.0)],
        plans=[(0.0, [(1.0, 2.0), (5.0, 2.0)]), (1.0, [(3.0, 2.0), (3.0, 3.0), (5.0, 2.0)])],
        replan_points=[(3.0, 2.0)],
        fields_of_view={'/vs1/detect_object_boundary': [(0.0, 0.0), (6.0, 0.0), (6.0, 4.0), (0.0, 4.0)]},
        grid=np.zeros((80, 120), np.int8),
        vision_systems={'vs1': {'requests': 4, 'callbacks': 2, 'callback_bytes': 300}},
    )
    result = summary(record, best_length=4.0)
    assert {
        'reached',
        'elapsed',
        'driven_length',
        'best_length',
        'replans',
        'collisions',
        'vision_systems',
    } <= set(result)
    assert result['driven_length'] == pytest.approx(3.0)
    assert result['vision_systems']['vs1']['callback_bytes'] == 300
    picture = tmp_path / 'run.png'
    draw(record, picture)
    assert picture.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def test_path_length_of_points_and_timed_points():
    assert path_length([(0, 0), (3, 4)]) == 5.0
    assert path_length([(9.0, 0, 0), (10.0, 3, 4), (11.0, 3, 5)]) == 6.0


def test_the_picture_legend_names_every_camera_the_human_and_where_the_robot_ended(tmp_path):
    cameras = [
        {'name': name, 'position': [x, 2.0, 4.0], 'fov_deg': 60}
        for name, x in (('vs1', 4.5), ('vs2', 1.5), ('vs3', 3.0))
    ]
    world = make_world(tmp_path, [], cameras)
    record = RunRecord(
        world=world,
        reached=True,
        trajectory=[(0.0, 1.0, 2.0), (1.0, 3.0, 2.0), (2.0, 4.8, 2.0)],
        plans=[(0.0, [(1.0, 2.0), (5.0, 2.0)])],
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
