"""When a vision system registers, renews, moves and unregisters (no ROS, no sleeps: a manual clock)."""

import doctest

import pytest

import drvs.vision.registration
from drvs.common.status import BUSY, INVALID, RATE_LIMITED, UNAVAILABLE
from drvs.testing import ManualClock
from drvs.vision.registration import (
    DEFAULT_LEASE,
    MOVE,
    REGISTER,
    RENEW,
    UNREGISTER,
    Registration,
    RegistrationReport,
)

FLOOR = [(0.0, 0.0), (2.0, 0.0), (2.0, 1.0), (0.0, 1.0)]
WAITING = 'waiting for the field of view (CameraInfo, tf and a frame)'
STALE = 'no field of view to register: the camera feed is stale or it sees no floor'


def shifted(footprint, dx):
    return [(x + dx, y) for x, y in footprint]


@pytest.fixture
def clock():
    return ManualClock(100.0)


@pytest.fixture
def registration(clock):
    return Registration(move_threshold=0.01, retry_period=1.0, clock=clock, rng=lambda: 0.0)


def register(registration, footprint=FLOOR, lease=10.0):
    attempt = registration.due(footprint)
    registration.accepted(attempt, lease)
    return attempt


def test_doctests():
    assert doctest.testmod(drvs.vision.registration).failed == 0


def test_nothing_is_registered_while_the_field_of_view_is_unknown_and_the_report_says_why(registration):
    assert registration.due(None) is None
    assert registration.report() == RegistrationReport(False, '', WAITING)
    assert registration.due([]) is None  # nothing to unregister either
    assert registration.report() == RegistrationReport(False, '', STALE)
    assert registration.farewell() is None


def test_registers_once_known_then_renews_at_half_the_lease(registration, clock):
    attempt = registration.due(FLOOR)
    assert (attempt.what, attempt.footprint, attempt.at) == (REGISTER, FLOOR, 100.0)
    clock.now += 0.2  # the call took this long
    registration.accepted(attempt, 8.0)
    assert registration.lease == 8.0
    assert registration.report() == RegistrationReport(True, '', '')
    clock.now = 103.99  # half the lease after the attempt was decided, not after the answer
    assert registration.due(FLOOR) is None
    clock.now = 104.0
    renewal = registration.due(FLOOR)
    assert renewal.what == RENEW
    registration.accepted(renewal, 0.0)  # no lease said: the last one still holds
    assert registration.lease == 8.0
    clock.now = 108.0
    assert registration.due(FLOOR).what == RENEW


def test_a_lease_not_renewed_runs_out_counted_from_the_answer(registration, clock):
    attempt = registration.due(FLOOR)
    clock.now += 0.5  # the call took this long
    registration.accepted(attempt, 8.0)
    clock.now = 108.49
    assert registration.report().registered
    clock.now = 108.5
    assert not registration.report().registered


def test_without_a_lease_from_the_server_it_renews_every_half_default_lease(registration, clock):
    register(registration, lease=0.0)
    assert registration.lease is None
    clock.now += DEFAULT_LEASE / 2 - 0.01
    assert registration.due(FLOOR) is None
    clock.now += 0.01
    assert registration.due(FLOOR).what == RENEW
    clock.now = 100.0 + DEFAULT_LEASE - 0.01
    assert registration.report().registered


@pytest.mark.parametrize(
    'new, what',
    [
        (shifted(FLOOR, 0.005), None),  # within ~move_threshold: not a move
        (shifted(FLOOR, 0.02), MOVE),
        (FLOOR[:3], MOVE),  # another number of vertices
    ],
)
def test_a_field_of_view_that_moved_beyond_the_threshold_is_registered_at_once(
    registration, clock, new, what
):
    register(registration)
    clock.now += 0.1
    attempt = registration.due(new)
    assert (attempt and attempt.what) == what
    if attempt:
        assert attempt.footprint == new


def test_a_move_is_measured_from_what_the_server_holds(registration, clock):
    register(registration)
    clock.now += 0.1
    assert registration.due(shifted(FLOOR, 0.006)) is None
    assert registration.due(shifted(FLOOR, 0.012)).what == MOVE  # 0.012 from the registered one


def test_an_empty_field_of_view_unregisters_and_a_returning_one_registers_again(registration, clock):
    register(registration)
    clock.now += 1.0
    attempt = registration.due([])
    assert (attempt.what, attempt.footprint) == (UNREGISTER, [])
    registration.accepted(attempt, 10.0)
    assert registration.report() == RegistrationReport(False, '', STALE)
    clock.now += 20.0
    assert registration.due([]) is None  # nothing to renew while it stays empty
    assert registration.farewell() is None
    assert registration.due(FLOOR).what == REGISTER


def test_a_clean_stop_unregisters_what_is_registered(registration, clock):
    register(registration)
    clock.now += 1.0
    farewell = registration.farewell()
    assert (farewell.what, farewell.footprint) == (UNREGISTER, [])
    registration.accepted(farewell, 10.0)
    assert not registration.report().registered and registration.farewell() is None


@pytest.mark.parametrize(
    'status, name', [(BUSY, 'BUSY'), (RATE_LIMITED, 'RATE_LIMITED'), (UNAVAILABLE, 'UNAVAILABLE')]
)
def test_a_temporary_refusal_is_retried_after_the_servers_retry_after(registration, clock, status, name):
    attempt = registration.due(FLOOR)
    registration.refused(attempt, status, 'ejected: try later', 2.5)
    assert registration.report() == RegistrationReport(False, name, 'ejected: try later')
    clock.now = 102.49
    assert registration.due(FLOOR) is None
    clock.now = 102.5
    retry = registration.due(FLOOR)
    assert retry.what == REGISTER
    registration.accepted(retry, 10.0)
    assert registration.report() == RegistrationReport(True, '', '')


def test_a_permanent_refusal_is_retried_every_retry_period(registration, clock):
    attempt = registration.due(FLOOR)
    registration.refused(attempt, INVALID, 'field_of_view: not a simple polygon', 0.0)
    assert registration.report() == RegistrationReport(
        False, 'INVALID', 'field_of_view: not a simple polygon'
    )
    clock.now = 100.99
    assert registration.due(FLOOR) is None
    clock.now = 101.0
    assert registration.due(FLOOR).what == REGISTER


def test_no_answer_backs_off_growing_up_to_the_retry_period(registration, clock):
    waits = []
    for _ in range(6):
        attempt = registration.due(FLOOR)
        registration.unanswered(attempt, 'no server at /drvs/register_vision_service')
        start = clock.now
        while registration.due(FLOOR) is None:
            clock.now = round(clock.now + 0.01, 2)
        waits.append(round(clock.now - start, 2))
    assert waits == [0.1, 0.2, 0.4, 0.8, 1.0, 1.0]
    assert registration.report() == RegistrationReport(
        False, '', 'no server at /drvs/register_vision_service'
    )


def test_jitter_only_lengthens_the_wait(clock):
    registration = Registration(0.01, 1.0, clock=clock, rng=lambda: 1.0)
    attempt = registration.due(FLOOR)
    registration.refused(attempt, BUSY, 'busy', 2.0)
    clock.now = 102.99
    assert registration.due(FLOOR) is None
    clock.now = 103.0  # 2 s and half again
    assert registration.due(FLOOR) is not None


def test_a_success_resets_the_backoff(registration, clock):
    for _ in range(3):
        registration.unanswered(registration.due(FLOOR), 'timeout')
        clock.now += 1.0
    register(registration)
    clock.now += 5.0
    registration.unanswered(registration.due(FLOOR), 'timeout')
    clock.now += 0.1
    assert registration.due(FLOOR).what == RENEW  # the first backoff again: 0.1 s


def test_a_failed_renewal_keeps_the_lease_it_holds_until_it_ends(registration, clock):
    register(registration, lease=10.0)
    clock.now = 105.0
    renewal = registration.due(FLOOR)
    registration.refused(renewal, BUSY, 'busy', 1.0)
    assert registration.report() == RegistrationReport(True, 'BUSY', 'busy')
    clock.now = 109.99
    assert registration.report().registered
    clock.now = 110.0
    assert not registration.report().registered
