"""The watches' bookkeeping: event ids, resuming, slow listeners, renewal and linger, on a manual clock."""

import doctest

import pytest

from drvs.gateway import answers, body, sse, tokens, watches
from drvs.gateway.watches import WatchHub
from drvs.testing.clock import ManualClock


@pytest.fixture
def clock():
    return ManualClock(0.0)


@pytest.fixture
def hub(clock):
    return WatchHub(clock, duration=10.0, linger=30.0, buffer=5, queue=3)


def kinds(events):
    return [(event.id, event.kind) for event in events]


def test_events_are_numbered_and_resumed_after_last_event_id(hub):
    hub.open('w', 'r', 'robot', None)
    first = hub.listen('w')
    for n in range(3):
        hub.deliver('r', {'n': n})
    assert kinds(first.take()) == [(1, 'callback'), (2, 'callback'), (3, 'callback')]
    hub.leave(first)
    resumed = hub.listen('w', last_event_id=2)
    assert kinds(resumed.take()) == [(3, 'callback')]
    assert not hub.deliver('other', {})


def test_resuming_past_the_buffer_says_what_was_lost(hub):
    hub.open('w', 'r', 'robot', None)
    for n in range(8):
        hub.deliver('r', {'n': n})
    late = hub.listen('w', last_event_id=1)
    events = late.take()
    assert kinds(events) == [
        (3, 'status'),
        (4, 'callback'),
        (5, 'callback'),
        (6, 'callback'),
        (7, 'callback'),
        (8, 'callback'),
    ]
    assert events[0].data['status'] == 'GAP' and events[0].data['dropped'] == 2


def test_a_slow_listener_loses_the_oldest_and_is_told(hub):
    hub.open('w', 'r', 'robot', None)
    slow, fast = hub.listen('w'), hub.listen('w')
    for n in range(5):
        hub.deliver('r', {'n': n})
        fast.take()
    events = slow.take()
    assert kinds(events) == [(2, 'status'), (3, 'callback'), (4, 'callback'), (5, 'callback')]
    assert events[0].data == {
        'status': 'DROPPED',
        'dropped': 2,
        'message': '2 event(s) dropped: this client read too slowly',
    }
    assert slow.take() == []


def test_renewed_at_half_the_granted_duration_withdrawn_after_the_linger(hub, clock):
    watch = hub.open('w', 'r', 'robot', None, granted={'duration': 8.0})
    assert hub.due() == ([], [])
    clock.now = 4.0
    assert hub.due() == ([watch], [])
    hub.renewed(watch, {'duration': 8.0})
    listener = hub.listen('w')
    clock.now = 7.9
    assert hub.due() == ([], [])
    clock.now = 100.0  # listened to: never withdrawn
    hub.renewed(watch, {'duration': 8.0})
    assert hub.due() == ([], [])
    hub.leave(listener)
    clock.now = 129.9
    hub.renewed(watch, {})
    assert hub.due() == ([], [])
    clock.now = 130.0
    assert hub.due() == ([], [watch])
    assert hub.get('w') is None and watch.ended and hub.withdrawn == 1
    assert kinds(watch.buffer)[-1][1] == 'end'


def test_a_watch_nobody_ever_listens_to_lingers_from_its_creation(hub, clock):
    watch = hub.open('w', 'r', 'robot', None)
    clock.now = 29.0
    hub.renewed(watch, {})
    assert hub.due()[1] == []
    clock.now = 30.0
    assert hub.due()[1] == [watch]


def test_end_tells_every_listener_and_forgets_the_watch(hub):
    hub.open('w', 'r', 'robot', None)
    listener = hub.listen('w')
    assert hub.end('w', 'deleted').id == 'w'
    assert [(e.kind, e.data) for e in listener.take()] == [('end', {'reason': 'deleted'})]
    assert hub.end('w', 'again') is None and len(hub) == 0 and not hub.deliver('r', {})
    with pytest.raises(KeyError):
        hub.listen('w')


def test_retry_renewal_posts_a_status_event(hub, clock):
    watch = hub.open('w', 'r', 'robot', None)
    listener = hub.listen('w')
    hub.retry_renewal(watch, 2.0, {'status': 'BUSY', 'message': 'saturated'})
    assert watch.renew_at == 2.0 and listener.take()[0].data['status'] == 'BUSY'


@pytest.mark.parametrize(('header', 'value'), [(None, None), ('', None), (' 12 ', 12)])
def test_last_event_id(header, value):
    assert sse.last_event_id(header) == value


@pytest.mark.parametrize('header', ['-1', 'abc', '1' * 30])
def test_a_bad_last_event_id_is_refused(header):
    with pytest.raises(ValueError, match='expected the id of an event'):
        sse.last_event_id(header)


@pytest.mark.parametrize('module', [answers, body, sse, tokens, watches])
def test_doctests(module):
    assert doctest.testmod(module).failed == 0
