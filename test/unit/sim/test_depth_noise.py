"""The simulated depth sensor: error growing with the square of the distance, holes at depth edges
and on dark and shiny surfaces, repeatable with a seed; and its world file key, ``depth_noise``."""

import numpy as np
import pytest
import yaml

from drvs.sim.depth_noise import DepthNoise
from drvs.sim.world import WorldError
from drvs.sim.world_file import load_world

WALL = np.full((200, 200), 2.0, np.float32)


def rng(seed=3):
    return np.random.default_rng(seed)


@pytest.mark.parametrize('distance', [1.0, 2.0, 4.0])
def test_the_error_grows_with_the_square_of_the_distance(distance):
    noise = DepthNoise(error=0.002, edge_width=0, dark_dropout=0)
    noisy = noise.apply(np.full((300, 300), distance, np.float32), None, rng())
    assert np.std(noisy) == pytest.approx(0.002 * distance**2, rel=0.03)
    assert np.mean(noisy) == pytest.approx(distance, abs=0.002 * distance**2 * 0.03)


def test_holes_fall_along_depth_edges_and_on_dark_surfaces_only():
    depth = WALL.copy()
    depth[50:150, 50:150] = 1.5  # a box: its outline is a depth edge
    rgb = np.full((200, 200, 3), 200, np.uint8)
    rgb[:, :20] = 10  # a dark strip
    noise = DepthNoise(error=0.0, edge_width=2, edge_dropout=1.0, dark_level=30, dark_dropout=1.0)
    holes = noise.apply(depth, rgb, rng()) == 0
    expected = np.zeros((200, 200), bool)
    expected[48:152, 48:152] = True  # 2 pixels either side of each edge (between rows 49 and 50 ...)
    expected[52:148, 52:148] = False
    expected[[48, 48, 151, 151], [48, 151, 48, 151]] = False  # the band's outer corners: only diagonal
    expected[:, :20] = True
    assert np.array_equal(holes, expected)


def test_shiny_pixels_drop_out_at_their_rate():
    shiny = np.zeros((200, 200), bool)
    shiny[:100] = True
    holes = DepthNoise(error=0.0, edge_width=0, dark_dropout=0, shiny_dropout=0.5).apply(
        WALL, None, rng(), shiny
    )
    assert np.mean(holes[:100] == 0) == pytest.approx(0.5, abs=0.02)
    assert not np.any(holes[100:] == 0)


def test_a_seed_repeats_the_noise_and_holes_stay_holes():
    depth = WALL.copy()
    depth[0, 0] = np.nan
    depth[0, 1] = 0.0
    noise = DepthNoise()
    first, again = noise.apply(depth, None, rng(5)), noise.apply(depth, None, rng(5))
    assert np.array_equal(first, again)
    assert first[0, 0] == 0 and first[0, 1] == 0
    assert not np.array_equal(first, noise.apply(depth, None, rng(6)))
    assert np.array_equal(
        noise.generator('vs1').random(4), DepthNoise().generator('vs1').random(4)
    )  # a camera's generator is its own, run after run


WORLD = {
    'floor': {'size': [4.0, 3.0]},
    'robot': {'position': [0.5, 1.5], 'size': [0.3, 0.3, 0.2], 'colour': [0, 200, 0]},
    'station': {'position': [3.5, 2.5], 'size': [0.4, 0.3, 0.1], 'colour': [0, 0, 220]},
    'objects': [{'name': 'tray', 'position': [2.0, 1.0], 'size': [0.4, 0.6, 0.1], 'colour': [90, 90, 90]}],
    'vision_systems': [{'name': 'vs1', 'position': [2.0, 1.5, 3.0], 'fov_deg': 60}],
    'colour_models': {
        'self': 'colour:0,150,0,80,255,80',
        'station': 'colour:0,0,150,80,80,255',
        'obstacle': 'colour:80,80,80,100,100,100',
        'human': 'colour:150,0,0,255,80,80',
    },
}


def world_with(tmp_path, noise, shiny=None):
    data = yaml.safe_load(yaml.safe_dump(WORLD))
    data['vision_systems'][0]['depth_noise'] = noise
    if shiny is not None:
        data['objects'][0]['shiny'] = shiny
    path = tmp_path / 'noisy.yaml'
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize(
    'value, expected',
    [
        (True, DepthNoise()),
        (False, None),
        ({'error': 0.003, 'seed': 7}, DepthNoise(error=0.003, seed=7)),
        ({}, DepthNoise()),
    ],
)
def test_a_camera_reads_its_depth_noise(tmp_path, value, expected):
    world = load_world(world_with(tmp_path, value, shiny=True))
    assert world.camera('vs1').depth_noise == expected
    assert world.objects[0].shiny


@pytest.mark.parametrize(
    'value, message',
    [
        (
            'yes',
            "vision_system 'vs1'.depth_noise: expected true, false or a mapping of error, edge_jump, "
            "edge_width, edge_dropout, dark_level, dark_dropout, shiny_dropout, seed, got 'yes'",
        ),
        (
            {'eror': 0.01},
            "vision_system 'vs1'.depth_noise.eror: unknown key; did you mean error? (keys of depth_noise: "
            'error, edge_jump, edge_width, edge_dropout, dark_level, dark_dropout, shiny_dropout, seed)',
        ),
        (
            {'error': 0.5},
            "vision_system 'vs1'.depth_noise.error: expected a number 0-0.1 (metres at 1 m), got 0.5",
        ),
        (
            {'edge_dropout': 2},
            "vision_system 'vs1'.depth_noise.edge_dropout: expected a probability 0-1, got 2",
        ),
        (
            {'edge_width': 1.5},
            "vision_system 'vs1'.depth_noise.edge_width: expected an integer 0-20, got 1.5",
        ),
        ({'seed': -1}, "vision_system 'vs1'.depth_noise.seed: expected an integer 0-4294967295, got -1"),
    ],
)
def test_bad_depth_noise_is_refused_naming_the_key(tmp_path, value, message):
    path = world_with(tmp_path, value)
    with pytest.raises(WorldError) as error:
        load_world(path)
    assert [str(problem) for problem in error.value.problems] == [message]


def test_the_scene_renders_noisy_depth_with_holes_on_shiny_bodies(tmp_path):
    from drvs.sim.scene import Scene
    from drvs.vision.camera import PinholeCamera

    noise = {'error': 0.0, 'edge_width': 0, 'dark_dropout': 0.0, 'shiny_dropout': 1.0}
    world = load_world(world_with(tmp_path, noise, shiny=True))
    camera = PinholeCamera.from_config(world.camera('vs1'), resolution=(160, 120))
    tray = camera.project_3d_to_pixel((2.0, 1.0, 0.1)).astype(int)  # the centre of its top
    with Scene(world) as scene:
        perfect = scene.render(camera)
        noisy = scene.render(camera, noise=world.camera('vs1').depth_noise, rng=rng())
    assert perfect.depth[tray[1], tray[0]] == pytest.approx(2.9, abs=0.01)
    assert noisy.depth[tray[1], tray[0]] == 0  # a hole on the shiny tray
    assert np.count_nonzero(noisy.depth == 0) == pytest.approx(
        np.count_nonzero(perfect.rgb[..., 0] == 90), rel=0.05
    )
