"""The order in which a client asks several DRVS servers (replicas), and the nodes' ``~servers``."""

import doctest

import pytest

import drvs.common.failover
from drvs.common.failover import Heard, Move, ServerList, moves_on, namespace_of, namespaces, service_names
from drvs.common.settings import ParamError
from drvs.common.status import BUSY, RATE_LIMITED, UNAVAILABLE
from drvs.robot.params import RobotParams
from drvs.ros.params import read_params
from drvs.testing import ManualClock
from drvs.vision.params import VisionSystemParams


def test_doctests():
    assert doctest.testmod(drvs.common.failover).failed == 0


def test_unavailable_or_no_answer_moves_on_and_load_refusals_stay():
    assert moves_on(None) and moves_on(UNAVAILABLE)
    assert not moves_on(BUSY) and not moves_on(RATE_LIMITED)


def test_failures_go_round_the_list_in_order():
    servers = ServerList(['/a', '/b', '/c'])
    assert [servers.current] + [servers.failed() for _ in range(4)] == ['/a', '/b', '/c', '/a', '/b']
    assert ServerList(['/a']).failed() == '/a'


@pytest.mark.parametrize(
    'names, message',
    [
        ([], 'servers: empty; name at least one DRVS server'),
        (['/a', '/b', '/a'], 'servers: /a named more than once'),
    ],
)
def test_bad_lists_are_refused(names, message):
    with pytest.raises(ValueError) as caught:
        ServerList(names)
    assert str(caught.value) == message


def test_a_move_is_logged_once_a_whole_round_once_and_the_answer_after_it():
    servers = ServerList(['/a', '/b'])
    move = servers.fail('/a', 'connection refused')
    assert move == Move('/b', 'DRVS server /a did not serve (connection refused); asking /b from now on')
    assert servers.fail('/a', 'timed out') is None  # a call to /a still out: already moved
    assert servers.answered('/b') == ''
    assert servers.fail('/b', 'UNAVAILABLE: no database').line.startswith('DRVS server /b did not serve')
    round_failed = servers.fail('/a', 'connection refused')  # /b, then /a: a whole round
    assert round_failed == Move(
        '/b', 'no DRVS server answers (/a, /b; /a: connection refused); still trying them in turn, now /b'
    )
    assert [servers.fail(servers.current, 'refused').line for _ in range(3)] == ['', '', '']  # quiet
    assert servers.current == '/a'
    assert servers.answered('/b') == '' and servers.answered('/a') == 'DRVS server /a answers again'
    assert servers.fail('/a', 'refused').line.startswith('DRVS server /a did not serve')
    assert servers.moves == 7


def test_one_server_never_moves():
    servers = ServerList(['/drvs/watch_object_boundary'])
    assert servers.fail('/drvs/watch_object_boundary', 'connection refused') is None
    assert (servers.moves, servers.answered('/drvs/watch_object_boundary')) == (0, '')


def test_servers_parameter_names_namespaces():
    assert namespaces('/drvs,/drvs_b') == ['/drvs', '/drvs_b']
    assert service_names(namespaces('/drvs, /site/b'), '/drvs/register_vision_service') == [
        '/drvs/register_vision_service',
        '/site/b/register_vision_service',
    ]
    assert namespace_of('/drvs_b/watch_object_boundary') == '/drvs_b'


@pytest.mark.parametrize(
    'text, message',
    [
        ('', '~servers: empty; name at least one DRVS server namespace, e.g. [/drvs]'),
        ('/a,,/b', "~servers: an empty name in '/a,,/b'; expected namespaces such as /drvs"),
        (
            'drvs',
            "~servers: 'drvs' is not a global ROS name (it must start with /); expected namespaces "
            'such as /drvs',
        ),
        ('/a b', "~servers: '/a b' is not a valid ROS name; expected namespaces such as /drvs"),
        ('/a,/a', '~servers: /a named more than once'),
    ],
)
def test_bad_servers_parameters_are_refused_by_name(text, message):
    with pytest.raises(ParamError) as caught:
        namespaces(text)
    assert str(caught.value) == message


@pytest.mark.parametrize('settings', [VisionSystemParams, RobotParams])
def test_the_nodes_refuse_bad_servers_and_default_to_todays_server(settings):
    required = {'camera': 'vs1'} if settings is VisionSystemParams else {'world': 'w.yaml'}
    services = (lambda p: p.register_services) if settings is VisionSystemParams else (lambda p: p.services)
    assert services(settings(**required)) == [
        '/drvs/register_vision_service' if settings is VisionSystemParams else '/drvs/watch_object_boundary'
    ]
    assert len(services(settings(**required, servers='/drvs,/drvs_b'))) == 2
    for bad, message in [
        ([], '~servers: empty; name at least one DRVS server namespace, e.g. [/drvs]'),
        ([1, 2], '~servers: expected a string or a list of strings, got [1, 2]'),
        ({'a': 1}, "~servers: expected a string, got {'a': 1}"),
    ]:
        with pytest.raises(ParamError) as caught:
            read_params(
                settings,
                get=lambda name, default, bad=bad: {**required, 'servers': bad}.get(name[1:], default),
            )
        assert str(caught.value) == message


def test_a_polling_robot_asks_detect_object_boundary_on_each_server():
    params = RobotParams(world='w.yaml', requests='poll', servers='/drvs,/drvs_b')
    assert params.services == ['/drvs/detect_object_boundary', '/drvs_b/detect_object_boundary']


def test_the_first_server_is_asked_again_after_return_after_and_kept_when_it_answers():
    clock = ManualClock()
    servers = ServerList(['/a', '/b', '/c'], clock=clock, return_after=30.0)
    servers.fail('/a', 'connection refused')
    clock.now += 29.9
    assert servers.to_ask() == '/b'
    clock.now += 0.1
    assert servers.to_ask() == '/a'  # time to try the first again
    assert servers.answered('/a') == 'DRVS server /a answers again; asking it from now on'
    clock.now += 1000.0
    assert (servers.to_ask(), servers.returns, servers.moves) == ('/a', 1, 1)


def test_a_first_server_still_down_sends_the_client_back_quietly_and_waits_longer_each_time():
    clock = ManualClock()
    servers = ServerList(['/a', '/b', '/c'], clock=clock, return_after=10.0)
    servers.fail('/a', 'connection refused')
    servers.fail('/b', 'UNAVAILABLE')  # now on /c: the client came from /c when it tries /a
    tries = []
    for _ in range(7):
        while servers.to_ask() != '/a':
            clock.now += 1.0
        tries.append(clock())
        assert servers.fail('/a', 'connection refused') == Move('/c', '')
        assert servers.to_ask() == '/c'
    assert [round(b - a) for a, b in zip(tries, tries[1:], strict=False)] == [20, 40, 80, 160, 300, 300]
    assert servers.returns == 0
    clock.now += 300.0
    assert servers.to_ask() == '/a' and servers.answered('/a').startswith('DRVS server /a answers again')
    servers.fail('/a', 'refused')
    clock.now += 10.0
    assert servers.to_ask() == '/a'  # the wait starts again from return_after after an answer


def test_a_client_on_its_first_server_never_returns_and_a_round_back_to_it_is_no_return():
    clock = ManualClock()
    servers = ServerList(['/a', '/b'], clock=clock, return_after=5.0)
    clock.now += 100.0
    assert servers.to_ask() == '/a'
    servers.fail('/a', 'refused')
    servers.fail('/b', 'refused')  # a whole round: on /a again, by turn
    clock.now += 100.0
    assert servers.to_ask() == '/a' and servers.answered('/a') == 'DRVS server /a answers again'
    assert servers.returns == 0
    with pytest.raises(ValueError, match='server_return: must be positive'):
        ServerList(['/a'], return_after=0.0)


def test_what_a_client_makes_of_a_calls_end():
    servers = ServerList(['/a', '/b'])
    assert servers.heard('/a', BUSY, 'busy') == Heard()  # a load refusal: retried at the same server
    moved = servers.heard('/a', UNAVAILABLE, 'no database')
    assert moved == Heard(
        'DRVS server /a did not serve (UNAVAILABLE: no database); asking /b from now on',
        warning=True,
        moved=True,
    )
    assert servers.heard('/b', None, 'timed out after 2 s').moved and servers.current == '/a'
    assert servers.heard('/a', 0, '') == Heard('DRVS server /a answers again')
    assert ServerList(['/a']).heard('/a', None, 'refused') == Heard()  # nowhere else to go
