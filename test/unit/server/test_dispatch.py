"""The forwarding pool: one in flight per destination, bounded queues, stuck ones hold one worker."""

import threading

import pytest

from drvs.common.status import RATE_LIMITED
from drvs.server.dispatch import Busy, Dispatcher, OverShare
from drvs.testing import wait_for


class Recorder:
    def __init__(self, stuck=()):
        self.sent = []
        self.release = threading.Event()
        self.stuck = set(stuck)
        self.lock = threading.Lock()

    def __call__(self, destination, item):
        with self.lock:
            self.sent.append((destination, item))
        if destination in self.stuck:
            self.release.wait(30)

    def items(self, destination):
        with self.lock:
            return [item for d, item in self.sent if d == destination]


@pytest.fixture
def pool():
    made = []

    def make(send, **kwargs):
        made.append(Dispatcher(send, **kwargs))
        made[-1].start()
        return made[-1]

    yield make
    for dispatcher in made:
        dispatcher.send.release.set()
        dispatcher.stop()


def test_a_stuck_destination_holds_one_worker_and_the_others_flow(pool):
    send = Recorder(stuck={'hung'})
    dispatcher = pool(send, workers=2, max_pending=100, max_per_destination=10)
    for index in range(5):
        assert dispatcher.submit(['hung', 'a', 'b'], index) == (['hung', 'a', 'b'], [])
    wait_for(lambda: send.items('a') == list(range(5)) and send.items('b') == list(range(5)), 10, 'a and b')
    assert send.items('hung') == [0]  # one at a time per destination, in order
    send.release.set()
    wait_for(lambda: send.items('hung') == list(range(5)), 10, 'hung to catch up')
    wait_for(lambda: dispatcher.pending == 0, 10, 'an empty pool')


def test_limits_refuse_instead_of_queueing(pool):
    send = Recorder(stuck={'hung', 'other'})
    dispatcher = pool(send, workers=1, max_pending=3, max_per_destination=2)
    assert dispatcher.submit(['hung'], 0) == (['hung'], [])
    wait_for(lambda: send.items('hung') == [0], 10, 'the first item in flight')
    assert dispatcher.submit(['hung'], 1) == (['hung'], [])
    assert dispatcher.submit(['hung', 'other'], 2) == (['other'], ['hung'])  # hung has 2 already
    with pytest.raises(Busy) as caught:
        dispatcher.submit(['x', 'y'], 3)
    assert str(caught.value) == 'busy: 3 forwards pending, 2 more would pass the limit of 3; try again later'
    assert dispatcher.drop('hung') == 1  # the queued one; the one in flight finishes on its own
    assert dispatcher.pending == 2


def test_an_exception_in_send_is_logged_and_the_worker_goes_on(pool, caplog):
    seen = []

    def send(destination, item):
        seen.append(item)
        if item == 'boom':
            raise RuntimeError('boom')

    send.release = threading.Event()
    dispatcher = pool(send, workers=1)
    dispatcher.submit(['a'], 'boom')
    dispatcher.submit(['a'], 'next')
    wait_for(lambda: seen == ['boom', 'next'], 10, 'both items')
    assert 'sending to a failed unexpectedly' in caplog.text


class Begin:
    """A ``begin`` that starts items on the calling thread and ends them when the test says."""

    def __init__(self, refuse=()):
        self.begun = []  # (destination, item, thread name)
        self.done = {}  # destination -> its done() for the item in flight
        self.refuse = set(refuse)  # items left to the workers
        self.lock = threading.Lock()

    def __call__(self, destination, item, done):
        if item in self.refuse:
            return False
        with self.lock:
            self.begun.append((destination, item, threading.current_thread().name))
            self.done[destination] = done
        return True

    def end(self, destination):
        with self.lock:
            done = self.done.pop(destination)
        done()


def test_held_items_start_on_the_releasing_thread_and_follow_on_the_finishing_one(pool):
    send, begin = Recorder(), Begin()
    dispatcher = pool(send, workers=2, begin=begin)
    assert dispatcher.submit(['a', 'b'], 0, wake=False) == (['a', 'b'], [])
    assert dispatcher.submit(['a'], 1, wake=False) == (
        ['a'],
        [],
    )  # queued behind 0: one in flight per destination
    here = threading.current_thread().name
    dispatcher.release(3)
    assert begin.begun == [('a', 0, here), ('b', 0, here)]
    assert dispatcher.pending == 3
    finisher = threading.Thread(target=begin.end, args=('a',), name='finisher')
    finisher.start()
    finisher.join()
    assert begin.begun[-1] == ('a', 1, 'finisher')  # the next item of a, started where 0 ended
    begin.end('a')
    begin.end('b')
    assert dispatcher.pending == 0
    assert send.sent == []  # no worker was needed


def test_what_begin_cannot_start_goes_to_a_worker_in_order(pool):
    send, begin = Recorder(), Begin(refuse={'connect'})
    dispatcher = pool(send, workers=1, begin=begin)
    dispatcher.submit(['a'], 'connect', wake=False)
    dispatcher.submit(['a'], 'then', wake=False)
    dispatcher.release(1)
    wait_for(lambda: begin.begun and begin.begun[0][:2] == ('a', 'then'), 10, 'the second item begun')
    assert send.sent == [('a', 'connect')]  # sent (blocking) by the worker, before the next one
    assert begin.begun[0][2] == 'dispatch-0'  # which went on to start the next one itself
    begin.end('a')
    assert dispatcher.pending == 0


def test_an_exception_in_begin_is_logged_and_the_item_counts_as_sent(pool, caplog):
    def begin(destination, item, done):
        raise RuntimeError('boom')

    send = Recorder()
    dispatcher = pool(send, workers=1, begin=begin)
    dispatcher.submit(['a'], 'boom', wake=False)
    dispatcher.release(1)
    assert dispatcher.pending == 0
    assert 'sending to a failed unexpectedly' in caplog.text
    assert send.sent == []


def test_doctests():
    import doctest

    import drvs.server.dispatch

    assert doctest.testmod(drvs.server.dispatch).failed == 0


def test_a_flooding_caller_gets_its_fair_share_and_another_caller_always_finds_room(pool):
    recorder = Recorder(stuck={'cam'})  # nothing finishes: every place stays held
    dispatcher = pool(recorder, workers=2, max_per_destination=10)
    accepted = [dispatcher.submit(['cam'], f'flood{n}', caller='/flood')[0] for n in range(8)]
    assert accepted == [['cam']] * 8 and dispatcher.holding('cam', '/flood') == 8
    with pytest.raises(OverShare) as caught:
        dispatcher.submit(['cam'], 'flood8', caller='/flood')
    assert caught.value.status == RATE_LIMITED and caught.value.retry_after == 0.5
    assert str(caught.value) == (
        'rate limited: /flood holds 8 of the 10 forward places of cam, its fair share while 0 other '
        'caller(s) wait there; try again after 0.5 s'
    )
    # Another caller finds room, and from now on the flood's share is half of what is not spare.
    assert dispatcher.submit(['cam'], 'polite0', caller='/polite') == (['cam'], [])
    assert dispatcher.submit(['cam'], 'polite1', caller='/polite') == (['cam'], [])
    with pytest.raises(OverShare, match='while 1 other caller'):
        dispatcher.submit(['cam'], 'flood9', caller='/flood')
    # Items of nobody's (a watch's renewal, a fused delivery) are bounded by the places alone.
    assert dispatcher.submit(['cam'], 'internal') == ([], ['cam'])


def test_over_its_share_at_one_destination_a_caller_is_still_served_by_the_others(pool):
    recorder = Recorder(stuck={'a', 'b'})
    dispatcher = pool(recorder, workers=2, max_per_destination=5)
    for n in range(4):
        dispatcher.submit(['a'], n, caller='/r')
    assert dispatcher.submit(['a', 'b'], 'next', caller='/r') == (['b'], ['a'])


def test_places_come_back_when_items_are_sent_or_dropped(pool):
    recorder = Recorder()
    dispatcher = pool(recorder, workers=1, max_per_destination=10)
    for n in range(8):
        dispatcher.submit(['cam'], n, caller='/r')
    wait_for(lambda: dispatcher.holding('cam', '/r') == 0, 5, 'every item sent')
    recorder.stuck.add('cam')
    for n in range(8):
        dispatcher.submit(['cam'], n, caller='/r')
    wait_for(lambda: len(recorder.items('cam')) == 9, 5, 'the first of them in flight')
    assert dispatcher.drop('cam') == 7 and dispatcher.holding('cam', '/r') == 1  # the one in flight
    recorder.release.set()
    wait_for(lambda: dispatcher.holding('cam', '/r') == 0, 5, 'the one in flight done')
    assert dispatcher.pending == 0
