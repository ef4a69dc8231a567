"""Health rules (drvs.common.health) and their publication on /diagnostics (drvs.ros.diagnostics)."""

import doctest
import sys
import textwrap

import pytest
import rospy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

from drvs.common import health
from drvs.common.health import ERROR, OK, WARN, Health, robot_health, server_health, vision_system_health
from drvs.ros.diagnostics import DiagnosticsPublisher, health_to_status, statuses_to_array
from drvs.testing.messages import round_trip

pytestmark = pytest.mark.shared_master  # see test/conftest.py


@pytest.mark.parametrize(
    ('ours', 'theirs'),
    [
        (health.OK, DiagnosticStatus.OK),
        (health.WARN, DiagnosticStatus.WARN),
        (health.ERROR, DiagnosticStatus.ERROR),
        (health.STALE, DiagnosticStatus.STALE),
    ],
)
def test_levels_equal_diagnostic_msgs(ours, theirs):
    assert ours == theirs


# -- the server ------------------------------------------------------------------------------------

SERVER = dict(
    registered=2,
    pending_forwards=10,
    max_pending=100,
    refusals_by_status={},
    refusals_recent={},
    rate_limited_callers=0,
    ejected=0,
)


@pytest.mark.parametrize(
    ('facts', 'level', 'message'),
    [
        ({}, OK, 'ok'),
        ({'pending_forwards': 80}, OK, 'ok'),  # 80 % is not more than 80 %
        ({'pending_forwards': 81}, WARN, 'forward queue 81% full (81 of 100 pending)'),
        ({'pending_forwards': 100}, ERROR, 'forward queue full: refusing BUSY (100 of 100 pending)'),
        ({'registered': 0}, WARN, 'no vision system registered'),
        ({'refusals_recent': {'BUSY': 3}}, WARN, 'refused 3 BUSY in the last period'),
        (
            {'refusals_recent': {'BUSY': 3, 'RATE_LIMITED': 1, 'INVALID': 7}},
            WARN,
            'refused 3 BUSY, 1 RATE_LIMITED in the last period',
        ),
        ({'refusals_recent': {'INVALID': 7, 'UNSUPPORTED': 2, 'BUSY': 0}}, OK, 'ok'),  # callers' mistakes
        ({'refusals_by_status': {'BUSY': 40}}, OK, 'ok'),  # refused long ago, fine now
        ({'rate_limited_callers': 2}, OK, 'ok'),  # a value; the refusals tell the story
        ({'ejected': 1}, WARN, '1 vision system ejected after failed forwards'),
        ({'ejected': 2}, WARN, '2 vision systems ejected after failed forwards'),
        (
            {
                'registry': 'postgresql://drvs@db:5432/drvs',
                'registry_problem': 'registry database unreachable',
            },
            ERROR,
            'registry database unreachable',
        ),
        (
            {'left_out': {'/cam3/detect_object_boundary': 'its outlines are 0.8 m from its neighbours'}},
            WARN,
            'left out of fusion: /cam3/detect_object_boundary: its outlines are 0.8 m from its neighbours',
        ),
        (
            {'registered': 0, 'pending_forwards': 100, 'refusals_recent': {'RATE_LIMITED': 5}},
            ERROR,
            'forward queue full: refusing BUSY (100 of 100 pending); no vision system registered; '
            'refused 5 RATE_LIMITED in the last period',
        ),
    ],
)
def test_server_rules(facts, level, message):
    verdict = server_health(**{**SERVER, **facts})
    assert (verdict.level, verdict.message) == (level, message)


def test_server_values_name_its_site():
    values = dict(server_health(**{**SERVER, 'site': 'b'}).values)
    assert values['site'] == 'b'


def test_server_values_name_every_refusal_status():
    verdict = server_health(
        **{**SERVER, 'refusals_by_status': {'BUSY': 4, 'WEIRD': 1}, 'refusals_recent': {'BUSY': 1}}
    )
    assert verdict.values == [
        ('registered vision systems', '2'),
        ('registry', 'memory'),
        ('site', '(the only one)'),
        ('pending forwards', '10'),
        ('max pending forwards', '100'),
        ('rate-limited callers', '0'),
        ('ejected vision systems', '0'),
        ('watches', '0'),
        ('fused tracks', '0'),
        ('left out of fusion', 'none'),
        ('refused INVALID (last period)', '0'),
        ('refused INVALID (since start)', '0'),
        ('refused BUSY (last period)', '1'),
        ('refused BUSY (since start)', '4'),
        ('refused RATE_LIMITED (last period)', '0'),
        ('refused RATE_LIMITED (since start)', '0'),
        ('refused UNAVAILABLE (last period)', '0'),
        ('refused UNAVAILABLE (since start)', '0'),
        ('refused UNSUPPORTED (last period)', '0'),
        ('refused UNSUPPORTED (since start)', '0'),
        ('refused WEIRD (last period)', '0'),
        ('refused WEIRD (since start)', '1'),
    ]


# -- a vision system -------------------------------------------------------------------------------

VISION = dict(
    registered=True,
    source='topic',
    frame_age=0.1,
    stale_after=2.0,
    queue_length=0,
    queue_size=10,
    callback_failures_recent=0,
    callbacks_recent=5,
    registration_status='',
    registration_error='',
)


@pytest.mark.parametrize(
    ('facts', 'level', 'message'),
    [
        ({}, OK, 'ok'),
        ({'frame_age': 2.0}, OK, 'ok'),
        ({'frame_age': 3.25}, ERROR, 'camera feed stale: last frame 3.2 s ago (stale after 2 s)'),
        ({'frame_age': None}, ERROR, 'no frame yet from the camera topic'),
        ({'frame_age': None, 'source': 'render'}, OK, 'ok'),  # renders on demand: never stale
        (
            {'registered': False, 'registration_status': 'INVALID', 'registration_error': 'algorithms: bad'},
            ERROR,
            'registration refused INVALID: algorithms: bad',
        ),
        (
            {'registered': False, 'registration_status': 'UNAVAILABLE', 'registration_error': 'ejected'},
            WARN,
            'not registered: refused UNAVAILABLE: ejected',
        ),
        ({'registered': False, 'registration_status': 'BUSY'}, WARN, 'not registered: refused BUSY'),
        (
            {'registered': False, 'registration_error': 'no answer from /drvs/register within 2 s'},
            WARN,
            'not registered: no answer from /drvs/register within 2 s',
        ),
        ({'registered': False}, WARN, 'not registered: no answer from the server yet'),
        ({'queue_length': 8}, OK, 'ok'),
        ({'queue_length': 9}, WARN, 'request queue 90% full (9 of 10)'),
        ({'queue_length': 50, 'queue_size': 0}, OK, 'ok'),  # unbounded: never nearly full
        ({'callback_failures_recent': 2}, WARN, '2 of 5 callbacks failed in the last period'),
        (
            {
                'frame_problems': [
                    'elevation: the depth image has no valid pixel (every one 0, NaN or infinite)'
                ]
            },
            WARN,
            'elevation: the depth image has no valid pixel (every one 0, NaN or infinite)',
        ),
        (
            {'registered': False, 'frame_age': 9.0, 'callback_failures_recent': 1, 'callbacks_recent': 1},
            ERROR,
            'camera feed stale: last frame 9.0 s ago (stale after 2 s); '
            'not registered: no answer from the server yet; 1 of 1 callbacks failed in the last period',
        ),
    ],
)
def test_vision_system_rules(facts, level, message):
    verdict = vision_system_health(**{**VISION, **facts})
    assert (verdict.level, verdict.message) == (level, message)


def test_vision_system_values():
    assert vision_system_health(**{**VISION, 'source': 'render', 'frame_age': None}).values == [
        ('registered', 'yes'),
        ('source', 'render'),
        ('frame age (s)', 'none'),
        ('stale after (s)', '2.00'),
        ('queue length', '0'),
        ('queue size', '10'),
        ('watches', '0'),
        ('callbacks (last period)', '5'),
        ('callback failures (last period)', '0'),
        ('last registration refusal', 'none'),
        ('last registration error', 'none'),
    ]


# -- a robot ---------------------------------------------------------------------------------------

ROBOT = dict(state='moving', reason='', fix_age=0.5, fix_timeout=5.0, coverage=True)


@pytest.mark.parametrize(
    ('facts', 'level', 'message'),
    [
        ({}, OK, 'ok'),
        ({'state': 'localising'}, OK, 'ok'),
        ({'state': 'arriving'}, OK, 'ok'),
        ({'state': 'arrived', 'fix_age': 60.0, 'coverage': False}, OK, 'ok'),  # not judged once arrived
        ({'state': 'failed', 'reason': 'no fix for 5.0 s'}, ERROR, 'failed: no fix for 5.0 s'),
        ({'state': 'failed'}, ERROR, 'failed'),
        ({'state': 'blocked', 'reason': 'no path to the station'}, WARN, 'blocked: no path to the station'),
        ({'state': 'blocked'}, WARN, 'blocked'),
        ({'fix_age': 2.5}, OK, 'ok'),
        ({'fix_age': 3.14}, WARN, 'last fix 3.1 s ago (fails after 5 s)'),
        ({'state': 'localising', 'fix_age': None}, WARN, 'no fix yet'),
        ({'coverage': False}, WARN, 'no vision system covers the robot'),
        (
            {'state': 'blocked', 'reason': 'a human', 'fix_age': 4.0, 'coverage': False},
            WARN,
            'blocked: a human; last fix 4.0 s ago (fails after 5 s); no vision system covers the robot',
        ),
    ],
)
def test_robot_rules(facts, level, message):
    verdict = robot_health(**{**ROBOT, **facts})
    assert (verdict.level, verdict.message) == (level, message)


def test_robot_values():
    assert robot_health(**ROBOT).values == [
        ('state', 'moving'),
        ('reason', 'none'),
        ('fix age (s)', '0.50'),
        ('fix timeout (s)', '5.00'),
        ('covered', 'yes'),
    ]


def test_a_client_of_several_servers_shows_the_one_in_use_and_its_moves():
    """~servers (docs/registry.md, "Replicas"): values, no rule."""
    server = {'server': '/drvs_b/watch_object_boundary', 'server_moves': 1}
    verdict = robot_health(**ROBOT, **server)
    assert verdict.level == OK and verdict.values[-2:] == [
        ('DRVS server', '/drvs_b/watch_object_boundary'),
        ('server moves', '1'),
    ]
    assert vision_system_health(**VISION, server='/drvs/register_vision_service').values[-2:] == [
        ('DRVS server', '/drvs/register_vision_service'),
        ('server moves', '0'),
    ]


# -- bad input -------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ('make', 'error', 'message'),
    [
        (
            lambda: Health(5, 'x'),
            ValueError,
            'level: must be one of 0 (OK), 1 (WARN), 2 (ERROR), 3 (STALE), got 5',
        ),
        (
            lambda: Health(OK, 'ok', [('queue', 3)]),
            TypeError,
            "values: key and value must be str, got str 'queue': int 3",
        ),
        (
            lambda: server_health(**{**SERVER, 'max_pending': 0}),
            ValueError,
            'max_pending: must be positive, got 0',
        ),
        (
            lambda: vision_system_health(**{**VISION, 'stale_after': 0.0}),
            ValueError,
            'stale_after: must be positive, got 0.0',
        ),
        (
            lambda: robot_health(**{**ROBOT, 'fix_timeout': -1.0}),
            ValueError,
            'fix_timeout: must be positive, got -1.0',
        ),
    ],
)
def test_bad_input_is_refused_naming_the_field(make, error, message):
    with pytest.raises(error) as raised:
        make()
    assert str(raised.value) == message


# -- conversion ------------------------------------------------------------------------------------


def test_health_to_status_round_trips():
    verdict = Health(
        WARN, 'request queue 90% full (9 of 10)', [('queue length', '9'), ('frame age (s)', '0.10')]
    )
    status = round_trip(health_to_status(verdict, 'drvs: /cam1', 'cam1'))
    assert (status.level, status.name, status.message, status.hardware_id) == (
        DiagnosticStatus.WARN,
        'drvs: /cam1',
        'request queue 90% full (9 of 10)',
        'cam1',
    )
    assert [(pair.key, pair.value) for pair in status.values] == verdict.values


def test_array_round_trips_with_its_stamp():
    statuses = [health_to_status(Health(ERROR, 'no frame yet from the camera topic'), 'drvs: /cam1', 'cam1')]
    array = round_trip(statuses_to_array(statuses, rospy.Time(12, 345)))
    assert isinstance(array, DiagnosticArray)
    assert array.header.stamp == rospy.Time(12, 345)
    assert [(s.level, s.message) for s in array.status] == [(ERROR, 'no frame yet from the camera topic')]


def test_a_failing_sample_becomes_an_error_status_and_is_logged_once(caplog):
    calls = []

    def sample():
        calls.append(1)
        if len(calls) <= 2:
            raise KeyError('queue')
        return Health(OK, 'ok')

    publisher = DiagnosticsPublisher('drvs: /cam1', 'cam1', sample)
    with caplog.at_level('INFO', logger='rosout.drvs.ros.diagnostics'):
        first, second, third = publisher.status(), publisher.status(), publisher.status()
    assert (first.level, first.message) == (ERROR, "health check failed: KeyError: 'queue'")
    assert (second.level, second.message) == (ERROR, "health check failed: KeyError: 'queue'")
    assert (third.level, third.message) == (OK, 'ok')
    messages = [record.getMessage().splitlines()[0] for record in caplog.records]
    assert messages == [
        "drvs: /cam1: health check failed: KeyError: 'queue'",
        'drvs: /cam1: health check works again',
    ]


def test_a_sample_that_returns_no_health_is_an_error():
    status = DiagnosticsPublisher('drvs: /x', 'x', lambda: 'fine').status()
    assert (status.level, status.message) == (
        ERROR,
        'health check failed: TypeError: sample() must return a Health, got str',
    )


def test_period_must_be_positive():
    with pytest.raises(ValueError) as raised:
        DiagnosticsPublisher('drvs: /x', 'x', lambda: Health(OK, 'ok'), period=0)
    assert str(raised.value) == 'period: must be positive, got 0'


# -- live ------------------------------------------------------------------------------------------

NODE = textwrap.dedent(
    """
    import rospy
    from drvs.common.health import WARN, Health
    from drvs.ros.diagnostics import DiagnosticsPublisher

    def broken():
        raise RuntimeError('boom')

    rospy.init_node('diag')
    warn = Health(WARN, 'request queue 90% full (9 of 10)', [('queue length', '9')])
    ok = DiagnosticsPublisher('drvs: /diag', 'cam9', lambda: warn, period=0.2)
    failing = DiagnosticsPublisher('drvs: /diag broken', 'cam9', broken, period=0.2)
    ok.start()
    failing.start()
    rospy.on_shutdown(ok.stop)
    rospy.on_shutdown(failing.stop)
    rospy.spin()
    """
)


def echo_one(ros, condition):
    command = f'timeout 30 rostopic echo -n 1 --filter "{condition}" /diagnostics'
    result = ros.run(command, timeout=40)
    assert result.returncode == 0, f'{command}: {result.stdout}{result.stderr}\n{ros.describe()}'
    return result.stdout


def test_statuses_reach_rostopic_echo(ros):
    ros.spawn('diag', [sys.executable, '-c', NODE])
    shown = echo_one(ros, "m.status[0].name == 'drvs: /diag'")
    assert 'level: 1' in shown
    assert 'message: "request queue 90% full (9 of 10)"' in shown
    assert 'hardware_id: "cam9"' in shown
    assert 'key: "queue length"' in shown
    shown = echo_one(ros, "m.status[0].name == 'drvs: /diag broken'")
    assert 'level: 2' in shown
    assert 'message: "health check failed: RuntimeError: boom"' in shown


def test_doctests():
    result = doctest.testmod(health)
    assert result.attempted > 0 and result.failed == 0
