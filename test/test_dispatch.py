"""The forwarding pool: one in flight per destination, bounded queues, stuck ones hold one worker."""

import threading

import pytest

from drvs.dispatch import Busy, Dispatcher
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
