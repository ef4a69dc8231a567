"""Which callback services the server trusts without asking the master again (no ROS, no sleeps)."""

import pytest

from drvs.common.status import INVALID, UNAVAILABLE, Refusal
from drvs.server.callback_check import CallbackCheck
from drvs.testing import ManualClock


class Probe:
    """A fake master check: counts its calls; raises ``refusal`` while one is set."""

    def __init__(self):
        self.calls = []
        self.refusal = None

    def __call__(self, service):
        self.calls.append(service)
        if self.refusal is not None:
            raise self.refusal
        return f'rosrpc://{service.strip("/").replace("/", "-")}:{len(self.calls)}'


UNKNOWN = Refusal(INVALID, 'callback_service: /robot/cb is not known to the ROS master')


@pytest.fixture
def clock():
    return ManualClock()


@pytest.fixture
def probe():
    return Probe()


@pytest.fixture
def check(probe, clock):
    return CallbackCheck(probe, cache=5.0, memory=60.0, retry_after=1.0, clock=clock)


def test_a_verified_service_is_trusted_for_the_cache_time_then_probed_again(check, probe, clock):
    check.check('/robot/cb')
    clock.now += 4.9
    check.check('/robot/cb')
    assert probe.calls == ['/robot/cb']
    clock.now += 0.1
    check.check('/robot/cb')
    assert probe.calls == ['/robot/cb'] * 2


def test_an_unknown_service_never_verified_is_invalid(check, probe):
    probe.refusal = UNKNOWN
    with pytest.raises(Refusal) as refused:
        check.check('/robot/cb')
    assert refused.value is UNKNOWN
    with pytest.raises(Refusal):
        check.check('/robot/cb')  # a refusal is not remembered: probed again
    assert len(probe.calls) == 2


def test_a_remembered_service_the_master_no_longer_lists_is_unavailable(check, probe, clock):
    check.check('/robot/cb')
    clock.now += 12.25
    probe.refusal = UNKNOWN
    with pytest.raises(Refusal) as refused:
        check.check('/robot/cb')
    assert (refused.value.status, refused.value.retry_after) == (UNAVAILABLE, 1.0)
    assert refused.value.message == (
        'callback_service: /robot/cb is not known to the ROS master now, though it was 12.2 s ago '
        '(a restarted master?); retry later'
    )


def test_a_service_forgotten_after_the_memory_time_is_invalid_again(check, probe, clock):
    check.check('/robot/cb')
    clock.now += 60.0
    probe.refusal = UNKNOWN
    with pytest.raises(Refusal) as refused:
        check.check('/robot/cb')
    assert refused.value is UNKNOWN


def test_a_master_that_does_not_answer_stays_unavailable(check, probe, clock):
    check.check('/robot/cb')
    clock.now += 10.0
    probe.refusal = Refusal(
        UNAVAILABLE, 'callback_service: cannot check /robot/cb: timed out; retry later', 1.0
    )
    with pytest.raises(Refusal) as refused:
        check.check('/robot/cb')
    assert refused.value is probe.refusal


def test_a_new_verification_starts_the_cache_time_again(check, probe, clock):
    check.check('/robot/cb')
    clock.now += 5.0
    check.check('/robot/cb')
    clock.now += 4.0
    check.check('/robot/cb')
    assert len(probe.calls) == 2


def test_the_memory_is_bounded_in_size_the_oldest_first(probe, clock):
    check = CallbackCheck(probe, cache=5.0, memory=60.0, retry_after=1.0, max_services=2, clock=clock)
    for service in ('/a', '/b', '/c'):
        check.check(service)
        clock.now += 1.0
    assert len(check) == 2
    check.check('/c')
    check.check('/b')
    assert probe.calls == ['/a', '/b', '/c']  # still trusted
    check.check('/a')
    assert probe.calls == ['/a', '/b', '/c', '/a']  # forgotten


def test_the_memory_is_bounded_in_age(check, clock):
    check.check('/a')
    clock.now += 61.0
    check.check('/b')
    assert len(check) == 1


@pytest.mark.parametrize(
    ('cache', 'memory', 'remembered'), [(5.0, 60.0, 60.0), (5.0, 1.0, 5.0), (0.0, 0.0, 1e-3)]
)
def test_a_service_is_remembered_at_least_as_long_as_it_is_trusted(probe, clock, cache, memory, remembered):
    assert CallbackCheck(probe, cache, memory, 1.0, clock=clock).remembered == remembered


def test_without_a_cache_every_check_probes(probe, clock):
    check = CallbackCheck(probe, cache=0.0, memory=60.0, retry_after=1.0, clock=clock)
    check.check('/robot/cb')
    check.check('/robot/cb')
    assert len(probe.calls) == 2


def test_max_services_must_be_positive(probe):
    with pytest.raises(ValueError, match='max_services: must be at least 1, got 0'):
        CallbackCheck(probe, 5.0, 60.0, 1.0, max_services=0)


def test_the_address_the_probe_found_is_kept_with_the_service(check, probe, clock):
    assert check.check('/robot/cb') == 'rosrpc://robot-cb:1'
    clock.now += 4.9
    assert check.check('/robot/cb') == 'rosrpc://robot-cb:1'  # trusted: the address found then
    clock.now += 0.1
    assert check.check('/robot/cb') == 'rosrpc://robot-cb:2'  # probed again: a restarted robot's new one
