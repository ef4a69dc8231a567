"""drvs.common.client_cache: ClosingCache, a bounded cache that closes what it drops (no sleeps)."""

import logging
import threading

import pytest

from drvs.common.client_cache import ClosingCache
from drvs.testing import ManualClock

WAIT = 5.0  # seconds a thread may take before the test fails


def joined(thread):
    thread.join(WAIT)
    return not thread.is_alive()


class Connection:
    """A fake closeable value that counts its closes."""

    def __init__(self, key, fail_close=False):
        self.key = key
        self.closes = 0
        self.fail_close = fail_close

    def close(self):
        self.closes += 1
        if self.fail_close:
            raise OSError(f'socket of {self.key} already gone')


class Factory:
    def __init__(self, fail_close=()):
        self.made = []
        self.fail_close = set(fail_close)
        self._lock = threading.Lock()

    def __call__(self, key):
        connection = Connection(key, fail_close=key in self.fail_close)
        with self._lock:
            self.made.append(connection)
        return connection


@pytest.fixture
def factory():
    return Factory()


def test_factory_called_once_per_key_while_cached(factory):
    cache = ClosingCache(factory, maxsize=4, ttl=10, clock=ManualClock())
    first = cache.get('/a')
    assert cache.get('/a') is first
    assert cache.get('/b') is not first
    assert [connection.key for connection in factory.made] == ['/a', '/b']
    assert len(cache) == 2
    assert '/a' in cache and '/c' not in cache


def test_least_recently_used_is_evicted_and_closed(factory):
    clock = ManualClock()
    cache = ClosingCache(factory, maxsize=2, ttl=10, clock=clock)
    a, b = cache.get('/a'), cache.get('/b')
    cache.get('/a')  # /b is now the least recently used
    c = cache.get('/c')
    assert '/b' not in cache and '/a' in cache and '/c' in cache
    assert (a.closes, b.closes, c.closes) == (0, 1, 0)
    assert cache.evictions == 1
    assert cache.get('/b') is not b  # a new one
    assert a.closes == 1 and b.closes == 1


def test_idle_values_expire_and_are_closed(factory):
    clock = ManualClock()
    cache = ClosingCache(factory, maxsize=10, ttl=5, clock=clock)
    a = cache.get('/a')
    clock.now += 3
    b = cache.get('/b')
    clock.now += 2
    assert cache.expire() == 0  # /a idle exactly ttl: kept
    clock.now += 0.5
    assert cache.expire() == 1
    assert '/a' not in cache and a.closes == 1 and b.closes == 0
    clock.now += 10
    c = cache.get('/c')  # get drops idle values too
    assert list(factory.made) == [a, b, c]
    assert b.closes == 1 and len(cache) == 1
    assert cache.evictions == 2


def test_an_idle_value_is_replaced_not_reused(factory):
    clock = ManualClock()
    cache = ClosingCache(factory, maxsize=10, ttl=5, clock=clock)
    old = cache.get('/a')
    clock.now += 6
    new = cache.get('/a')
    assert new is not old
    assert old.closes == 1 and new.closes == 0


def test_use_refreshes_last_use_time(factory):
    clock = ManualClock()
    cache = ClosingCache(factory, maxsize=10, ttl=5, clock=clock)
    a = cache.get('/a')
    for _ in range(10):
        clock.now += 4
        assert cache.get('/a') is a
    assert cache.expire() == 0
    assert a.closes == 0


def test_pop_and_clear_close_exactly_once(factory):
    cache = ClosingCache(factory, maxsize=10, ttl=5, clock=ManualClock())
    a, b, c = cache.get('/a'), cache.get('/b'), cache.get('/c')
    assert cache.pop('/a') is True
    assert cache.pop('/a') is False
    cache.clear()
    cache.clear()
    assert len(cache) == 0
    assert [connection.closes for connection in (a, b, c)] == [1, 1, 1]
    assert cache.evictions == 0


def test_close_exceptions_are_logged_and_the_cache_goes_on(caplog):
    factory = Factory(fail_close={'/bad'})
    cache = ClosingCache(factory, maxsize=1, ttl=5, clock=ManualClock())
    bad = cache.get('/bad')
    with caplog.at_level(logging.ERROR, logger='rosout.drvs.client_cache'):
        good = cache.get('/good')  # evicts /bad, whose close raises
    assert bad.closes == 1
    assert cache.get('/good') is good and len(cache) == 1
    assert [record.getMessage() for record in caplog.records] == [
        "closing the cached value for '/bad' failed"
    ]
    assert caplog.records[0].exc_info[0] is OSError


def test_a_failing_factory_changes_nothing(factory):
    clock = ManualClock()

    def flaky(key):
        if key == '/broken':
            raise ValueError('bad service name')
        return factory(key)

    cache = ClosingCache(flaky, maxsize=10, ttl=5, clock=clock)
    a = cache.get('/a')
    clock.now += 6
    with pytest.raises(ValueError, match='^bad service name$'):
        cache.get('/broken')
    assert '/broken' not in cache
    assert a.closes == 1  # what the failed get dropped is still closed


def test_custom_close():
    closed = []
    cache = ClosingCache(lambda key: key.upper(), maxsize=1, ttl=5, clock=ManualClock(), close=closed.append)
    cache.get('a')
    cache.get('b')
    assert closed == ['A']


@pytest.mark.parametrize(
    'maxsize, ttl, message',
    [
        (0, 1, 'maxsize: must be at least 1, got 0'),
        (1, 0, 'ttl: must be positive, got 0'),
        (1, float('nan'), 'ttl: must be positive, got nan'),
    ],
)
def test_closing_cache_bad_arguments(maxsize, ttl, message):
    with pytest.raises(ValueError) as caught:
        ClosingCache(Factory(), maxsize=maxsize, ttl=ttl)
    assert str(caught.value) == message


def test_many_threads_keep_the_cache_bounded_and_close_every_eviction(factory):
    cache = ClosingCache(factory, maxsize=16, ttl=3600, clock=ManualClock())
    start = threading.Barrier(6)
    errors = []

    def hammer(worker):
        try:
            start.wait(WAIT)
            for n in range(500):
                cache.get(f'/caller_{worker}_{n % 50}')
                assert len(cache) <= 16
        except BaseException as error:  # reported to the main thread below
            errors.append(error)

    threads = [threading.Thread(target=hammer, args=(worker,)) for worker in range(6)]
    for thread in threads:
        thread.start()
    for thread in threads:
        assert joined(thread)
    assert errors == []
    assert len(cache) == 16
    made = len(factory.made)
    open_ = [connection for connection in factory.made if connection.closes == 0]
    assert len(open_) == 16
    assert all(cache.get(connection.key) is connection for connection in open_)  # these are the cached ones
    assert len(factory.made) == made
    assert all(connection.closes == 1 for connection in factory.made if connection not in open_)
    assert cache.evictions == made - 16
