"""Recording a run: ``run_scenario.sh --record`` writes ``run.bag``, and ``drvs_report`` regenerates
the live recorder's summary from it.

Without a master: the recorder's core (:class:`drvs.ros.recorder.RunRecorder`) fed a run
live and the same run from a bag written here give the same summary; ``drvs_report``'s
refusals. Live: a recorded scenario, its bag, the regenerated report and ``rosbag play``.
"""

import json
import subprocess
import sys

import genpy
import pytest
import rosbag
from geometry_msgs.msg import Point32, Polygon, PoseStamped
from nav_msgs.msg import OccupancyGrid
from nav_msgs.msg import Path as PathMsg
from std_msgs.msg import Header, String

from drvs.msg import NodeCpu, RecorderSample, Registry, VisionSystemEntry
from drvs.report import write_report
from drvs.ros.bag_report import read_bag, regenerate
from drvs.ros.messages import robot_status_to_msg, stats_to_msg
from drvs.ros.recorder import RunRecorder, cpu_summary
from drvs.testing import RosHarness, wait_for
from drvs.testing.harness import REPO, echo
from drvs.testing.messages import round_trip
from drvs.world import load_world

WORLD = REPO / 'worlds' / 'localisation.yaml'
SCENARIO_TIMEOUT = 150
REQUIRED_TOPICS = (
    '/drvs/registry',
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


def sample(first_status, final=False, entries=()):
    return RecorderSample(
        header=Header(stamp=genpy.Time.from_sec(100.0)),
        world=str(WORLD),
        first_status=genpy.Time.from_sec(first_status) if first_status else genpy.Time(),
        final=final,
        cpu=list(entries),
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
def truth(t, x, y, contacts=0):
    return String(
        data=json.dumps({'time': t, 'robot': {'position': [x, y]}, 'contacts': contacts, 'objects': {}})
    )


def status(t, state, replans=0):
    return robot_status_to_msg({'state': state, 'stamp': t, 'replans': replans, 'position': [1.0, 2.0]})


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


def stats(requests):
    return stats_to_msg({'requests': requests, 'callbacks': requests // 2}, {'colour:1': requests}, stamp=1.0)


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
        ('/world_sim/ground_truth', truth(3.0, 2.0, 2.5), True),
        ('/robot/map', grid_map(100), True),
        ('/robot/status', status(4.0, 'moving', replans=1), True),
        ('/robot/path', path(4.0, [(2.0, 2.5), (5.0, 3.0)]), True),
        ('/world_sim/ground_truth', truth(4.5, 5.0, 3.0, contacts=1), True),
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


def test_a_bag_of_the_run_gives_the_summary_the_live_recorder_wrote(tmp_path):
    live = RunRecorder(load_world(WORLD))
    handlers = {topic: handler for topic, (_, handler) in live.topics().items()}
    handlers['/scenario_recorder/samples'] = live.on_sample
    for topic, msg, seen in a_run():
        if seen:
            handlers[topic](msg)
    assert live.closed
    live_summary = write_report(live.record, tmp_path / 'live')
    bag = write_bag(tmp_path / 'run.bag', [(topic, msg) for topic, msg, _ in a_run()])

    assert regenerate(bag, tmp_path / 'again') == live_summary
    assert json.loads((tmp_path / 'again' / 'summary.json').read_text()) == live_summary
    assert (tmp_path / 'again' / 'run.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    # From the first status the live recorder saw (its samples say which) to arrival.
    assert live_summary['elapsed'] == 3.5
    assert (live_summary['reached'], live_summary['state'], live_summary['replans']) == (True, 'arrived', 1)
    assert live_summary['collisions'] == 1
    assert live_summary['driven_length'] == pytest.approx(1.118 + 3.041, abs=1e-3)
    assert live_summary['vision_systems']['vs1']['requests'] == 2  # not 9: that came after the end
    assert live_summary['vision_systems']['vs2']['callbacks'] == 3
    assert live_summary['cpu'] == {'/drvs': {'seconds': 2.0, 'percent': 25.0}}
    replayed = read_bag(bag).record
    assert [plan for _, plan in replayed.plans] == [plan for _, plan in live.record.plans]
    assert replayed.fields_of_view == live.record.fields_of_view
    assert (replayed.grid == live.record.grid).all()


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
def test_a_recorded_scenario_replays_and_regenerates_its_summary(ros: RosHarness):
    out = ros.root / 'out'
    argv = ['bash', 'scripts/run_scenario.sh', str(WORLD), '--external-master', '--record']
    runner = ros.spawn('run_scenario', [*argv, '--timeout', str(SCENARIO_TIMEOUT), '--out', str(out)])
    wait_for(lambda: not runner.running(), SCENARIO_TIMEOUT + 60, 'run_scenario.sh --record', interval=0.5)
    logs = runner.describe() + ''.join(
        f'\n--- {log.name} ---\n{log.read_text(errors="replace")[-2000:]}'
        for log in sorted(out.glob('*.log'))
    )
    assert runner.process.returncode == 0, logs
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
