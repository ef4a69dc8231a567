"""drvs.common.rate_limit: the per-caller token bucket, on a manual clock."""

import pytest

from drvs.common.rate_limit import RateLimiter
from drvs.testing import ManualClock


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
