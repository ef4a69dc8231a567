"""The rosbridge protocol's pure rules: frames parsed and refused naming the field, token rights per
operation, the table of calls awaiting a client's answer with their deadlines, the bounded send
queue and a subscription's throttle."""

import json

import pytest

from drvs.gateway.rosbridge import (
    PendingCalls,
    ProtocolError,
    SendQueue,
    Throttle,
    bearer_from_protocols,
    parse,
    required_right,
    shown,
)
from drvs.testing.clock import ManualClock

SERVICES = {'/drvs/detect_object_boundary': 'detect', '/drvs/watch_object_boundary': 'watch'}


def test_a_call_service_frame_is_parsed_with_its_fields():
    op = parse(
        '{"op": "call_service", "id": "call_service:/drvs/detect_object_boundary:1", '
        '"service": "/drvs/detect_object_boundary", "args": {"algorithm": "colour"}, "timeout": 2, '
        '"fragment_size": 100}'
    )
    assert (op.op, op.id, op.service, op.args, op.timeout) == (
        'call_service',
        'call_service:/drvs/detect_object_boundary:1',
        '/drvs/detect_object_boundary',
        {'algorithm': 'colour'},
        2,
    )


@pytest.mark.parametrize(
    ('frame', 'field'),
    [
        ('not json', 'frame'),
        ('{"op": "call_service", "service": NaN}', 'frame'),
        ('[1, 2]', 'frame'),
        ('"op"', 'frame'),
        ('{}', 'op'),
        ('{"op": 5}', 'op'),
        ('{"op": "publish", "topic": "/a", "msg": {}}', 'op'),
        ('{"op": "advertise", "topic": "/a", "type": "std_msgs/String"}', 'op'),
        ('{"op": "call_service"}', 'service'),
        ('{"op": "call_service", "service": 3}', 'service'),
        ('{"op": "call_service", "service": "/s", "args": "x"}', 'args'),
        ('{"op": "call_service", "service": "/s", "timeout": -1}', 'timeout'),
        ('{"op": "call_service", "service": "/s", "timeout": true}', 'timeout'),
        ('{"op": "call_service", "service": "/s", "id": {"a": 1}}', 'id'),
        ('{"op": "service_response", "service": "/s"}', 'id'),
        ('{"op": "service_response", "service": "/s", "id": "x", "result": "yes"}', 'result'),
        ('{"op": "advertise_service", "service": "/s"}', 'type'),
        ('{"op": "subscribe", "topic": null}', 'topic'),
        ('{"op": "subscribe", "topic": "/t", "throttle_rate": "fast"}', 'throttle_rate'),
        ('{"op": "set_level", "level": "loud"}', 'level'),
        ('{"op": "auth"}', 'mac'),
        ('[' * 100_000, 'frame'),
    ],
)
def test_bad_frames_are_refused_naming_the_field(frame, field):
    with pytest.raises(ProtocolError) as refused:
        parse(frame)
    assert refused.value.field == field


def test_a_refusal_carries_the_frames_id():
    with pytest.raises(ProtocolError) as refused:
        parse('{"op": "call_service", "id": 7}')
    assert (refused.value.field, refused.value.id) == ('service', 7)


def test_rights_per_operation():
    call = parse(
        '{"op": "call_service", "service": "/drvs/watch_object_boundary", "args": {"algorithm": "colour:1"}}'
    )
    assert required_right(call, SERVICES) == (('watch',), 'colour:1')
    assert required_right(parse('{"op": "advertise_service", "service": "/a", "type": "t"}'), SERVICES) == (
        ('detect', 'watch'),
        None,
    )
    assert required_right(parse('{"op": "subscribe", "topic": "/drvs/registry"}'), SERVICES) == (
        ('read',),
        None,
    )
    assert required_right(parse('{"op": "set_level", "level": "info"}'), SERVICES) == ((), None)


def test_the_token_travels_in_a_subprotocol():
    assert bearer_from_protocols('drvs, bearer.drvs.abc.s3cr-t_') == 'drvs.abc.s3cr-t_'
    assert bearer_from_protocols('drvs') is None
    assert bearer_from_protocols(None) is None
    assert bearer_from_protocols('bearer.') is None


def test_status_levels():
    assert shown('error', 'warning') and shown('warning', 'warning') and not shown('info', 'warning')
    assert not shown('error', 'none') and shown('info', 'info')


def test_pending_calls_are_answered_once_within_their_deadline():
    clock = ManualClock()
    calls = PendingCalls(clock, limit=2)
    first = calls.add('/cb', 1.5, 'first')
    second = calls.add('/cb', 1.5, 'second')
    assert calls.add('/cb', 1.5, 'third') is None  # the limit
    assert first.id != second.id and len(calls) == 2
    assert calls.answer(first.id, '/cb').waiter == 'first'
    with pytest.raises(ProtocolError, match='answered or too late'):
        calls.answer(first.id, '/cb')  # answered already
    with pytest.raises(ProtocolError) as wrong:
        calls.answer(second.id, '/other')
    assert wrong.value.field == 'service'
    clock.now += 2.0
    with pytest.raises(ProtocolError, match='too late'):
        calls.answer(second.id, '/cb')
    assert len(calls) == 0


def test_expired_calls_leave_the_table():
    clock = ManualClock()
    calls = PendingCalls(clock, limit=10)
    early = calls.add('/cb', 1.0, 'early')
    late = calls.add('/cb', 3.0, 'late')
    clock.now += 2.0
    assert [call.id for call in calls.expire()] == [early.id]
    assert calls.drop(late.id) is late and calls.clear() == []


def test_the_send_queue_drops_the_oldest_and_says_how_many():
    queue = SendQueue(3)
    for i in range(10):
        queue.put(str(i))
    first, *rest = queue.take()
    assert json.loads(first) == {
        'op': 'status',
        'level': 'warning',
        'msg': '7 message(s) dropped: this client read too slowly',
    }
    assert rest == ['7', '8', '9'] and queue.dropped_total == 7
    queue.put('10')
    assert queue.take() == ['10']  # said once
    for i in range(5):
        queue.put(str(i))
    assert queue.take(level='error') == ['2', '3', '4']  # a client that asked for errors only


def test_a_throttle_lets_one_message_through_per_period():
    throttle = Throttle(100.0)
    assert [throttle.due(t) for t in (0.0, 0.05, 0.1, 0.15, 0.3)] == [True, False, True, False, True]
    assert all(Throttle().due(t) for t in (0.0, 0.0, 0.001))
