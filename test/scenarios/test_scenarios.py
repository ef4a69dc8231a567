"""The paper's case study end to end (section 4): one run of scripts/run_scenario.sh per world.

Each test runs the real thing — rosmaster, drvs_server, world_sim, a vision_system
per camera, the recorder and blind_robot — against a private master
(``--external-master``), then checks the summary and the ground truth it recorded. The
runs of ``make test`` start two at a time (test/scenarios/conftest.py), each on a master
of its own; the slow variants run one at a time.
"""

import json
import math

import pytest
from shapely.geometry import LineString, Point, Polygon, box

from drvs.robot.params import RobotParams
from drvs.sim.world_file import load_world
from drvs.testing import RosHarness
from drvs.testing.scenario import ScenarioRun, start_scenario
from drvs.vision.camera import PinholeCamera

SCENARIO_TIMEOUT = 150


def checked(run: ScenarioRun) -> tuple[int, dict, dict, str]:
    """Wait for a run to end; its (exit code, summary, trace, logs), its output checked."""
    code, out = run.wait(), run.out
    logs = (
        run.runner.describe()
        + '\n'
        + '\n'.join(
            f'--- {path.name} ---\n' + '\n'.join(path.read_text(errors='replace').splitlines()[-15:])
            for path in sorted(out.glob('*.log'))
        )
    )
    summary_path = out / 'summary.json'
    assert summary_path.exists(), f'no summary.json\n{logs}'
    # Its output goes to a file, not a terminal: plain progress lines, no redrawing.
    output = run.runner.log_path.read_bytes()
    assert b'\r' not in output and b'\x1b' not in output, output
    assert b'run_scenario: state ' in output, output
    assert not (out / 'pids').exists(), 'DIR/pids left after the run'
    assert (out / 'run.png').read_bytes()[:4] == b'\x89PNG'
    return code, json.loads(summary_path.read_text()), json.loads((out / 'trace.json').read_text()), logs


def own_run(ros: RosHarness, world: str, camera_source: str) -> tuple[int, dict, dict, str]:
    """A run of ``world`` on the test's master, checked (:func:`checked`)."""
    options = ('--camera-source', camera_source, '--requests', 'watch')
    return checked(start_scenario(ros, world, *options, timeout=SCENARIO_TIMEOUT))


def scenario(request, name: str, camera_source: str = 'render') -> tuple[int, dict, dict, str]:
    """The default suite's run ``name`` (test/scenarios/conftest.py) or, with another camera
    source (a slow variant), a run of its own."""
    if camera_source == 'render':
        return checked(request.getfixturevalue('scenario_run')(name))
    return own_run(request.getfixturevalue('ros'), f'worlds/{name}.yaml', camera_source)


@pytest.mark.parametrize(
    'path', ['worlds/localisation.yaml', 'worlds/obstacles.yaml', 'worlds/selectivity.yaml']
)
def test_the_paper_geometry_vs2_sees_the_robot_vs1_the_station_neither_both(path):
    world = load_world(path)
    assert world.robot.position == (0.83, 2.65)
    assert world.station.position == (5.90, 3.55)
    views = {c.name: Polygon(PinholeCamera.from_config(c).floor_footprint()) for c in world.vision_systems}
    robot, station = Polygon(world.robot.footprint()), Polygon(world.station.footprint())
    assert world.camera('vs2').position[:2] == (2.05, 2.05)
    assert world.camera('vs1').position[:2] == (4.85, 2.78)
    assert views['vs2'].contains(robot) and not views['vs2'].intersects(station)
    assert views['vs1'].contains(station) and not views['vs1'].intersects(robot)


def test_selectivity_far_cameras_see_none_of_the_robot_station_box():
    """vs3 and vs4 stay clear of the obstacle region even with the robot's default margin."""
    world = load_world('worlds/selectivity.yaml')
    margin = RobotParams.__dataclass_fields__['roi_margin'].default
    (x0, y0), (x1, y1) = world.robot.position, world.station.position
    region = box(min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1)).buffer(margin + 0.3, join_style=2)
    for far in ('vs3', 'vs4'):
        assert not Polygon(PinholeCamera.from_config(world.camera(far)).floor_footprint()).intersects(region)


# `make test` runs case study 4.1 with rendering cameras once, recorded, in test_record.py
# (which makes these same checks); both camera sources here are slow variants.
@pytest.mark.slow
@pytest.mark.parametrize('camera_source', ['render', 'topic'])
def test_localisation_the_blind_robot_finds_itself_and_its_station(ros: RosHarness, camera_source):
    code, summary, trace, logs = own_run(ros, 'worlds/localisation.yaml', camera_source)
    assert code == 0, logs
    assert summary['reached'] is True
    assert summary['collisions'] == 0
    # Without obstacles the drive is nearly the straight line from start to station.
    assert summary['driven_length'] == pytest.approx(summary['best_length'], rel=0.15)
    assert {'vs1', 'vs2'} <= set(summary['vision_systems'])
    for camera in ('vs1', 'vs2'):
        assert summary['vision_systems'][camera]['callbacks'] > 0


@pytest.mark.parametrize(
    'camera_source', ['render', pytest.param('topic', marks=pytest.mark.slow, id='topic')]
)
def test_obstacles_robot_replans_round_the_human_without_collision(request, camera_source):
    world = load_world('worlds/obstacles.yaml')
    code, summary, trace, logs = scenario(request, 'obstacles', camera_source)
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
            # The robot asked about a plan's floor before it followed it: no plan crosses a box.
            footprint = Polygon(obstacle.footprint())
            assert not any(footprint.contains(Point(p)) for plan in plans for p in plan), obstacle.name


@pytest.mark.parametrize(
    'camera_source', ['render', pytest.param('topic', marks=pytest.mark.slow, id='topic')]
)
def test_selectivity_far_cameras_get_localisation_but_no_obstacle_requests(request, camera_source):
    world = load_world('worlds/selectivity.yaml')
    code, summary, trace, logs = scenario(request, 'selectivity', camera_source)
    assert code == 0, logs
    cameras = summary['vision_systems']
    models = world.colour_models
    for far in ('vs3', 'vs4'):
        by_algorithm = cameras[far]['requests_by_algorithm']
        assert by_algorithm.get(models['self'], 0) > 0, far
        assert by_algorithm.get(models['station'], 0) > 0, far
        assert by_algorithm.get(models['obstacle'], 0) == 0, far
        assert by_algorithm.get(models['human'], 0) == 0, far
        # (They do call back: a fused station watch's vision systems answer the fusion stage
        # every period, "nothing here" too.)
    for near in ('vs1', 'vs2'):
        assert cameras[near]['requests_by_algorithm'].get(models['obstacle'], 0) > 0, near
        assert cameras[near]['callbacks'] > 0, near
    assert summary['reached'] is True


def test_tags_the_robot_sees_its_pose_and_heading_and_finds_the_human_by_motion(request):
    """The fourth scenario: tags for the robot and its station, ``motion`` for the human."""
    world = load_world('worlds/tags.yaml')
    assert world.colour_models['human'] == 'motion'  # no colour model for the human
    # Polling: with watches the robot drives into the human once it stops in the gap (a person
    # who stands still fades out of the motion model, and changes_only reports it gone).
    code, summary, trace, logs = scenario(request, 'tags')
    assert code == 0, logs
    assert summary['reached'] is True
    assert summary['collisions'] == 0
    poses = trace['tag_poses']
    assert len(poses) >= 5, logs  # the picture has the poses the cameras saw
    headings = sorted(abs(math.remainder(heading - world.robot.yaw, math.tau)) for _, _, heading in poses)
    assert math.degrees(headings[len(headings) // 2]) <= 3.0  # seen, not predicted: the body's yaw
    walker = next(o for o in world.objects if o.kind == 'human')
    stand = Point(walker.waypoints[-1]).buffer(walker.size[0] / 2)
    driven = LineString([(x, y) for _, x, y in trace['trajectory']])
    assert not driven.intersects(stand)
