"""ServiceClient and probe_service against live services on a private master."""

import os
import signal
import threading

import pytest

from drvs.msg import BoundingBox
from drvs.ros.service_client import ReplyLoop, ServiceCallError, ServiceClient, probe_service
from drvs.srv import CallbackCoordinates, DetectObjectBoundary, DetectObjectBoundaryRequest
from drvs.testing import freeze, wait_for

pytestmark = pytest.mark.shared_master  # see test/conftest.py

ECHO = 'test/nodes/echo_detect_boundary.py'
FAKE = 'test/nodes/fake_vision_system.py'


def request(request_id='r1'):
    return DetectObjectBoundaryRequest(
        algorithm='colour:0,0,150,80,80,255',
        region_of_interest=BoundingBox(0.5, 1.0, 2.5, 3.0),
        callback_service='/robot/callback_coordinates',
        request_id=request_id,
    )


def start_echo(ros, name='echo', replacing=None):
    """Start the echo node; with ``replacing`` (an old URI), wait until the master has the new one."""
    node = ros.start_node(ECHO, name=name)
    service = f'/{name}/detect_object_boundary'
    ros.wait_for_service(service, node=node)
    wait_for(lambda: ros.master.lookup_service(service) not in (None, replacing), 30.0, f'new {service}')
    return node


def test_calls_reuse_one_connection_and_pass_every_field(ros):
    start_echo(ros)
    client = ServiceClient(
        '/echo/detect_object_boundary', DetectObjectBoundary, 5.0, master_uri=ros.master.uri
    )
    try:
        for index in range(3):
            answer = client.call(request(f'r{index}'))
            assert answer.accepted
            assert answer.message == f'colour:0,0,150,80,80,255|r{index}|0.5,1.0,2.5,3.0'
            assert answer.vision_systems == len('/robot/callback_coordinates')
        assert client.connections == 1
        assert client.header['callerid'] == '/echo'
    finally:
        client.close()


def test_concurrent_calls_on_one_client_each_get_their_own_reply(ros):
    start_echo(ros)
    client = ServiceClient(
        '/echo/detect_object_boundary', DetectObjectBoundary, 5.0, master_uri=ros.master.uri
    )
    answers, errors = {}, []

    def worker(index):
        for repeat in range(20):
            request_id = f't{index}-{repeat}'
            try:
                answers[request_id] = client.call(request(request_id)).message.split('|')[1]
            except ServiceCallError as error:
                errors.append(error)

    threads = [threading.Thread(target=worker, args=(index,)) for index in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    client.close()
    assert errors == []
    assert len(answers) == 80
    assert all(key == value for key, value in answers.items())


def test_unknown_service(ros):
    client = ServiceClient(
        '/nobody/detect_object_boundary', DetectObjectBoundary, 2.0, master_uri=ros.master.uri
    )
    with pytest.raises(ServiceCallError) as caught:
        client.call(request())
    assert str(caught.value) == (
        'service /nobody/detect_object_boundary: unknown service ' '(the master says: no provider)'
    )


def test_timeout_against_a_hung_service_then_recovers(ros, tmp_path):
    node = ros.start_node(
        FAKE, name='hung', params={'output': tmp_path / 'hung.jsonl', 'register': False, 'hang': 3600}
    )
    ros.wait_for_service('/hung/detect_object_boundary', node=node)
    client = ServiceClient(
        '/hung/detect_object_boundary', DetectObjectBoundary, 0.5, master_uri=ros.master.uri
    )
    try:
        for _ in range(2):
            with pytest.raises(ServiceCallError) as caught:
                client.call(request())
            assert str(caught.value) == (
                'service /hung/detect_object_boundary: timed out after 0.5 s waiting for the reply'
            )
        assert client.connections == 2  # a fresh connection after the failure
    finally:
        client.close()


def test_wrong_type_is_refused_by_the_service(ros):
    start_echo(ros)
    client = ServiceClient(
        '/echo/detect_object_boundary', CallbackCoordinates, 2.0, master_uri=ros.master.uri
    )
    with pytest.raises(ServiceCallError) as caught:
        client.call(CallbackCoordinates._request_class(request_id='x'))
    assert str(caught.value) == (
        'service /echo/detect_object_boundary: the service refused the connection: '
        f'request from [/unnamed]: md5sums do not match: [{CallbackCoordinates._md5sum}] '
        f'vs. [{DetectObjectBoundary._md5sum}]'
    )


def test_reconnects_after_the_far_side_restarts(ros):
    node = start_echo(ros)
    client = ServiceClient(
        '/echo/detect_object_boundary', DetectObjectBoundary, 5.0, master_uri=ros.master.uri
    )
    try:
        assert client.call(request('before')).accepted
        old_uri = ros.master.lookup_service('/echo/detect_object_boundary')
        assert node.interrupt() == 0
        # Restarted while the client held its idle connection: the stale one is noticed.
        node = start_echo(ros, replacing=old_uri)
        assert client.call(request('after')).message.split('|')[1] == 'after'
        assert client.connections == 2
        # Gone: the call fails with a message, and the next one after a restart works.
        old_uri = ros.master.lookup_service('/echo/detect_object_boundary')
        assert node.interrupt() == 0
        with pytest.raises(ServiceCallError, match='^service /echo/detect_object_boundary: '):
            client.call(request('gone'))
        start_echo(ros, replacing=old_uri)
        assert client.call(request('back')).message.split('|')[1] == 'back'
    finally:
        client.close()


def test_probe_service_reports_type_and_provider(ros):
    start_echo(ros)
    info = probe_service('/echo/detect_object_boundary', 2.0, master_uri=ros.master.uri)
    assert (info.type, info.md5sum, info.provider) == (
        'drvs/DetectObjectBoundary',
        DetectObjectBoundary._md5sum,
        '/echo',
    )
    assert info.uri == ros.master.lookup_service('/echo/detect_object_boundary')


def test_constructor_refuses_a_non_positive_timeout():
    with pytest.raises(ValueError, match='^timeout: must be positive, got 0$'):
        ServiceClient('/x', DetectObjectBoundary, 0)


class Outcomes:
    """``done`` callbacks of :meth:`ServiceClient.start`: what each call ended with, and on which thread."""

    def __init__(self):
        self.ended = []
        self.lock = threading.Lock()

    def done(self, request_id):
        def done(response, error):
            with self.lock:
                self.ended.append((request_id, response, error, threading.current_thread().name))

        return done


@pytest.fixture
def replies():
    loop = ReplyLoop('test-replies')
    loop.start()
    yield loop
    loop.stop()


def test_start_sends_on_an_open_connection_and_the_loop_hands_over_the_reply(ros, replies):
    start_echo(ros)
    client = ServiceClient(
        '/echo/detect_object_boundary', DetectObjectBoundary, 5.0, master_uri=ros.master.uri
    )
    outcomes = Outcomes()
    try:
        assert not client.start(request('early'), replies, outcomes.done('early'))  # no connection yet
        client.call(request('opens'))
        for index in range(3):
            assert client.start(request(f's{index}'), replies, outcomes.done(f's{index}'))
            wait_for(lambda index=index: len(outcomes.ended) == index + 1, 10, f'the reply to s{index}')
        assert [(i, r.message.split('|')[1], e, t) for i, r, e, t in outcomes.ended] == [
            (f's{index}', f's{index}', None, 'test-replies') for index in range(3)
        ]
        assert client.connections == 1
        assert client.call(request('after')).message.split('|')[1] == 'after'  # the lock was given back
    finally:
        client.close()


def test_start_times_out_like_call_and_the_next_call_reconnects(ros, replies):
    node = start_echo(ros)
    client = ServiceClient(
        '/echo/detect_object_boundary', DetectObjectBoundary, 0.5, master_uri=ros.master.uri
    )
    outcomes = Outcomes()
    try:
        client.call(request('opens'))
        freeze(node.pid)  # the service hangs
        try:
            assert client.start(request('hung'), replies, outcomes.done('hung'))
            wait_for(lambda: outcomes.ended, 10, 'the timeout')
        finally:
            os.kill(node.pid, signal.SIGCONT)
        ((request_id, response, error, thread),) = outcomes.ended
        assert (request_id, response, thread) == ('hung', None, 'test-replies')
        assert (
            str(error) == 'service /echo/detect_object_boundary: timed out after 0.5 s waiting for the reply'
        )
        assert client.call(request('again')).message.split('|')[1] == 'again'
        assert client.connections == 2  # the timed-out connection was dropped
    finally:
        client.close()


def test_stopping_the_loop_ends_the_calls_in_flight(ros):
    node = start_echo(ros)
    loop = ReplyLoop('test-replies')
    loop.start()
    client = ServiceClient(
        '/echo/detect_object_boundary', DetectObjectBoundary, 30.0, master_uri=ros.master.uri
    )
    outcomes = Outcomes()
    try:
        client.call(request('opens'))
        freeze(node.pid)
        try:
            assert client.start(request('hung'), loop, outcomes.done('hung'))
            loop.stop()
        finally:
            os.kill(node.pid, signal.SIGCONT)
        assert [(i, r, str(e)) for i, r, e, _ in outcomes.ended] == [
            ('hung', None, 'service /echo/detect_object_boundary: shutting down')
        ]
        assert not client.start(request('late'), loop, outcomes.done('late'))  # a stopped loop takes none
    finally:
        client.close()
