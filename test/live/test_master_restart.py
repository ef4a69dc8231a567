"""Nodes survive a ROS master restart (ros/ros_comm#185): the detection rule, and live restarts."""

import doctest
import json
import os
import signal
import socket
import threading
import time

import pytest

import drvs.common.master_restart
from drvs.common.master_restart import MasterRestartDetector, Verdict
from drvs.msg import BoundingBox
from drvs.ros.master_watch import MasterWatch
from drvs.ros.service_client import ServiceClient
from drvs.srv import CallbackCoordinates, DetectObjectBoundary, RegisterVisionService
from drvs.testing import ManualClock, RosHarness, read_json_lines, wait_for
from drvs.testing.reliability_log import Trial

NODE = 'test/nodes/master_watch_node.py'
URI = 'http://127.0.0.1:4000/'
OTHER = 'http://127.0.0.1:5000/'
REREGISTER_DEADLINE = 5.0  # seconds: a 1 s poll period plus registering


# -- the detection rule, without a master -----------------------------------------------------------


@pytest.fixture
def clock():
    return ManualClock(50.0)


@pytest.fixture
def detector(clock):
    detector = MasterRestartDetector(URI, clock=clock)
    assert detector.observe(100, URI).verdict is Verdict.NONE  # the master init_node registered with
    return detector


def test_the_module_example_holds():
    assert doctest.testmod(drvs.common.master_restart).failed == 0


def verdicts(detector, polls):
    return [detector.observe(pid, uri).verdict for pid, uri in polls]


def test_the_first_answer_is_the_master_the_node_registered_with(detector):
    assert detector.pid == 100
    assert verdicts(detector, [(100, URI)] * 3) == [Verdict.NONE] * 3


def test_a_new_pid_means_register_again_until_it_is_done(detector):
    decision = detector.observe(200, None)
    assert (decision.verdict, decision.old_pid, decision.new_pid, decision.reason) == (
        Verdict.REGISTER,
        100,
        200,
        'new master process',
    )
    # Not reported as done: every answered poll says so again.
    assert detector.observe(200, None).verdict is Verdict.REGISTER
    detector.registered(200)
    assert detector.pid == 200
    assert detector.observe(200, URI).verdict is Verdict.NONE


def test_a_new_pid_counts_even_if_the_node_is_already_known_to_it(detector):
    """A restart faster than a poll, after which some other path registered part of the node."""
    assert detector.observe(200, URI).verdict is Verdict.REGISTER


def test_a_master_that_forgot_the_node_under_the_same_pid_gets_everything_again(detector):
    decision = detector.observe(100, None)
    assert (decision.verdict, decision.old_pid, decision.new_pid, decision.reason) == (
        Verdict.REGISTER,
        100,
        100,
        'the master does not know this node',
    )


def test_a_node_unknown_at_the_first_answer_registers(clock):
    """The master restarted between init_node and the watch's first poll."""
    detector = MasterRestartDetector(URI, clock=clock)
    decision = detector.observe(300, None)
    assert (decision.verdict, decision.old_pid, decision.new_pid) == (Verdict.REGISTER, None, 300)


def test_a_failed_registration_is_tried_again_even_when_the_master_knows_part_of_it(detector):
    assert detector.observe(200, None).verdict is Verdict.REGISTER
    detector.registration_failed()
    decision = detector.observe(200, URI)  # some registrations went through, not all
    assert (decision.verdict, decision.old_pid, decision.reason) == (
        Verdict.REGISTER,
        100,
        'new master process',
    )
    detector.registered(200)
    assert detector.observe(200, URI).verdict is Verdict.NONE
    # A failure against the same master: again until done.
    assert detector.observe(200, None).verdict is Verdict.REGISTER
    detector.registration_failed()
    decision = detector.observe(200, URI)
    assert (decision.verdict, decision.reason) == (Verdict.REGISTER, 'the last registration failed')


def test_silence_is_said_once_and_the_same_master_coming_back_costs_nothing(detector, clock):
    assert verdicts(detector, [(None, None)] * 3) == [Verdict.SILENT, Verdict.NONE, Verdict.NONE]
    clock.now += 4.5
    decision = detector.observe(100, URI)
    assert (decision.verdict, decision.silent_for, decision.new_pid) == (Verdict.BACK, 4.5, 100)
    assert detector.observe(100, URI).verdict is Verdict.NONE


def test_a_new_master_after_silence_says_how_long_it_was_gone(detector, clock):
    assert detector.observe(None, None).verdict is Verdict.SILENT
    clock.now += 2.0
    decision = detector.observe(200, None)
    assert (decision.verdict, decision.old_pid, decision.new_pid, decision.silent_for) == (
        Verdict.REGISTER,
        100,
        200,
        2.0,
    )


def test_a_name_taken_by_another_process_is_left_alone_and_said_once(detector):
    decision = detector.observe(200, OTHER)
    assert (decision.verdict, decision.other_uri) == (Verdict.NAME_TAKEN, OTHER)
    assert verdicts(detector, [(200, OTHER)] * 2) == [Verdict.NONE] * 2
    # The other one went away: the master forgot the name, so this node registers again.
    assert detector.observe(200, None).verdict is Verdict.REGISTER


# -- the watch's thread, without a master -------------------------------------------------------
def test_the_watch_thread_logs_an_unexpected_error_with_its_traceback_and_goes_on(caplog):
    watch = MasterWatch(period=0.01)
    polls = []

    def poll():
        polls.append(len(polls))
        if len(polls) == 1:
            raise KeyError('deliberate')
        if len(polls) == 3:
            watch.stop()
        return Verdict.NONE

    watch.poll = poll
    watch._run()  # the thread's body, here in the test's thread: returns once stopped
    assert polls == [0, 1, 2]
    (record,) = [r for r in caplog.records if r.name == 'rosout.drvs.ros.master_watch']
    assert record.getMessage() == 'master watch: unexpected error (watching on)'
    assert "KeyError: 'deliberate'" in caplog.text  # with the traceback


@pytest.mark.parametrize('name', ['period', 'timeout', 'lock_timeout'])
def test_the_watch_refuses_a_period_or_timeout_that_is_not_positive(name):
    with pytest.raises(ValueError, match=f'^{name}: must be positive, got 0$'):
        MasterWatch(**{name: 0})


# -- the harness: a new master on the same port -----------------------------------------------
def test_the_harness_restarts_its_master_on_the_same_port_with_nothing_in_it(ros):
    port, uri, pid = ros.master.port, ros.master.uri, ros.master.pid
    ros.master.call('setParam', '/before', 1)
    assert ros.master.restart() != pid
    assert (ros.master.port, ros.master.uri) == (port, uri)
    assert ros.master.call('hasParam', '/before') is False
    first, second = ros.master.processes
    assert not first.running() and second.running()


def test_the_harness_waits_for_a_port_still_taken_after_the_kill(ros):
    ros.master.kill()
    squatter = socket.socket()
    squatter.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    squatter.bind(('127.0.0.1', ros.master.port))
    squatter.listen()
    result = {}
    starter = threading.Thread(target=lambda: result.update(pid=ros.master.start_again(timeout=30)))
    starter.start()
    try:
        wait_for(
            lambda: 'Unable to start XML-RPC server' in ros.master.node.log(),
            20,
            'a rosmaster to find the port taken',
            on_timeout=ros.describe,
        )
    finally:
        squatter.close()
    starter.join(40)
    assert result['pid'] == ros.master.pid
    assert len(ros.master.processes) >= 3  # the killed one, at least one that could not bind, the new one
    assert [p.running() for p in ros.master.processes].count(True) == 1


# -- live: a node with a publication, a subscription and a service -----------------------------
def node_registered(ros: RosHarness, node: str, publications, subscriptions, services) -> bool:
    try:
        published, subscribed, served = ros.master.system_state()
    except OSError:
        return False

    def of(entries):
        return {name for name, nodes in entries if node in nodes}

    return (
        set(publications) <= of(published)
        and set(subscriptions) <= of(subscribed)
        and set(services) <= of(served)
    )


def records(path, kind):
    return [entry for entry in read_json_lines(path) if entry['kind'] == kind]


WATCHED = {
    'publications': ['/watched/out', '/rosout'],
    'subscriptions': ['/watched/in'],
    'services': ['/watched/callback', '/watched/get_loggers', '/watched/set_logger_level'],
}


def test_a_node_registers_everything_again_after_the_master_restarts(ros, tmp_path, monkeypatch):
    monkeypatch.setenv('ROS_MASTER_URI', ros.master.uri)
    output = tmp_path / 'watched.jsonl'
    node = ros.start_node(NODE, name='watched', params={'output': output})
    ros.wait_for_service('/watched/callback', node=node)
    wait_for(lambda: node_registered(ros, '/watched', **WATCHED), 10, 'the node registered')
    old_pid = ros.master.pid

    started = time.monotonic()
    new_pid = ros.master.restart()
    assert new_pid != old_pid
    wait_for(
        lambda: node_registered(ros, '/watched', **WATCHED),
        REREGISTER_DEADLINE,
        'the node registered again with the new master',
        on_timeout=ros.describe,
    )
    print(f'registered again {time.monotonic() - started:.2f} s after the restart began')
    assert node.running()
    assert (
        f'master at {ros.master.uri} restarted (pid {old_pid} -> {new_pid}): '
        'registered again 2 publications, 1 subscriptions, 3 services'
    ) in node.log()

    # A service call through a fresh lookup on the new master.
    client = ServiceClient('/watched/callback', CallbackCoordinates, 5.0)
    try:
        client.call(CallbackCoordinates._request_class(request_id='after the restart'))
    finally:
        client.close()
    assert records(output, 'call') == [{'kind': 'call', 'request_id': 'after the restart'}]

    # A node started after the restart publishes to the old subscriber and subscribes to the old publisher.
    heard = tmp_path / 'talker.jsonl'
    talker = ros.start_node(
        NODE, name='talker', params={'output': heard, 'publish': '/watched/in', 'subscribe': '/watched/out'}
    )
    wait_for(
        lambda: any(m['data'].startswith('/talker ') for m in records(output, 'message')),
        10,
        'the new talker to reach the old subscriber',
        on_timeout=ros.describe,
    )
    wait_for(
        lambda: any(m['data'].startswith('/watched ') for m in records(heard, 'message')),
        10,
        'the old publisher to reach the new subscriber',
        on_timeout=talker.describe,
    )
    assert node.running()


def test_a_hung_master_is_waited_for_and_a_new_one_gets_everything_again(ros, tmp_path, monkeypatch):
    monkeypatch.setenv('ROS_MASTER_URI', ros.master.uri)
    node = ros.start_node(
        NODE, name='watched', params={'output': tmp_path / 'out.jsonl', 'watch_period': 0.2}
    )
    ros.wait_for_service('/watched/callback', node=node)
    first = ros.master.pid

    def logged(text, times=1):
        return lambda: node.log(tail=1000).count(text) >= times

    # A master that hangs (SIGSTOP) costs the watch a poll timeout, not its thread, and
    # the same master coming back has lost nothing: no registering again.
    os.killpg(ros.master.node.pid, signal.SIGSTOP)
    try:
        wait_for(
            logged('does not answer; watching for its return'),
            10,
            'the watch to notice',
            on_timeout=node.describe,
        )
    finally:
        os.killpg(ros.master.node.pid, signal.SIGCONT)
    wait_for(logged('answers again after'), 10, 'the watch to see it back', on_timeout=node.describe)
    assert f'(same pid {first})' in node.log()
    assert 'registered again' not in node.log()

    # A master that dies is noticed, and the new one gets everything again.
    ros.master.kill()
    wait_for(logged('does not answer', 2), 10, 'the watch to notice the kill', on_timeout=node.describe)
    second = ros.master.start_again()
    wait_for(
        lambda: node_registered(ros, '/watched', **WATCHED),
        REREGISTER_DEADLINE,
        'registered again',
        on_timeout=ros.describe,
    )
    # It registers first and logs after: wait for the line rather than race it.
    wait_for(
        logged(f'restarted (pid {first} -> {second})'), 10, 'the restart logged', on_timeout=node.describe
    )

    # And a restart quicker than the poll period too (the pid changed).
    third = ros.master.restart()
    wait_for(
        lambda: node_registered(ros, '/watched', **WATCHED),
        REREGISTER_DEADLINE,
        'registered again',
        on_timeout=ros.describe,
    )
    wait_for(
        logged(f'restarted (pid {second} -> {third})'),
        REREGISTER_DEADLINE,
        'the log line',
        on_timeout=node.describe,
    )
    assert 'Traceback' not in node.log(tail=1000)
    assert node.running()


# -- live: the real DRVS server --------------------------------------------------------------------
def test_drvs_server_services_come_back_after_a_master_restart(ros, monkeypatch, request):
    monkeypatch.setenv('ROS_MASTER_URI', ros.master.uri)
    server = ros.start_node('nodes/drvs_server', name='drvs')
    services = ['/drvs/detect_object_boundary', '/drvs/register_vision_service']
    for service in services:
        ros.wait_for_service(service, node=server)
    old_pid = ros.master.pid

    with Trial('master', request.node.name, 'roscore killed and restarted on the same port') as trial:
        started = time.monotonic()
        new_pid = ros.master.restart()
        wait_for(
            lambda: all(ros.master.lookup_service(service) for service in services),
            REREGISTER_DEADLINE,
            'the DRVS services on the new master',
            on_timeout=ros.describe,
        )
        trial['recovery_seconds'] = round(time.monotonic() - started, 3)
    assert f'restarted (pid {old_pid} -> {new_pid})' in server.log()
    assert '/drvs/registry' in {topic for topic, _ in ros.master.system_state()[0]}

    # Both answer through fresh lookups (what they answer is the server's business, tested elsewhere).
    detect = ServiceClient(services[0], DetectObjectBoundary, 10.0)
    register = ServiceClient(services[1], RegisterVisionService, 10.0)
    try:
        answer = detect.call(
            DetectObjectBoundary._request_class(
                algorithm='colour:0,0,150,80,80,255',
                region_of_interest=BoundingBox(0.0, 0.0, 1.0, 1.0),
                callback_service='/robot/callback_coordinates',
                request_id='after the restart',
            )
        )
        assert isinstance(answer, DetectObjectBoundary._response_class)
        answer = register.call(
            RegisterVisionService._request_class(service_name='/nobody/detect_object_boundary')
        )
        assert isinstance(answer, RegisterVisionService._response_class)
    finally:
        detect.close()
        register.close()
    assert server.running()


# -- live: the case study, with a master restart while the robot drives --------------------------
# About 30 s on the 2-core machines: not marked slow.
SCENARIO_TIMEOUT = 150


@pytest.mark.slow  # a whole scenario (about 30 s); the nodes' own restart tests run in make test
def test_obstacles_scenario_reaches_the_station_across_a_master_restart(ros, request):
    with Trial('master', request.node.name, 'roscore restarted while the robot drives its scenario') as trial:
        _run_scenario_across_a_master_restart(ros, trial)


def _run_scenario_across_a_master_restart(ros, trial):
    out = ros.root / 'out'
    runner = ros.spawn(
        'run_scenario',
        [
            'bash',
            'scripts/run_scenario.sh',
            'worlds/obstacles.yaml',
            '--external-master',
            '--timeout',
            str(SCENARIO_TIMEOUT),
            '--out',
            str(out),
        ],
    )

    def moving():
        if not runner.running():
            raise AssertionError(f'run_scenario.sh ended before the robot moved\n{runner.describe()}')
        try:
            return 'state moving' in (out / 'status.line').read_text()
        except FileNotFoundError:
            return False

    wait_for(moving, 90, 'the robot to drive', interval=0.2, on_timeout=runner.describe)
    old_pid = ros.master.pid
    new_pid = ros.master.restart()
    wait_for(
        lambda: not runner.running(),
        SCENARIO_TIMEOUT + 60,
        'run_scenario.sh to finish',
        interval=0.5,
        on_timeout=runner.describe,
    )
    logs = {path.name: path.read_text(errors='replace') for path in sorted(out.glob('*.log'))}
    tails = '\n'.join(f'--- {name} ---\n' + '\n'.join(text.splitlines()[-15:]) for name, text in logs.items())
    summary_path = out / 'summary.json'
    assert summary_path.exists(), f'no summary.json\n{runner.describe()}\n{tails}'
    summary = json.loads(summary_path.read_text())
    assert summary['reached'] is True, tails
    assert runner.process.returncode == 0, tails
    trial.update(reached=summary['reached'], elapsed=summary['elapsed'], collisions=summary['collisions'])
    restarted = f'restarted (pid {old_pid} -> {new_pid})'
    for name in ('drvs_server.log', 'world_sim.log', 'vs1.log', 'vs2.log', 'recorder.log', 'robot.log'):
        assert restarted in logs[name], f'{name} did not register again\n{tails}'
