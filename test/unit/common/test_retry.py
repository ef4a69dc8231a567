"""drvs.common.retry: the delay before a retry (never before retry_after, bounded, jittered)."""

import doctest
import math

import pytest

import drvs.common.retry
from drvs.common.retry import retry_delay


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
