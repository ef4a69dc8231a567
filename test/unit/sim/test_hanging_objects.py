"""A static object hanging above the floor (``bottom``, a shelf): read, placed in the scene at its
height, passed under by what is lower, and over other bodies without overlapping them."""

import pytest
import yaml

from drvs.sim.world import WorldError
from drvs.sim.world_file import load_world

WORLD = {
    'floor': {'size': [4.0, 3.0]},
    'robot': {'position': [0.5, 1.5], 'size': [0.3, 0.3, 0.2], 'colour': [0, 200, 0]},
    'station': {'position': [3.5, 2.5], 'size': [0.4, 0.3, 0.1], 'colour': [0, 0, 220]},
    'objects': [
        {'name': 'box', 'position': [2.0, 1.0], 'size': [0.4, 0.4, 0.5], 'colour': [90, 90, 90]},
        # a shelf over the box and over the robot's way, 1.2 m up
        {
            'name': 'shelf',
            'position': [1.8, 1.2],
            'size': [1.0, 0.8, 0.05],
            'colour': [90, 90, 90],
            'bottom': 1.2,
        },
        {
            'name': 'walker',
            'kind': 'human',
            'position': [1.5, 0.4],
            'size': [0.3, 0.3, 1.1],
            'colour': [220, 0, 0],
            'waypoints': [[1.5, 0.4], [1.5, 2.6]],
            'speed': 0.5,
        },
    ],
    'vision_systems': [{'name': 'vs1', 'position': [2.0, 1.5, 3.0], 'fov_deg': 60, 'resolution': [160, 120]}],
    'colour_models': {
        'self': 'colour:0,150,0,80,255,80',
        'station': 'colour:0,0,150,80,80,255',
        'obstacle': 'colour:80,80,80,100,100,100',
        'human': 'colour:150,0,0,255,80,80',
    },
}


def load(tmp_path, changes=None):
    data = yaml.safe_load(yaml.safe_dump(WORLD))
    for (index, key), value in (changes or {}).items():
        data['objects'][index][key] = value
    path = tmp_path / 'hanging.yaml'
    path.write_text(yaml.safe_dump(data))
    return load_world(path)


def test_a_shelf_hangs_over_a_box_and_a_walk_passes_under_it(tmp_path):
    world = load(tmp_path)
    shelf = world.objects[1]
    assert (shelf.bottom, shelf.top) == (1.2, pytest.approx(1.25))
    assert world.objects[0].bottom == 0.0


@pytest.mark.parametrize(
    'change, message',
    [
        ({(1, 'bottom'): 0.3}, "object 'shelf'.position: overlaps object 'box': move one of them"),
        (
            {(2, 'size'): [0.3, 0.3, 1.7]},
            "human 'walker'.waypoints: its walk from [1.5, 0.4] to [1.5, 2.6] crosses",
        ),
        ({(1, 'bottom'): -1}, "object 'shelf'.bottom: expected a number 0-100 (metres), got -1"),
        (
            {(2, 'bottom'): 1.0},
            "human 'walker'.bottom: does not apply: only a static object may hang above the floor",
        ),
    ],
    ids=['shelf down on the box', 'a human too tall to pass', 'below the floor', 'a hanging human'],
)
def test_what_cannot_be_is_refused(tmp_path, change, message):
    with pytest.raises(WorldError) as error:
        load(tmp_path, change)
    assert any(str(problem).startswith(message) for problem in error.value.problems), error.value


def test_the_scene_places_it_at_its_height_and_the_robot_passes_under(tmp_path):
    from drvs.sim.scene import Scene
    from drvs.vision.camera import PinholeCamera

    world = load(tmp_path)
    camera = PinholeCamera.from_config(world.camera('vs1'))
    with Scene(world) as scene:
        frame = scene.render(camera)
        scene.set_pose('robot', 1.8, 1.5, 0.0)  # under the shelf
        assert scene.distances('robot', ['shelf'], 0.5) == {}  # no contact: 1 m of room
        assert scene.distances('robot', ['shelf'], 2.0) == {'shelf': pytest.approx(1.0, abs=0.01)}
    u, v = camera.project_3d_to_pixel((1.6, 1.5, 1.25)).astype(int)  # on the shelf, beside the box
    assert frame.depth[v, u] == pytest.approx(3.0 - 1.25, abs=0.01)
