"""Rate limiter, retry delay, loop guard and closing cache (no ROS, no sleeps)."""

import doctest
import logging
import math
import threading

import pytest

import drvs.common.retry
from drvs.common.client_cache import ClosingCache
from drvs.common.guard import RESTART, SHUTDOWN, LoopGuard
from drvs.common.retry import retry_delay
from drvs.server.rate_limit import RateLimiter
from drvs.testing import ManualClock

WAIT = 5.0  # seconds any thread event may take before the test fails


# --- RateLimiter -------------------------------------------------------------


def test_burst_then_refusal_with_retry_after():
    clock = ManualClock()
    limiter = RateLimiter(rate=50, burst=100, clock=clock)
    assert [limiter.take('/robot') for _ in range(100)] == [0.0] * 100
    assert limiter.take('/robot') == pytest.approx(0.02)
    assert limiter.take('/robot') == pytest.approx(0.02)  # a refusal takes nothing
    assert limiter.refused == 2


def test_refill_over_time_up_to_burst():
    clock = ManualClock()
    limiter = RateLimiter(rate=10, burst=5, clock=clock)
    for _ in range(5):
        limiter.take('/a')
    clock.now += 0.05
    assert limiter.take('/a') == pytest.approx(0.05)  # half a token there, half to go
    clock.now += 0.05
    assert limiter.take('/a') == 0.0
    assert limiter.take('/a') == pytest.approx(0.1)
    clock.now += 3600  # refills to burst, no further
    assert [limiter.take('/a') for _ in range(5)] == [0.0] * 5
    assert limiter.take('/a') > 0


def test_a_caller_that_waits_retry_after_is_served():
    clock = ManualClock(1234.567)
    limiter = RateLimiter(rate=7, burst=3, clock=clock)
    for _ in range(1000):
        retry_after = limiter.take('/a')
        if retry_after:
            clock.now += retry_after
            assert limiter.take('/a') == 0.0
    assert limiter.refused > 300


def test_keys_are_independent():
    clock = ManualClock()
    limiter = RateLimiter(rate=1, burst=2, clock=clock)
    assert [limiter.take('/a') for _ in range(3)] == [0.0, 0.0, pytest.approx(1.0)]
    assert [limiter.take('/b') for _ in range(2)] == [0.0, 0.0]
    assert limiter.refused == 1
    assert len(limiter) == 2


def test_memory_bounded_by_max_keys():
    clock = ManualClock()
    limiter = RateLimiter(rate=1, burst=10, clock=clock, max_keys=8)
    for n in range(1000):
        assert limiter.take(f'/caller_{n}') == 0.0
        assert len(limiter) <= 8
    assert len(limiter) == 8


def test_keys_forgotten_after_ttl_lose_nothing():
    clock = ManualClock()
    limiter = RateLimiter(rate=2, burst=4, clock=clock)  # ttl = 2 s
    for _ in range(4):
        limiter.take('/a')
    limiter.take('/b')
    assert len(limiter) == 2
    clock.now += 1.99
    assert len(limiter) == 2
    clock.now += 0.01
    assert len(limiter) == 0
    assert [limiter.take('/a') for _ in range(4)] == [0.0] * 4  # full again, as it would have been
    assert limiter.take('/a') == pytest.approx(0.5)


def test_limited_counts_the_callers_that_would_be_refused_now():
    clock = ManualClock()
    limiter = RateLimiter(rate=10, burst=2, clock=clock)
    limiter.take('/a')
    limiter.take('/a')  # empty
    limiter.take('/b')  # one token left
    assert limiter.limited() == 1
    clock.now += 0.05  # /a has half a token
    assert limiter.limited() == 1
    clock.now += 0.05  # /a has one again
    assert limiter.limited() == 0


@pytest.mark.parametrize(
    'rate, burst, max_keys, message',
    [
        (0, 1, 1, 'rate: must be positive, got 0'),
        (-1, 1, 1, 'rate: must be positive, got -1'),
        (float('nan'), 1, 1, 'rate: must be positive, got nan'),
        (1, 0.5, 1, 'burst: must be at least 1, got 0.5'),
        (1, 1, 0, 'max_keys: must be at least 1, got 0'),
    ],
)
def test_rate_limiter_bad_arguments(rate, burst, max_keys, message):
    with pytest.raises(ValueError) as caught:
        RateLimiter(rate=rate, burst=burst, max_keys=max_keys)
    assert str(caught.value) == message


# --- retry_delay --------------------------------------------------------------


def test_retry_delay_doctest():
    result = doctest.testmod(drvs.common.retry)
    assert result.attempted == 4
    assert result.failed == 0


@pytest.mark.parametrize('retry_after', [0.0, 0.01, 0.3, 2.0, 7.0, 60.0])
@pytest.mark.parametrize('attempt', [0, 1, 2, 5, 10, 100, 10_000, 10**18])
@pytest.mark.parametrize('draw', [0.0, 0.25, 0.999, 1.0])
def test_retry_delay_never_early_and_bounded(retry_after, attempt, draw):
    delay = retry_delay(retry_after, attempt, rng=lambda: draw)
    assert retry_after <= delay <= max(retry_after, 5.0) * 1.5


def test_retry_delay_grows_with_attempts_up_to_the_cap():
    delays = [retry_delay(0.0, attempt, rng=lambda: 0.0) for attempt in range(10)]
    assert delays == pytest.approx([0.1, 0.2, 0.4, 0.8, 1.6, 3.2, 5.0, 5.0, 5.0, 5.0])


def test_retry_delay_jitter_range():
    assert retry_delay(1.0, 0, jitter=0.5, rng=lambda: 0.0) == 1.0
    assert retry_delay(1.0, 0, jitter=0.5, rng=lambda: 1.0) == 1.5
    assert retry_delay(1.0, 0, jitter=0.0, rng=lambda: 1.0) == 1.0


@pytest.mark.parametrize('retry_after', [float('nan'), float('inf'), float('-inf'), -3.0])
def test_retry_delay_ignores_bad_hints(retry_after):
    assert retry_delay(retry_after, 2, rng=lambda: 0.0) == pytest.approx(0.4)


@pytest.mark.parametrize(
    'arguments, message',
    [
        ({'attempt': -1}, 'attempt: must not be negative, got -1'),
        ({'base': -0.1}, 'base: must not be negative, got -0.1'),
        ({'cap': float('nan')}, 'cap: must not be negative, got nan'),
        ({'jitter': -1}, 'jitter: must not be negative, got -1'),
    ],
)
def test_retry_delay_bad_arguments(arguments, message):
    arguments = {'retry_after': 0.0, 'attempt': 0} | arguments
    with pytest.raises(ValueError) as caught:
        retry_delay(**arguments)
    assert str(caught.value) == message


def test_retry_delay_default_rng_is_within_bounds():
    for attempt in range(20):
        delay = retry_delay(0.5, attempt)
        assert math.isfinite(delay)
        assert max(0.5, min(5.0, 0.1 * 2**attempt)) <= delay <= 7.5


# --- LoopGuard ----------------------------------------------------------------


class Fatal:
    """An on_fatal that records its calls and signals the first."""

    def __init__(self):
        self.reasons = []
        self.called = threading.Event()

    def __call__(self, reason):
        self.reasons.append(reason)
        self.called.set()


def joined(thread):
    thread.join(WAIT)
    return not thread.is_alive()


def test_loop_that_raises_once_is_restarted_then_finishes(caplog):
    fatal = Fatal()
    guard = LoopGuard(fatal, restart_delay=0)
    runs = []

    def loop():
        runs.append(len(runs))
        if len(runs) == 1:
            raise RuntimeError('first run fails')

    with caplog.at_level(logging.ERROR, logger='rosout.drvs.guard'):
        thread = guard.spawn(loop, 'renewal', RESTART)
        assert joined(thread)
    assert runs == [0, 1]
    assert guard.restarts == {'renewal': 1}
    assert guard.failure is None
    assert fatal.reasons == []
    assert guard.threads == [thread]
    assert thread.daemon and thread.name == 'renewal'


def test_shutdown_loop_failure_is_fatal_once():
    fatal = Fatal()
    stop = threading.Event()
    guard = LoopGuard(fatal, stop=stop)

    def loop():
        return 1 / 0

    first = guard.spawn(loop, 'registration', SHUTDOWN)
    assert fatal.called.wait(WAIT)
    assert joined(first)
    second = guard.spawn(lambda: [][1], 'other', SHUTDOWN)
    assert joined(second)
    reason = 'background loop registration failed: ZeroDivisionError: division by zero'
    assert fatal.reasons == [reason]
    assert guard.failure == reason
    assert stop.is_set()
    assert guard.restarts == {'registration': 0, 'other': 0}


def test_restart_escalates_after_max_restarts_within_window():
    fatal = Fatal()
    clock = ManualClock()
    guard = LoopGuard(fatal, restart_delay=0, max_restarts=2, window=60, clock=clock)
    runs = []

    def loop():
        runs.append(clock.now)
        clock.now += 10
        raise ValueError('bad frame')

    thread = guard.spawn(loop, 'worker', RESTART)
    assert joined(thread)
    assert len(runs) == 3
    assert guard.restarts == {'worker': 2}
    assert fatal.reasons == ['background loop worker failed: ValueError: bad frame (3 failures within 60 s)']
    assert guard.failure == fatal.reasons[0]


def test_failures_spread_beyond_the_window_do_not_escalate():
    fatal = Fatal()
    clock = ManualClock()
    guard = LoopGuard(fatal, restart_delay=0, max_restarts=1, window=60, clock=clock)
    runs = []

    def loop():
        runs.append(clock.now)
        clock.now += 60
        if len(runs) <= 5:
            raise ValueError('now and then')

    thread = guard.spawn(loop, 'worker', RESTART)
    assert joined(thread)
    assert len(runs) == 6
    assert guard.restarts == {'worker': 5}
    assert guard.failure is None
    assert fatal.reasons == []


def test_stop_during_restart_delay_ends_the_thread():
    fatal = Fatal()
    stop = threading.Event()
    guard = LoopGuard(fatal, stop=stop, restart_delay=3600)
    failed = threading.Event()

    def loop():
        failed.set()
        raise OSError('connection refused')

    thread = guard.spawn(loop, 'renewal', RESTART)
    assert failed.wait(WAIT)
    stop.set()
    assert joined(thread)
    assert guard.restarts == {'renewal': 0}
    assert guard.failure is None
    assert fatal.reasons == []


def test_failure_while_stopping_is_not_fatal():
    fatal = Fatal()
    stop = threading.Event()
    guard = LoopGuard(fatal, stop=stop)

    def loop():
        stop.set()
        raise ConnectionError('master went away')

    assert joined(guard.spawn(loop, 'expiry', SHUTDOWN))
    assert guard.failure is None
    assert fatal.reasons == []


def test_traceback_is_logged(caplog):
    guard = LoopGuard(Fatal())

    def failing_loop_body():
        raise KeyError('camera_3')

    with caplog.at_level(logging.ERROR, logger='rosout.drvs.guard'):
        assert joined(guard.spawn(failing_loop_body, 'watch', SHUTDOWN))
    errors = [record for record in caplog.records if record.levelno == logging.ERROR]
    assert len(errors) == 1
    message = errors[0].getMessage()
    assert message.startswith('background loop watch failed:\nTraceback (most recent call last):\n')
    assert 'in failing_loop_body' in message
    assert message.endswith("KeyError: 'camera_3'\n")
    critical = [record.getMessage() for record in caplog.records if record.levelno == logging.CRITICAL]
    assert critical == ["background loop watch failed: KeyError: 'camera_3'; stopping the node"]


def test_system_exit_in_a_loop_is_fatal():
    fatal = Fatal()
    guard = LoopGuard(fatal)
    hooked = []
    previous_hook = threading.excepthook
    threading.excepthook = lambda args: hooked.append(args.exc_type)
    try:

        def loop():
            raise SystemExit(3)

        assert joined(guard.spawn(loop, 'stray_exit', RESTART))
    finally:
        threading.excepthook = previous_hook
    assert hooked == [SystemExit]  # re-raised after failing the node
    assert fatal.reasons == ['background loop stray_exit failed: SystemExit: 3']


def test_on_fatal_that_raises_is_logged(caplog):
    def on_fatal(reason):
        raise RuntimeError('no master')

    guard = LoopGuard(on_fatal)
    with caplog.at_level(logging.ERROR, logger='rosout.drvs.guard'):
        assert joined(guard.spawn(lambda: 1 / 0, 'loop', SHUTDOWN))
    assert guard.failure == 'background loop loop failed: ZeroDivisionError: division by zero'
    assert 'on_fatal failed for: background loop loop failed' in caplog.text
    assert 'RuntimeError: no master' in caplog.text


@pytest.mark.parametrize(
    'arguments, message',
    [
        ({'restart_delay': -1}, 'restart_delay: must not be negative, got -1'),
        ({'max_restarts': -1}, 'max_restarts: must not be negative, got -1'),
        ({'window': 0}, 'window: must be positive, got 0'),
    ],
)
def test_guard_bad_arguments(arguments, message):
    with pytest.raises(ValueError) as caught:
        LoopGuard(Fatal(), **arguments)
    assert str(caught.value) == message


def test_guard_bad_policy():
    with pytest.raises(ValueError) as caught:
        LoopGuard(Fatal()).spawn(lambda: None, 'loop', 'ignore')
    assert str(caught.value) == "policy: must be 'restart' or 'shutdown', got 'ignore'"


# --- ClosingCache -------------------------------------------------------------


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
