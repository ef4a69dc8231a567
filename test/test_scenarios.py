"""The paper's case study end to end (section 4): one run of scripts/run_scenario.sh per world.

Each test runs the real thing — rosmaster, drvs_server, world_sim, a vision_system
per camera, the recorder and blind_robot — against the test's private master
(``--external-master``), then checks the summary and the ground truth it recorded.
"""

import json

import pytest
from shapely.geometry import LineString, Point, Polygon

from drvs.testing import RosHarness, wait_for
from drvs.world import load_world

SCENARIO_TIMEOUT = 150


def run_scenario(ros: RosHarness, world: str) -> tuple[int, dict, dict, str]:
    out = ros.root / 'out'
    runner = ros.spawn(
        'run_scenario',
        [
            'bash',
            'scripts/run_scenario.sh',
            world,
            '--external-master',
            '--timeout',
            str(SCENARIO_TIMEOUT),
            '--out',
            str(out),
        ],
    )
    wait_for(
        lambda: not runner.running(),
        SCENARIO_TIMEOUT + 60,
        f'run_scenario.sh {world} to finish',
        interval=0.5,
        on_timeout=runner.describe,
    )
    code = runner.process.returncode
    logs = (
        runner.describe()
        + '\n'
        + '\n'.join(
            f'--- {path.name} ---\n' + '\n'.join(path.read_text(errors='replace').splitlines()[-15:])
            for path in sorted(out.glob('*.log'))
        )
    )
    summary_path = out / 'summary.json'
    assert summary_path.exists(), f'no summary.json\n{logs}'
    assert (out / 'run.png').read_bytes()[:4] == b'\x89PNG'
    return code, json.loads(summary_path.read_text()), json.loads((out / 'trace.json').read_text()), logs


def test_localisation_the_blind_robot_finds_itself_and_its_station(ros: RosHarness):
    code, summary, trace, logs = run_scenario(ros, 'worlds/localisation.yaml')
    assert code == 0, logs
    assert summary['reached'] is True
    assert summary['collisions'] == 0
    # Without obstacles the drive is nearly the straight line from start to station.
    assert summary['driven_length'] == pytest.approx(summary['best_length'], rel=0.15)
    assert {'vs1', 'vs2'} <= set(summary['vision_systems'])
    for camera in ('vs1', 'vs2'):
        assert summary['vision_systems'][camera]['callbacks'] > 0


def test_obstacles_robot_replans_round_the_human_without_collision(ros: RosHarness):
    world = load_world('worlds/obstacles.yaml')
    code, summary, trace, logs = run_scenario(ros, 'worlds/obstacles.yaml')
    assert code == 0, logs
    assert summary['reached'] is True
    assert summary['collisions'] == 0
    assert summary['replans'] >= 1
    plans = trace['plans']
    walker = next(o for o in world.objects if o.kind == 'human')
    stand = Point(walker.waypoints[-1]).buffer(walker.size[0] / 2)
    # The first plan passed where the walker comes to stand; the robot did not drive there.
    assert LineString(plans[0]).intersects(stand), plans[0]
    driven = LineString([(x, y) for _, x, y in trace['trajectory']])
    assert not driven.intersects(stand)
    for obstacle in world.objects:
        if obstacle.kind == 'static':
            assert not driven.intersects(Polygon(obstacle.footprint())), obstacle.name


def test_selectivity_far_cameras_get_localisation_but_no_obstacle_requests(ros: RosHarness):
    world = load_world('worlds/selectivity.yaml')
    code, summary, trace, logs = run_scenario(ros, 'worlds/selectivity.yaml')
    assert code == 0, logs
    cameras = summary['vision_systems']
    models = world.colour_models
    for far in ('vs3', 'vs4'):
        by_algorithm = cameras[far]['requests_by_algorithm']
        assert by_algorithm.get(models['self'], 0) > 0, far
        assert by_algorithm.get(models['station'], 0) > 0, far
        assert by_algorithm.get(models['obstacle'], 0) == 0, far
        assert by_algorithm.get(models['human'], 0) == 0, far
        assert cameras[far]['callbacks'] == 0, far
    for near in ('vs1', 'vs2'):
        assert cameras[near]['requests_by_algorithm'].get(models['obstacle'], 0) > 0, near
        assert cameras[near]['callbacks'] > 0, near
    assert summary['reached'] is True
