"""Issue 26's depot: obstacles nobody named, found by elevation (noisy depth) or by foreground
(cameras without depth); the robot reaches its station without touching them, and with elevation
drives under the shelf that leaves it room (a camera saw floor under it), not under the low one.

The world checks are quick; the two runs are slow variants (about half a minute each on an
idle machine, a minute on a loaded one: more than a default-suite pair may take).
"""

import pytest
from shapely.geometry import LineString, Polygon
from test_scenarios import SCENARIO_TIMEOUT, checked

from drvs.algorithms.colour import ColourModel
from drvs.robot.mapping import HEADROOM
from drvs.sim.world_file import load_world
from drvs.testing import RosHarness
from drvs.testing.scenario import start_scenario

WORLDS = {'elevation': 'worlds/depot.yaml', 'foreground': 'worlds/depot_foreground.yaml'}
OPTIONS = {'elevation': ('--camera-source', 'render'), 'foreground': ('--camera-source', 'colour')}


@pytest.mark.parametrize('algorithm', sorted(WORLDS))
def test_no_model_names_an_obstacle_and_a_shelf_hangs_lower_than_the_robot(algorithm):
    world = load_world(WORLDS[algorithm])
    assert world.colour_models['obstacle'].split(':')[0] == algorithm
    colours = [
        ColourModel.parse(m.split(':', 1)[1]) for m in world.colour_models.values() if m.startswith('colour:')
    ]
    for body in world.objects:
        assert not any(
            all(c.lower[i] <= body.colour[i] <= c.upper[i] for i in range(3)) for c in colours
        ), body.name
    heights = sorted(body.top for body in world.objects if body.bottom == 0)
    assert heights[0] <= 0.05 and heights[-1] >= 1.0  # a pallet and a 1 m box
    shelves = {body.name: body for body in world.objects if body.bottom > 0}
    assert shelves['shelf'].bottom < world.robot.size[2] < shelves['shelf'].top  # it cannot pass under it
    if algorithm == 'elevation':  # room under it, measured from below up to 10 cm too low
        assert shelves['high_shelf'].bottom - 0.1 > world.robot.size[2] + HEADROOM
    depth = [camera.depth_noise is not None for camera in world.vision_systems]
    assert all(depth) if algorithm == 'elevation' else not any(depth)


@pytest.mark.slow
@pytest.mark.parametrize('algorithm', sorted(WORLDS))
def test_the_robot_reaches_its_station_round_obstacles_nobody_named(ros: RosHarness, algorithm):
    """With elevation, a second robot drives along the north wall: each cuts the other out of
    what elevation reports (where it is and was), and neither is in the other's way for good."""
    world = load_world(WORLDS[algorithm])
    run = start_scenario(ros, WORLDS[algorithm], *OPTIONS[algorithm], timeout=SCENARIO_TIMEOUT)
    code, summary, trace, logs = checked(run)
    assert code == 0, logs
    assert summary['reached'] is True and len(summary['robots']) == len(world.robots)
    assert summary['collisions'] == 0
    for name, driven in trace['robots'].items():
        path = LineString([(x, y) for _, x, y in driven['trajectory']])
        for body in (
            world.objects
        ):  # the pallet across the straight line, the low shelf: no robot drove over or under
            under = path.intersects(Polygon(body.footprint()))
            # The first robot under the high one (the shorter way round the pallet).
            assert under == (name == 'robot' and body.name == 'high_shelf'), (name, body.name)
