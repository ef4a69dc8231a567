"""Recording a run: ``run_scenario.sh --record`` writes ``run.bag``, and ``drvs_report`` regenerates
the live recorder's summary from it.

Without a master: the recorder's core (:class:`drvs.ros.recorder.RunRecorder`) fed a run
live and the same run from a bag written here give the same summary; ``drvs_report``'s
refusals. Live: a recorded scenario, its bag, the regenerated report and ``rosbag play``.
"""

import json
import math
import subprocess
import sys

import genpy
import pytest
import rosbag
from geometry_msgs.msg import Point32, Polygon, Pose2D, PoseStamped
from nav_msgs.msg import OccupancyGrid
from nav_msgs.msg import Path as PathMsg
from std_msgs.msg import Header, String

from drvs.msg import (
    BodyPoses,
    DetectedObject,
    NodeCpu,
    RecorderSample,
    Registry,
    ServerStats,
    TrackedObjects,
    VisionSystemEntry,
)
from drvs.robot.robot_status import RobotStatus
from drvs.ros.messages import robot_status_to_msg, stats_to_msg
from drvs.ros.recorder import RunRecorder, cpu_summary
from drvs.sim.report import write_report
from drvs.sim.world_file import load_world
from drvs.testing import RosHarness, wait_for
from drvs.testing.harness import REPO, echo
from drvs.testing.messages import round_trip
from drvs.tools.bag_report import read_bag, regenerate

WORLD = REPO / 'worlds' / 'localisation.yaml'
REQUIRED_TOPICS = (
    '/drvs/registry',
    '/drvs/stats',
    '/drvs/markers',
    '/world_sim/poses',
    '/world_sim/ground_truth',
    '/robot/status',
    '/robot/path',
    '/robot/map',
    '/robot/pose',
    '/robot/cmd_vel',
    '/vs1/stats',
    '/vs2/stats',
    '/scenario_recorder/samples',
    '/diagnostics',
    '/tf',
    '/tf_static',
    '/rosout',
)


# -- the messages -------------------------------------------------------------------------------------
def cpu(node, first, last, start=100.0, end=104.0):
    return NodeCpu(
        node=node,
        pid=42,
        first_seconds=first,
        first_stamp=genpy.Time.from_sec(start),
        last_seconds=last,
        last_stamp=genpy.Time.from_sec(end),
    )


def sample(first_status, final=False, entries=(), world=WORLD, wall_seconds=0.0, stamp=100.0):
    return RecorderSample(
        header=Header(stamp=genpy.Time.from_sec(stamp)),
        world=str(world),
        first_status=genpy.Time.from_sec(first_status) if first_status else genpy.Time(),
        final=final,
        cpu=list(entries),
        wall_seconds=wall_seconds,
    )


@pytest.mark.parametrize('message', [cpu('/drvs', 1.5, 2.25), sample(2.0, True, [cpu('/vs1', 0.0, 1.0)])])
def test_the_recorder_messages_round_trip(message):
    assert round_trip(message) == message


def test_cpu_summary_is_seconds_used_and_percent_of_one_core_over_the_sampled_time():
    entries = [cpu('/vs1', 1.0, 3.0), cpu('/drvs', 0.5, 0.5, start=100.0, end=100.0)]
    assert cpu_summary(entries) == {
        '/drvs': {'seconds': 0.5, 'percent': None},
        '/vs1': {'seconds': 3.0, 'percent': 50.0},
    }


# -- the same run, live and from a bag ------------------------------------------------------------------
def truth(t, x, y, contacts=0, travelled=0.0):
    """world_sim's ground truth as before fleets: the one robot under ``robot``."""
    data = {'time': t, 'robot': {'position': [x, y]}, 'contacts': contacts, 'travelled': travelled}
    return String(data=json.dumps({**data, 'objects': {}}))


def fleet_truth(t, robots, touching=None):
    """world_sim's ground truth of a fleet: ``robots`` {name: (x, y, contacts, travelled)},
    ``touching`` {name: [what it touches now]}."""
    touching = touching or {}
    robots = {
        name: {
            'position': [x, y],
            'contacts': contacts,
            'travelled': travelled,
            'touching': touching.get(name, []),
        }
        for name, (x, y, contacts, travelled) in robots.items()
    }
    first = dict(next(iter(robots.values())))
    data = {'time': t, 'robot': {'position': first.pop('position')}, **first, 'robots': robots}
    return String(data=json.dumps({**data, 'objects': {}}))


def poses(t, bodies):
    """world_sim's /world_sim/poses: ``bodies`` {name: (x, y)}."""
    return BodyPoses(
        header=Header(stamp=genpy.Time.from_sec(t), frame_id='map'),
        names=list(bodies),
        poses=[Pose2D(x, y, 0.0) for x, y in bodies.values()],
    )


def tracked(t, tracks):
    """The fusion stage's /drvs/objects: ``tracks`` [(algorithm, track id, (x, y))], 0.3 m squares."""

    def square(x, y):
        return Polygon(
            [
                Point32(x + dx, y + dy, 0.0)
                for dx, dy in ((-0.15, -0.15), (0.15, -0.15), (0.15, 0.15), (-0.15, 0.15))
            ]
        )

    return TrackedObjects(
        header=Header(stamp=genpy.Time.from_sec(t), frame_id='map'),
        algorithms=[algorithm for algorithm, _, _ in tracks],
        objects=[DetectedObject(boundary=square(*xy), track_id=track_id) for _, track_id, xy in tracks],
    )


def status(t, state, replans=0, reason='', **figures):
    msg = robot_status_to_msg(
        RobotStatus(state=state, stamp=t, replans=replans, reason=reason, position=(1.0, 2.0))
    )
    for key, value in figures.items():
        setattr(msg, key, value)
    return msg


def server_stats(requests):
    return ServerStats(requests=requests, watch_requests=requests // 4, forwards=2 * requests)


def path(t, points):
    msg = PathMsg(header=Header(stamp=genpy.Time.from_sec(t), frame_id='map'))
    for x, y in points:
        pose = PoseStamped()
        pose.pose.position.x, pose.pose.position.y = x, y
        msg.poses.append(pose)
    return msg


def grid_map(value):
    msg = OccupancyGrid()
    msg.info.width, msg.info.height, msg.info.resolution = 4, 3, 0.5
    msg.data = [value] * 12
    return msg


def registry():
    square = Polygon([Point32(x, y, 0.0) for x, y in ((0, 0), (2, 0), (2, 2), (0, 2))])
    service = '/vs1/detect_object_boundary'
    entry = VisionSystemEntry(service_name=service, provider='/vs1', field_of_view=square)
    return Registry(vision_systems=[entry])


def stats(requests, **figures):
    counters = {'requests': requests, 'callbacks': requests // 2, **figures}
    return stats_to_msg(counters, {'colour:1': requests}, stamp=1.0)


def a_run():
    """(topic, message, seen live) of a run as a bag holds it: the bag recorder started first, so
    it has what the live recorder missed before it subscribed, and what came after its final sample."""
    drvs = [cpu('/drvs', 1.0, 2.0)]
    return [
        ('/robot/status', status(1.0, 'localising'), False),
        ('/world_sim/ground_truth', truth(0.5, 1.0, 2.0), False),
        ('/vs1/stats', stats(1), False),
        ('/drvs/registry', registry(), True),
        ('/world_sim/ground_truth', truth(0.6, 1.0, 2.0), True),
        ('/vs1/stats', stats(2), True),
        ('/robot/status', status(2.0, 'localising'), True),
        ('/scenario_recorder/samples', sample(2.0, entries=[cpu('/drvs', 1.0, 1.5, end=102.0)]), True),
        ('/robot/path', path(2.5, [(1.0, 2.0), (5.0, 3.0)]), True),
        ('/robot/status', status(3.0, 'moving'), True),
        ('/world_sim/ground_truth', truth(3.0, 2.0, 2.5, travelled=1.125), True),
        ('/robot/map', grid_map(100), True),
        ('/robot/status', status(4.0, 'moving', replans=1), True),
        ('/robot/path', path(4.0, [(2.0, 2.5), (5.0, 3.0)]), True),
        ('/world_sim/ground_truth', truth(4.5, 5.0, 3.0, contacts=1, travelled=4.25), True),
        ('/robot/status', status(5.5, 'arrived', replans=1), True),
        ('/vs2/stats', stats(7), True),
        ('/scenario_recorder/samples', sample(2.0, final=True, entries=drvs), True),
        ('/vs1/stats', stats(9), False),
        ('/robot/status', status(6.0, 'failed'), False),
        ('/world_sim/ground_truth', truth(6.0, 9.0, 9.0, contacts=3), False),
    ]


def write_bag(path, messages):
    with rosbag.Bag(str(path), 'w') as bag:
        for i, (topic, msg) in enumerate(messages):
            bag.write(topic, msg, t=genpy.Time.from_sec(1000.0 + i * 0.1))
    return path


def live_and_from_a_bag(tmp_path, world, run):
    """The summary the live recorder writes for ``run`` (what it saw), the recorder, and the bag
    of the whole run."""
    live = RunRecorder(load_world(world))
    handlers = {topic: handler for topic, (_, handler) in live.topics().items()}
    handlers['/scenario_recorder/samples'] = live.on_sample
    for topic, msg, seen in run:
        if seen:
            handlers[topic](msg)
    assert live.closed
    live_summary = write_report(live.record, tmp_path / 'live')
    bag = write_bag(tmp_path / 'run.bag', [(topic, msg) for topic, msg, _ in run])

    assert regenerate(bag, tmp_path / 'again') == live_summary
    assert json.loads((tmp_path / 'again' / 'summary.json').read_text()) == live_summary
    assert (tmp_path / 'again' / 'run.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    return live_summary, live, bag


def test_a_bag_of_the_run_gives_the_summary_the_live_recorder_wrote(tmp_path):
    live_summary, live, bag = live_and_from_a_bag(tmp_path, WORLD, a_run())
    # From the first status the live recorder saw (its samples say which) to arrival.
    assert live_summary['elapsed'] == 3.5
    assert (live_summary['reached'], live_summary['state'], live_summary['replans']) == (True, 'arrived', 1)
    assert live_summary['collisions'] == 1
    assert live_summary['driven_length'] == 4.25  # world_sim's odometer
    assert live_summary['vision_systems']['vs1']['requests'] == 2  # not 9: that came after the end
    assert live_summary['vision_systems']['vs2']['callbacks'] == 3
    assert live_summary['cpu'] == {'/drvs': {'seconds': 2.0, 'percent': 25.0}}
    replayed = read_bag(bag).record
    robot, live_robot = replayed.robots['robot'], live.record.robots['robot']
    assert [plan for _, plan in robot.plans] == [plan for _, plan in live_robot.plans]
    assert replayed.fields_of_view == live.record.fields_of_view
    assert (replayed.grid == live.record.grid).all()


FLEET_WORLD = """
floor: {size: [6.0, 4.0]}
robots:
  - {name: robot1, position: [1.0, 3.0], size: [0.3, 0.3, 0.2], colour: [0, 200, 0], speed: 0.4,
     station: {position: [5.0, 1.0], size: [0.4, 0.3, 0.1], colour: [0, 0, 220]},
     colour_models: {self: "colour:0,150,0,80,255,80", station: "colour:0,0,150,80,80,255"}}
  - {name: robot2, position: [1.0, 1.0], size: [0.3, 0.3, 0.2], colour: [200, 200, 0], speed: 0.4,
     station: {position: [5.0, 3.0], size: [0.4, 0.3, 0.1], colour: [0, 200, 200]},
     colour_models: {self: "colour:150,150,0,255,255,80", station: "colour:0,150,150,80,255,255"}}
vision_systems:
  - {name: vs1, position: [3.0, 2.0, 4.0], fov_deg: 60}
colour_models:
  robot: "colour:0,150,0,255,255,80"
  obstacle: "colour:40,40,40,90,90,90"
  human: "colour:150,0,0,255,80,80"
"""


def a_fleet_run(world):
    """(topic, message, seen live) of a run of two robots: robot1 arrives, robot2 fails."""

    def at(t, one, two, contacts=(0, 0), touching=None):
        travelled = math.dist((1.0, 3.0), one), 0.0  # robot1 drives, robot2 stays
        return fleet_truth(
            t,
            {'robot1': (*one, contacts[0], travelled[0]), 'robot2': (*two, contacts[1], travelled[1])},
            touching,
        )

    robots = 'colour:0,150,0,255,255,80'  # the world's robot model
    return [
        ('/robot1/status', status(1.0, 'localising'), False),
        ('/drvs/stats', server_stats(2), False),
        ('/drvs/objects', tracked(0.8, [(robots, 9, (3.0, 3.0))]), False),  # before the first sample
        ('/world_sim/ground_truth', at(0.5, (1.0, 3.0), (1.0, 1.0)), False),
        ('/drvs/registry', registry(), True),
        ('/world_sim/ground_truth', at(1.5, (1.0, 3.0), (1.0, 1.0)), True),
        ('/robot1/status', status(2.0, 'localising'), True),
        ('/robot2/status', status(2.5, 'localising'), True),
        # The tracks counted: stamped from the first sample to the final one less a second.
        ('/scenario_recorder/samples', sample(2.0, world=world, stamp=1.9), True),
        ('/world_sim/poses', poses(1.5, {'robot1': (1.0, 3.0), 'robot2': (1.0, 1.0), 'other': (0, 0)}), True),
        ('/drvs/objects', tracked(2.0, [(robots, 1, (1.02, 3.0)), (robots, 2, (1.0, 1.0))]), True),
        ('/world_sim/ground_truth', at(3.0, (2.0, 3.0), (1.0, 1.0)), True),
        ('/world_sim/poses', poses(3.0, {'robot1': (2.0, 3.0), 'robot2': (1.0, 1.0)}), True),
        (
            '/drvs/objects',
            tracked(3.0, [(robots, 1, (2.0, 3.03)), (robots, 2, (1.0, 1.0)), (robots, 3, (1.1, 1.0))]),
            True,
        ),
        ('/robot1/path', path(3.0, [(1.0, 3.0), (5.0, 1.0)]), True),
        ('/robot2/path', path(3.0, [(1.0, 1.0), (5.0, 3.0)]), True),
        ('/robot1/map', grid_map(99), True),
        ('/robot2/map', grid_map(100), True),
        ('/robot1/status', status(4.0, 'moving', replans=1, requests=5, watch_calls=5), True),
        ('/robot1/path', path(4.0, [(2.0, 3.0), (5.0, 1.0)]), True),
        ('/world_sim/ground_truth', at(4.5, (4.0, 3.0), (1.0, 1.0), (0, 1), {'robot2': ['box']}), True),
        ('/world_sim/ground_truth', at(5.0, (5.0, 3.0), (1.0, 1.0), contacts=(0, 2)), True),
        ('/robot1/status', status(6.0, 'arrived', 1, '', requests=6, watch_calls=6, callbacks=30), True),
        ('/robot2/status', status(7.5, 'failed', 0, 'no route', callbacks=4, callback_bytes=999), True),
        ('/robot2/status', status(8.5, 'failed', 0, 'no route', callbacks=4, callback_bytes=999), True),
        ('/drvs/stats', server_stats(12), True),
        ('/vs1/stats', stats(3, watch_calls=11, watch_evaluations=40, renders=20), True),
        ('/scenario_recorder/samples', sample(2.0, True, world=world, wall_seconds=11.0, stamp=5.0), True),
        ('/drvs/stats', server_stats(99), False),
        ('/robot1/status', status(9.0, 'arrived', 1, '', requests=60), False),
        ('/drvs/objects', tracked(9.0, [(robots, 7, (2.0, 2.0))]), False),
    ]


def test_a_bag_of_a_fleet_run_gives_a_row_per_robot_and_the_figures(tmp_path):
    world = tmp_path / 'fleet.yaml'
    world.write_text(FLEET_WORLD)
    summary, live, _ = live_and_from_a_bag(tmp_path, world, a_fleet_run(world))
    rows = {row['name']: row for row in summary['robots']}
    assert list(rows) == ['robot1', 'robot2']
    one, two = rows['robot1'], rows['robot2']
    # Elapsed from the run's first status (the sample's) to arrival, or failure: later statuses
    # of a robot that is done do not count.
    assert (one['reached'], one['elapsed'], one['arrival'], one['replans']) == (True, 4.0, 4.0, 1)
    assert (two['reached'], two['elapsed'], two['arrival'], two['state'], two['reason']) == (
        False,
        5.5,
        None,
        'failed',
        'no route',
    )
    assert (one['requests'], one['watch_calls'], one['callbacks'], one['collisions']) == (6, 6, 30, 0)
    assert (two['callbacks'], two['callback_bytes'], two['collisions']) == (4, 999, 2)
    assert (one['driven_length'], two['driven_length']) == (pytest.approx(4.0), 0.0)
    assert (summary['reached'], summary['elapsed'], summary['replans'], summary['collisions']) == (
        False,
        5.5,
        1,
        2,
    )
    # Where it touched what, as far as the ground truths the recorder saw tell.
    assert two['collided'] == (
        "robot2 collided 2 times (box at (1.0, 1.0), ...): a collision fails a blind robot's mission"
    )
    assert (one['collided'], summary['success']) == ('', False)
    assert summary['reason'] == f"robot2 did not reach its station (failed: no route); {two['collided']}"
    assert summary['server']['requests'] == 12  # not 99: that came after the end
    assert (summary['server']['watch_requests'], summary['server']['forwards']) == (3, 24)
    vs1 = summary['vision_systems']['vs1']
    assert (vs1['watch_calls'], vs1['watch_evaluations'], vs1['renders']) == (11, 40, 20)
    assert (summary['wall_seconds'], summary['real_time_factor']) == (11.0, 1.0)
    assert (live.record.grid == 100).all()  # both robots' maps in one
    assert [len(live.record.robots[name].plans) for name in ('robot1', 'robot2')] == [2, 1]
    # The fused tracks against ground truth interpolated to their stamps: robot1 at (1.33, 3.0) at 2 s.
    tracking = summary['tracking']
    assert (tracking['measured'], tracking['periods'], tracking['span']) == (True, 2, 1.0)
    (robots,) = tracking['algorithms']
    assert (robots['bodies'], robots['matches'], robots['duplicates'], robots['switches']) == (
        ['robot1', 'robot2'],
        4,
        1,
        0,
    )
    assert robots['position_error_mean'] == pytest.approx((0.313 + 0.03) / 4, abs=1e-3)


def test_the_progress_line_of_a_fleet_counts_the_robots_by_state(tmp_path):
    world = tmp_path / 'fleet.yaml'
    world.write_text(FLEET_WORLD)
    recorder = RunRecorder(load_world(world))
    assert recorder.status_line() == 'state starting 2 | arrived 0 of 2 | replans 0 | collisions 0'
    recorder.on_status(status(1.0, 'moving', replans=2), robot='robot1')
    recorder.on_status(status(1.0, 'arrived'), robot='robot2')
    assert recorder.status_line() == 'state arrived 1, moving 1 | arrived 1 of 2 | replans 2 | collisions 0'


# -- drvs_report's refusals ------------------------------------------------------------------------------
def drvs_report(*args):
    return subprocess.run(
        [sys.executable, str(REPO / 'nodes' / 'drvs_report'), *map(str, args)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def refusal(tmp_path, case):
    if case == 'missing':
        return tmp_path / 'run.bag', 'no such file'
    if case == 'not a bag':
        (tmp_path / 'run.bag').write_text('hello\n')
        return tmp_path / 'run.bag', None
    if case == 'unindexed':  # what a recording killed before it closed its bag leaves
        whole = write_bag(tmp_path / 'whole.bag', [('/chatter', String(data='x' * 100))] * 50).read_bytes()
        (tmp_path / 'run.bag').write_bytes(whole[: len(whole) // 2])
        return tmp_path / 'run.bag', 'not indexed (its recording did not stop cleanly): rosbag reindex it'
    if case == 'no samples':
        write_bag(tmp_path / 'run.bag', [('/chatter', String(data='hello'))])
        message = 'no drvs/RecorderSample messages: not a run recorded by run_scenario.sh --record'
        return tmp_path / 'run.bag', message
    if case == 'world gone':
        world = tmp_path / 'world.yaml'
        world.write_text(WORLD.read_text())
        gone = sample(0.0, final=True)
        gone.world = str(world)
        write_bag(tmp_path / 'run.bag', [('/scenario_recorder/samples', gone)])
        world.unlink()
        error = f'the world of the run: {world}: cannot read the world file: No such file or directory'
        return tmp_path / 'run.bag', error
    raise AssertionError(case)


@pytest.mark.parametrize('case', ['missing', 'not a bag', 'unindexed', 'no samples', 'world gone'])
def test_drvs_report_refuses_in_one_line_with_exit_2(tmp_path, case):
    bag, message = refusal(tmp_path, case)
    result = drvs_report(bag, '--out', tmp_path / 'out')
    assert result.returncode == 2
    assert result.stdout == ''
    assert len(result.stderr.splitlines()) == 1, result.stderr
    if message is None:
        assert result.stderr.startswith(f'drvs_report: {bag}: not a readable bag: '), result.stderr
    else:
        assert result.stderr == f'drvs_report: {bag}: {message}\n'
    assert not (tmp_path / 'out').exists()


# -- live: a recorded scenario ---------------------------------------------------------------------------
def test_a_recorded_scenario_replays_and_regenerates_its_summary(ros: RosHarness, scenario_run):
    run = scenario_run('recorded')  # worlds/localisation.yaml --record (test/scenarios/conftest.py)
    code, out = run.wait(), run.out
    logs = run.logs(2000)
    assert code == 0, logs
    assert not (out / 'run.bag.active').exists(), logs
    both = {'/vs1/detect_object_boundary', '/vs2/detect_object_boundary'}
    with rosbag.Bag(str(out / 'run.bag')) as bag:  # opens only a closed, indexed bag
        counts = {topic: info.message_count for topic, info in bag.get_type_and_topic_info().topics.items()}
        finals = [msg.final for _, msg, _ in bag.read_messages(topics=['/scenario_recorder/samples'])]
        start = bag.get_start_time()
        registries = [
            (time.to_sec() - start, {entry.service_name for entry in msg.vision_systems})
            for _, msg, time in bag.read_messages(topics=['/drvs/registry'])
        ]
    assert [topic for topic in REQUIRED_TOPICS if not counts.get(topic)] == [], counts
    assert finals[-1] is True and finals.count(True) == 1, finals

    again = ros.root / 'again'
    result = drvs_report(out / 'run.bag', '--out', again)
    assert result.returncode == 0, result.stderr
    live = json.loads((out / 'summary.json').read_text())
    assert json.loads((again / 'summary.json').read_text()) == live
    assert live['reached'] is True and live['cpu'] and live['elapsed'] > 0
    # This is also `make test`'s run of case study 4.1 (test_scenarios' own run of it is slow):
    # no contact, nearly the straight line from start to station, both cameras calling back.
    assert live['collisions'] == 0
    assert live['driven_length'] == pytest.approx(live['best_length'], rel=0.15)
    assert all(live['vision_systems'][camera]['callbacks'] > 0 for camera in ('vs1', 'vs2')), live
    assert (again / 'run.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'

    # rosbag play brings the latched registry and the cameras' static tf back, for RViz. The
    # bag ends with the cameras unregistering at shutdown: play it up to the registry with both.
    first = next(i for i, (_, names) in enumerate(registries) if names == both)
    after = registries[first + 1][0] if first + 1 < len(registries) else registries[first][0] + 2.0
    duration = registries[first][0] + min((after - registries[first][0]) / 2, 1.0)
    play = ['rosbag', 'play', '--keep-alive', '--rate', '20', '--duration', f'{duration:.3f}']
    ros.spawn('rosbag_play', [*play, str(out / 'run.bag')])

    def registry_of_both():
        return {entry['service_name'] for entry in echo(ros, '/drvs/registry')['vision_systems']} == both

    wait_for(registry_of_both, 30.0, 'the replayed /drvs/registry with vs1 and vs2', on_timeout=ros.describe)
    assert echo(ros, '/tf_static')['transforms'][0]['header']['frame_id'] == 'map'
