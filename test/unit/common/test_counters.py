"""drvs.common.counters: counts since start and over the last period (no ROS)."""

import doctest
import threading

import pytest

import drvs.common.counters
from drvs.common.counters import OTHER, PeriodCounts


def test_doctests():
    result = doctest.testmod(drvs.common.counters)
    assert result.attempted > 0 and result.failed == 0


def test_each_period_counts_only_what_came_since_the_last():
    counts = PeriodCounts()
    counts.add('BUSY')
    counts.add('BUSY', 2)
    assert counts.take_period() == {'BUSY': 3}
    counts.add('RATE_LIMITED')
    assert counts.take_period() == {'RATE_LIMITED': 1}
    assert counts.take_period() == {}
    assert counts.totals() == {'BUSY': 3, 'RATE_LIMITED': 1}


def test_names_beyond_max_keys_count_as_other():
    counts = PeriodCounts(max_keys=2)
    for key in ('a', 'b', 'c', 'd', 'a'):
        counts.add(key)
    assert counts.totals() == {'a': 2, 'b': 1, OTHER: 2}
    assert counts.take_period() == {'a': 2, 'b': 1, OTHER: 2}


def test_threads_lose_no_count():
    counts = PeriodCounts()
    taken = []

    def add():
        for _ in range(1000):
            counts.add('x')

    threads = [threading.Thread(target=add) for _ in range(4)]
    for thread in threads:
        thread.start()
    while any(thread.is_alive() for thread in threads):
        taken.append(counts.take_period().get('x', 0))
    for thread in threads:
        thread.join()
    taken.append(counts.take_period().get('x', 0))
    assert sum(taken) == counts.totals()['x'] == 4000


def test_max_keys_must_be_positive():
    with pytest.raises(ValueError) as raised:
        PeriodCounts(max_keys=0)
    assert str(raised.value) == 'max_keys: must be at least 1, got 0'
