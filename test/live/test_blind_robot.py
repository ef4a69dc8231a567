"""The blind robot node against a scripted fake DRVS (test/nodes/fake_drvs.py): no rendering."""

import json
import math

import pytest
import yaml

from drvs.testing import read_json_lines, wait_for

pytestmark = pytest.mark.shared_master  # see test/conftest.py

FLOOR = (3.0, 3.0)
STATION = (2.6, 1.5)
START = (0.4, 1.5)
NEAR = (1.8, 1.5)  # a start 0.8 m from the station, for tests that are not about the drive
MODELS = {
    'self': 'colour:0,150,0,80,255,80',
    'station': 'colour:0,0,150,80,80,255',
    'obstacle': 'colour:40,40,40,90,90,90',
    'human': 'colour:150,0,0,255,80,80',
}


def write_world(root, objects, start=START):
    world = {
        'floor': {'size': list(FLOOR)},
        'robot': {'position': list(start), 'size': [0.3, 0.3, 0.2], 'colour': [0, 200, 0], 'speed': 0.6},
        'station': {'position': list(STATION), 'size': [0.4, 0.3, 0.1], 'colour': [0, 0, 220]},
        'objects': objects,
        'vision_systems': [{'name': 'vs1', 'position': [1.5, 1.5, 3.0], 'fov_deg': 60}],
        'colour_models': MODELS,
    }
    path = root / 'world.yaml'
    path.write_text(yaml.safe_dump(world))
    return path


def start(ros, world, fake_params=None, robot_params=None):
    output = ros.root / 'fake_drvs.jsonl'
    fake = ros.start_node(
        'test/nodes/fake_drvs.py',
        name='drvs',
        params={'world': world, 'output': output, **(fake_params or {})},
    )
    ros.wait_for_service('/drvs/detect_object_boundary', node=fake)
    robot = ros.start_node(
        'nodes/blind_robot',
        name='robot',
        params={'world': world, 'once': True, **(robot_params or {})},
    )
    ros.wait_for_service('/robot/callback_coordinates', node=robot)
    return fake, robot, output


def wait_exit(ros, node, timeout):
    wait_for(lambda: not node.running(), timeout, f'{node.name} to exit', on_timeout=ros.describe)
    return node.process.returncode


def final_truth(ros, output, state):
    """The fake's last record of the truth once it shows the robot's status in ``state``."""

    def last():
        truths = [e for e in read_json_lines(output) if e['kind'] == 'truth']
        status = truths[-1]['status'] if truths else None
        return truths[-1] if status and status['state'] == state else None

    return wait_for(last, 10, f'the fake to record the final status ({state})', on_timeout=ros.describe)


def calls(output):
    """The robot's calls to the fake DRVS as it recorded them: one-shot requests and watch calls."""
    return [e for e in read_json_lines(output) if e['kind'] in ('request', 'watch')]


# The polling variant is long and slow-marked: polling re-plans are checked in the default suite by the
# whole runs that poll (test_scenarios' tags run, test_fleet's crossing with polling).
@pytest.mark.parametrize('mode', ['watch', pytest.param('poll', marks=pytest.mark.slow)])
def test_reaches_the_station_and_replans_around_an_obstacle_that_appears(ros, mode):
    world = write_world(
        ros.root,
        [
            {'name': 'box1', 'position': [1.3, 0.8], 'size': [0.3, 0.3, 0.5], 'colour': [60, 60, 60]},
            {'name': 'late', 'position': [1.8, 1.5], 'size': [0.3, 0.6, 0.5], 'colour': [60, 60, 60]},
            {
                'name': 'walker',
                'kind': 'human',
                'position': [1.0, 2.7],
                'size': [0.2, 0.2, 1.7],
                'colour': [220, 0, 0],
                'waypoints': [[0.6, 2.7], [1.4, 2.7]],
                'speed': 0.3,
            },
        ],
    )
    fake_params = {'hidden': 'late', 'appear_distance': 0.8}
    fake, robot, output = start(ros, world, fake_params=fake_params, robot_params={'requests': mode})
    # the robot's only inputs are DRVS callbacks: it subscribes to nothing at all
    assert ros.master.subscriptions_of('/robot') == []
    code = wait_exit(ros, robot, 60)
    assert code == 0, ros.describe()
    assert 'arrived at the station' in robot.log(200)
    truth = final_truth(ros, output, 'arrived')
    events = read_json_lines(output)
    assert [e['name'] for e in events if e['kind'] == 'appear'] == ['late']
    assert math.dist(truth['robot'], STATION) <= 0.1 + 0.05  # tolerance + what happened after the last fix
    assert truth['contacts'] == 0
    status = truth['status']
    assert status['replans'] >= 1
    assert status['refused'] == {}
    assert status['callback_bytes'] > 100 * status['callbacks'] > 0  # a callback carries outlines

    sent = calls(output)
    assert {e['kind'] for e in sent} == {'watch' if mode == 'watch' else 'request'}
    assert {e['role'] for e in sent} == {'self', 'station', 'obstacle', 'human'}
    whole = [0.0, 0.0, *FLOOR]
    for role in ('self', 'station'):  # the whole floor until found, then around it
        rois = [e['roi'] for e in sent if e['role'] == role]
        assert rois[0] == whole and rois[-1] != whole, (role, rois)
    station_rois = [e['roi'] for e in sent if e['role'] == 'station']
    found = next(i for i, roi in enumerate(station_rois) if roi != whole)
    for roi in station_rois[found:]:  # its box plus a metre
        assert roi == pytest.approx(
            [STATION[0] - 1.2, STATION[1] - 1.15, FLOOR[0], STATION[1] + 1.15], abs=0.01
        )
    obstacle_rois = [e['roi'] for e in sent if e['role'] in ('obstacle', 'human')]
    assert obstacle_rois
    for roi in obstacle_rois:  # the robot-station box plus the margin (0.75 m), never the whole floor
        assert roi != whole
        assert 0.0 <= roi[0] <= STATION[0] - 0.75
        assert roi[2] == pytest.approx(FLOOR[0])  # the station's x plus the margin, clipped
        assert 0.0 <= roi[1] <= STATION[1] - 0.75 + 1e-9
        assert STATION[1] + 0.75 - 1e-9 <= roi[3] <= FLOOR[1]
        # (Both also reach 1.5 ~roi_margin round the robot and over its plan's corridor, so they
        # may touch the floor's edges: never the whole floor, asserted above.)
    if mode == 'poll':
        assert status['callbacks'] > status['requests'] // 2  # twice-sent answers were all taken in
        assert (status['watch_calls'], status['watches']) == (0, 0)
        return
    assert status['watch_calls'] == status['requests'] == len(sent) - 4  # then it cancelled its 4 watches
    assert status['watches'] == 4
    assert all(e['duration'] == 20.0 for e in sent[:-4])
    assert sorted((e['role'], e['duration']) for e in sent[-4:]) == [
        ('human', 0.0),
        ('obstacle', 0.0),
        ('self', 0.0),
        ('station', 0.0),
    ]
    assert {e['request_id'] for e in sent} == {
        '/robot/self',
        '/robot/station',
        '/robot/obstacle',
        '/robot/human',
    }
    periods = {e['role']: e['period'] for e in sent}
    # The control period for itself, ~fused_period for a person (fused: the fusion stage predicts
    # the track between), ~obstacle_period and ~station_period.
    assert periods == pytest.approx({'self': 0.2, 'station': 2.0, 'obstacle': 0.5, 'human': 0.5})


@pytest.mark.parametrize(
    'status, name, mode',
    # busy-poll is slow-marked: the poll schedule's retries after retry_after are unit-tested
    # (test/unit/robot/test_poll_schedule.py) and the watch variants run here by default.
    [(2, 'BUSY', 'watch'), (9, 'status 9', 'watch'), pytest.param(2, 'BUSY', 'poll', marks=pytest.mark.slow)],
    ids=['busy', 'unknown-status', 'busy-poll'],
)
def test_temporary_refusals_are_retried_after_retry_after_and_the_robot_arrives(ros, status, name, mode):
    world = write_world(ros.root, [], start=NEAR)
    refusals = 6
    fake_params = {'refuse_first': refusals, 'refuse_status': status, 'refuse_retry_after': 0.3}
    fake_params['refuse_message'] = 'busy: try again later'
    _, robot, output = start(ros, world, fake_params=fake_params, robot_params={'requests': mode})
    assert wait_exit(ros, robot, 60) == 0, ros.describe()
    assert 'arrived at the station' in robot.log(200)
    truth = final_truth(ros, output, 'arrived')
    assert truth['status']['refused'] == {name: refusals}
    assert math.dist(truth['robot'], STATION) <= 0.1 + 0.05

    requests = calls(output)
    assert [e['status'] for e in requests[:refusals]] == [name] * refusals
    assert {e['status'] for e in requests[refusals:]} == {'ACCEPTED'}
    for refused in requests[:refusals]:  # each role came back no earlier than retry_after
        later = [e for e in requests if e['role'] == refused['role'] and e['time'] > refused['time']]
        assert later and later[0]['time'] - refused['time'] >= 0.3, (refused, later[:1])
    warnings = robot.log(400).count('DRVS answered with unknown status 9; retrying it later')
    assert warnings == (1 if name == 'status 9' else 0)


def test_an_invalid_request_ends_the_mission_with_the_servers_message(ros):
    world = write_world(ros.root, [])
    message = 'region_of_interest: refused by the fake DRVS'
    fake_params = {
        'refuse_first': 1000,
        'refuse_status': 1,
        'refuse_message': json.dumps(message),  # _param:= values are YAML: quote the colon
    }
    _, robot, output = start(ros, world, fake_params=fake_params)
    assert wait_exit(ros, robot, 30) == 1
    reason = f'DRVS refused the self request: {message}'
    assert reason in robot.log(200)
    truth = final_truth(ros, output, 'failed')
    assert truth['status']['reason'] == reason
    assert truth['status']['refused'] == {'INVALID': 1}
    # never asked again, and nothing to cancel: no watch was granted
    assert [(e['role'], e['status']) for e in calls(output)] == [('self', 'INVALID')]


def test_a_slow_server_never_holds_up_the_control_loop(ros):
    """Acks take 1 s, five control periods: ticks (cmd_vel, status) keep coming at about ~rate."""
    world = write_world(ros.root, [])
    rate, window = 5.0, 5.0
    _, robot, output = start(
        ros,
        world,
        fake_params={'ack_delay': 1.0},
        robot_params={
            'requests': 'poll',  # a call every tick: the most to wait for
            'rate': rate,
            'request_timeout': 3.0,
            'fix_timeout': 30.0,
            'once': False,
        },
    )

    def truths():
        return [e for e in read_json_lines(output) if e['kind'] == 'truth' and e['status']]

    first = wait_for(lambda: truths()[:1], 30, 'the robot to publish a status', on_timeout=ros.describe)[0]
    last = wait_for(
        lambda: [t for t in truths() if t['time'] >= first['time'] + window][:1],
        30,
        f'{window} s of the fake recording the robot',
        on_timeout=ros.describe,
    )[0]
    elapsed = last['time'] - first['time']
    requests = [
        e
        for e in read_json_lines(output)
        if e['kind'] == 'request' and first['time'] <= e['time'] <= last['time']
    ]
    assert 2 <= len(requests) <= elapsed / 1.0 + 1  # requests were slow: one ack a second at most
    # ...while the control loop kept its rate (at least half of it, on a shared machine).
    assert last['cmd_vels'] - first['cmd_vels'] >= 0.5 * rate * elapsed, (first, last)
    assert last['status']['stamp'] - first['status']['stamp'] >= 0.5 * elapsed
    assert last['status']['state'] not in ('localising', 'failed'), last['status']
    assert robot.running()


@pytest.mark.parametrize(
    'mode, failed',
    [
        (
            'watch',
            'DRVS watch /robot/self (new) failed: service /drvs/watch_object_boundary: unknown service',
        ),
        ('poll', 'DRVS request self-1 failed: service /drvs/detect_object_boundary: unknown service'),
    ],
    ids=['watch', 'poll'],
)
def test_without_drvs_the_robot_fails_by_its_own_deadline(ros, mode, failed):
    world = write_world(ros.root, [])
    params = {'world': world, 'once': True, 'fix_timeout': 2.0, 'requests': mode}
    robot = ros.start_node('nodes/blind_robot', name='robot', params=params)
    assert wait_exit(ros, robot, 30) == 1
    log = robot.log(200)
    assert failed in log
    assert 'blind robot failed: no fix of the robot for 2.0 s' in log


def test_no_vision_system_covering_the_robot_is_a_failure(ros):
    world = write_world(ros.root, [])
    _, robot, _ = start(ros, world, fake_params={'cameras': 0}, robot_params={'fix_timeout': 1.0})
    assert wait_exit(ros, robot, 30) == 1
    assert (
        'no vision system covers the robot: DRVS forwarded its self request to none for 1.0 s'
        in robot.log(200)
    )


def test_an_unreachable_station_is_a_failure(ros):
    wall = {'name': 'wall', 'position': [1.8, 1.5], 'size': [0.1, 3.0, 0.5], 'colour': [60, 60, 60]}
    world = write_world(ros.root, [wall])
    _, robot, _ = start(ros, world, robot_params={'unreachable_timeout': 1.0})
    assert wait_exit(ros, robot, 30) == 1
    assert 'goal unreachable: no way from' in robot.log(200)


def test_ctrl_c_stops_the_robot_cleanly_and_cancels_its_watches(ros):
    world = write_world(ros.root, [])
    _, robot, output = start(ros, world, robot_params={'once': False, 'fix_timeout': 30.0})

    def standing():
        return {e['role'] for e in calls(output) if e['duration'] > 0 and e['status'] == 'ACCEPTED'}

    wait_for(lambda: len(standing()) == 4, 30, 'the robot to watch all four roles', on_timeout=ros.describe)
    assert robot.interrupt() == 0, robot.describe()
    cancels = [e['role'] for e in calls(output) if e['duration'] == 0]
    assert sorted(cancels) == ['human', 'obstacle', 'self', 'station']


@pytest.mark.parametrize(
    'params, message',
    [
        ({'rate': 0}, '~rate: must be positive, got 0'),
        ({'roi_margin': -1.0}, '~roi_margin: must not be negative, got -1.0'),
        ({'requests': 'push'}, "~requests: must be one of watch, poll, got 'push'"),
        ({'world': '/nonexistent.yaml'}, '/nonexistent.yaml: cannot read the world file'),
    ],
)
def test_bad_parameters_are_refused_with_the_reason(ros, params, message):
    world = write_world(ros.root, [])
    robot = ros.start_node('nodes/blind_robot', name='robot', params={'world': world, **params})
    assert wait_exit(ros, robot, 30) == 2
    assert message in robot.log()


@pytest.mark.parametrize('mode', ['watch', pytest.param('poll', marks=pytest.mark.slow)])
def test_a_server_that_is_not_there_sends_the_robot_to_the_next_of_its_servers(ros, mode):
    """~servers (docs/registry.md, "Replicas"): the first is gone, one failed call moves it on for good."""
    world = write_world(ros.root, [], start=NEAR)
    robot_params = {'requests': mode, 'servers': ['/gone', '/drvs']}
    _, robot, output = start(ros, world, robot_params=robot_params)
    assert wait_exit(ros, robot, 60) == 0, ros.describe()
    status = final_truth(ros, output, 'arrived')['status']
    assert status['failed_requests'] == 1 and status['refused'] == {}, status
    assert {e['status'] for e in calls(output)} == {'ACCEPTED'}
