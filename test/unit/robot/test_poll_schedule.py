"""The blind robot's request schedule: rounds, periods, retries, refusals and its request rate (no ROS)."""

import doctest
import logging
import random
from collections import deque

import pytest

import drvs.robot.poll_schedule
from drvs.common.rate_limit import RateLimiter
from drvs.common.status import ACCEPTED, BUSY, INVALID, RATE_LIMITED, UNAVAILABLE, UNSUPPORTED
from drvs.common.status import name as status_name
from drvs.robot.mission import request_schedule
from drvs.robot.params import RobotParams
from drvs.robot.poll_schedule import ACCEPT, GIVE_UP, RETRY, Outcome, Request, RequestSchedule
from drvs.testing import ManualClock

FLOOR = (0.0, 0.0, 3.0, 3.0)
ROI = (0.5, 0.5, 2.5, 2.0)
ALL = {'self': FLOOR, 'station': FLOOR, 'obstacle': ROI, 'human': ROI}
DEFAULTS = RobotParams(world='unused.yaml')


@pytest.fixture
def clock():
    return ManualClock()


@pytest.fixture
def schedule(clock):
    return RequestSchedule(periods={'station': 2.0}, clock=clock, rng=lambda: 0.0)


def drain(schedule, clock, respond=None):
    """Take every request ready now (stepping over the rate spacing); answer each with ``respond(role)``."""
    roles = []
    while True:
        request = schedule.next_request()
        if request is None:
            wait = schedule.wait_time()
            if wait is None or wait > schedule.min_interval + 1e-9:
                return roles
            clock.now += wait
            continue
        roles.append(request.role)
        schedule.on_response(request.role, *(respond or (lambda role: (ACCEPTED,)))(request.role))


def test_the_module_example():
    result = doctest.testmod(drvs.robot.poll_schedule)
    assert result.attempted > 0 and result.failed == 0


# -- rounds --------------------------------------------------------------------------------------


def test_each_role_once_per_round_in_the_round_order(schedule, clock):
    assert schedule.next_request() is None  # nothing posted yet
    assert schedule.wait_time() is None
    schedule.post({'self': FLOOR, 'station': FLOOR})
    assert schedule.next_request() == Request('self', FLOOR, 0)
    assert schedule.next_request() is None  # 1 / max_rate between two requests
    assert schedule.wait_time() == pytest.approx(1 / 40)
    schedule.on_response('self', ACCEPTED)
    clock.now += 1 / 40
    assert schedule.next_request() == Request('station', FLOOR, 0)
    schedule.on_response('station', ACCEPTED)
    clock.now += 1.0
    assert schedule.next_request() is None  # both asked in this round
    assert schedule.wait_time() is None
    schedule.post(ALL)
    assert drain(schedule, clock) == ['obstacle', 'human', 'self', 'station']  # least recently asked first
    assert schedule.sent == 6


def test_a_new_round_replaces_the_old_one_with_its_regions(schedule, clock):
    schedule.post({'self': FLOOR, 'obstacle': ROI})
    newer = (1.0, 1.0, 2.0, 2.0)
    schedule.post({'self': FLOOR, 'obstacle': newer})  # the requester was busy: no backlog
    assert schedule.next_request() == Request('self', FLOOR, 0)
    schedule.on_response('self', ACCEPTED)
    clock.now += 1.0
    assert schedule.next_request() == Request('obstacle', newer, 0)
    schedule.on_response('obstacle', ACCEPTED)
    assert schedule.next_request() is None


def test_a_role_in_flight_is_not_handed_out_twice(schedule, clock):
    schedule.post({'self': FLOOR})
    assert not schedule.in_flight('self')
    assert schedule.next_request().role == 'self'
    assert schedule.in_flight('self')
    clock.now += 1.0
    schedule.post({'self': FLOOR})
    assert schedule.next_request() is None  # still waiting for its response
    schedule.on_response('self', ACCEPTED)
    assert not schedule.in_flight('self')
    assert schedule.next_request().role == 'self'


def test_a_slow_server_delays_every_role_alike(schedule, clock):
    """Acks take 1 s while rounds come every 0.2 s: the least recently asked role goes first."""
    sent = []
    next_post = clock.now
    end = clock.now + 20.0
    while clock.now < end:
        while next_post <= clock.now:
            schedule.post(ALL)
            next_post += 0.2
        request = schedule.next_request()
        if request is None:
            clock.now += 0.01
            continue
        sent.append(request.role)
        clock.now += 1.0
        schedule.on_response(request.role, ACCEPTED)
    assert sent[:8] == ['self', 'station', 'obstacle', 'human'] * 2
    assert {role: sent.count(role) for role in ALL} == {role: 5 for role in ALL}


def test_the_station_is_asked_every_round_until_found_then_once_per_period(schedule, clock):
    asked = []
    for tick in range(40):  # 10 s at 4 rounds/s; found after 1 s
        clock.now = 100.0 + tick * 0.25
        schedule.post({'station': FLOOR}, found=('station',) if tick >= 5 else ())
        request = schedule.next_request()
        if request is not None:
            asked.append(clock.now - 100.0)
            schedule.on_response('station', ACCEPTED)
    assert asked == [0.0, 0.25, 0.5, 0.75, 1.0, 3.0, 5.0, 7.0, 9.0]  # found at 1 s: every 2 s


# -- refusals and failures ----------------------------------------------------------------------


@pytest.mark.parametrize(
    'status, status_name', [(BUSY, 'BUSY'), (RATE_LIMITED, 'RATE_LIMITED'), (UNAVAILABLE, 'UNAVAILABLE')]
)
def test_a_temporary_refusal_puts_the_role_aside_for_retry_after(schedule, clock, status, status_name):
    schedule.post({'self': FLOOR, 'station': FLOOR})
    schedule.next_request()
    outcome = schedule.on_response('self', status, retry_after=0.3, message='try again later')
    assert outcome == Outcome(RETRY, 0.3)
    assert schedule.refused == {status_name: 1}
    assert schedule.invalid is None
    clock.now += 0.05
    assert schedule.next_request().role == 'station'  # other roles go on
    schedule.on_response('station', ACCEPTED)
    clock.now += 0.2
    schedule.post({'self': FLOOR})  # a new round does not hurry the retry
    assert schedule.next_request() is None
    assert schedule.wait_time() == pytest.approx(0.05)
    clock.now += 0.05
    assert schedule.next_request() == Request('self', FLOOR, 1)  # the first retry
    assert schedule.on_response('self', ACCEPTED) == Outcome(ACCEPT)
    schedule.post({'self': FLOOR})
    clock.now += 0.1
    assert schedule.next_request() == Request('self', FLOOR, 0)  # accepted: the count starts again


def test_a_refused_role_waits_for_the_next_round_even_when_its_delay_is_short(schedule, clock):
    schedule.post({'self': FLOOR})
    schedule.next_request()
    schedule.on_response('self', BUSY, retry_after=0.0)
    clock.now += 1.0
    assert schedule.next_request() is None  # once per round, refusals included: no retry storm
    schedule.post({'self': FLOOR})
    assert schedule.next_request().attempt == 1


def test_failures_and_refusals_back_off_exponentially_up_to_the_cap(clock):
    schedule = RequestSchedule(cap=1.0, clock=clock, rng=lambda: 0.0)
    delays = []
    for _ in range(7):
        schedule.post({'self': FLOOR})
        clock.now += 10.0
        assert schedule.next_request() is not None
        delays.append(schedule.on_failure('self').delay)
    assert delays == pytest.approx([0.1, 0.2, 0.4, 0.8, 1.0, 1.0, 1.0])
    assert schedule.failed == 7
    assert schedule.refused == {}


def test_jitter_only_lengthens_the_wait_and_the_servers_hint_beats_the_cap(clock):
    schedule = RequestSchedule(cap=1.0, clock=clock, rng=lambda: 1.0)
    schedule.post({'self': FLOOR})
    schedule.next_request()
    assert schedule.on_failure('self').delay == pytest.approx(0.15)
    schedule.post({'self': FLOOR})
    clock.now += 1.0
    schedule.next_request()
    refused_at = clock.now
    assert schedule.on_response('self', UNAVAILABLE, retry_after=4.0).delay == pytest.approx(6.0)
    schedule.post({'self': FLOOR})
    clock.now = refused_at + 5.99
    assert schedule.next_request() is None
    clock.now = refused_at + 6.0
    assert schedule.next_request().role == 'self'


@pytest.mark.parametrize(
    'code, message',
    [
        (INVALID, 'region_of_interest: x_max 9.0 is beyond the floor'),
        (UNSUPPORTED, "algorithm: no registered vision system runs 'apriltag'; available: colour"),
    ],
    ids=['INVALID', 'UNSUPPORTED'],
)
def test_a_final_refusal_gives_up_for_good_with_the_servers_message(schedule, clock, code, message):
    schedule.post({'self': FLOOR, 'station': FLOOR})
    schedule.next_request()
    assert schedule.on_response('self', code, message=message) == Outcome(GIVE_UP)
    assert schedule.invalid == ('self', message)
    assert schedule.refused == {status_name(code): 1}
    clock.now += 1.0
    schedule.post({'self': FLOOR, 'station': FLOOR})
    assert schedule.next_request() is None
    assert schedule.wait_time() is None


def test_an_unknown_status_is_retried_and_warned_about_once(schedule, clock, caplog):
    caplog.set_level(logging.WARNING, logger='rosout.drvs.request_schedule')
    for _ in range(3):
        schedule.post({'self': FLOOR})
        clock.now += 10.0
        schedule.next_request()
        assert schedule.on_response('self', 9, retry_after=0.5).action == RETRY
    assert schedule.refused == {'status 9': 3}
    assert schedule.invalid is None
    assert [r.getMessage() for r in caplog.records] == [
        'DRVS answered with unknown status 9; retrying it later'
    ]


def test_stop_ends_the_requests(schedule, clock):
    schedule.post(ALL)
    schedule.stop()
    assert schedule.next_request() is None
    assert schedule.wait_time() is None


@pytest.mark.parametrize(
    'kwargs, message',
    [
        ({'max_rate': 0}, 'max_rate: must be positive, got 0'),
        ({'periods': {'station': -1.0}}, "periods['station']: must be positive, got -1.0"),
        ({'cap': -1.0}, 'cap: must not be negative, got -1.0'),
        ({'base': -0.1}, 'base: must not be negative, got -0.1'),
    ],
)
def test_bad_settings_are_refused(kwargs, message):
    with pytest.raises(ValueError) as error:
        RequestSchedule(**kwargs)
    assert str(error.value) == message


# -- the request rate against the server's limit --------------------------------------------------


def respond_always(status, retry_after=0.0):
    return lambda rng, role: (status, retry_after)


def respond_at_random(rng, role):
    return rng.choice([(ACCEPTED, 0.0), (BUSY, 0.5), (RATE_LIMITED, 0.02), (UNAVAILABLE, 1.0), (7, 0.0)])


def respond_alternately():
    refused = set()

    def respond(rng, role):
        refused.symmetric_difference_update({role})
        return (BUSY, 0.0) if role in refused else (ACCEPTED, 0.0)

    return lambda rng, role: respond(rng, role)


def simulate(params, respond, seconds=60.0, latency=0.0, seed=1):
    """Send times of the requests the robot's schedule makes in ``seconds`` of simulated time.

    Rounds of all four roles are posted at ``params.rate`` (the station never found: the most
    requests); a single requester answers each request ``latency`` seconds after sending it.
    """
    clock = ManualClock()
    rng = random.Random(seed)
    schedule = request_schedule(params, clock=clock, rng=rng.random)
    start, sent = clock.now, []
    next_post, busy_until, in_flight = clock.now, None, None
    while clock.now < start + seconds:
        if next_post <= clock.now:
            schedule.post(ALL)
            next_post += 1.0 / params.rate
        if in_flight is not None and clock.now >= busy_until:
            response = respond(rng, in_flight)
            if response is None:
                schedule.on_failure(in_flight)
            else:
                schedule.on_response(in_flight, *response)
            in_flight = None
        if in_flight is None:
            request = schedule.next_request()
            if request is not None:
                sent.append(clock.now - start)
                in_flight, busy_until = request.role, clock.now + latency
                continue
        clock.now += 0.001
    return sent


def assert_under_the_servers_limit(sent, seconds=60.0):
    limiter_clock = ManualClock()
    limiter = RateLimiter(rate=50, burst=100, clock=limiter_clock)  # the server's defaults
    for t in sent:
        limiter_clock.now = t
        assert limiter.take('/robot') == 0.0, f'rate limited at {t:.3f} s'
    assert len(sent) / seconds < 50
    window = deque()
    for t in sent:  # and in every second, not just on average
        window.append(t)
        while window[0] <= t - 1.0:
            window.popleft()
        assert len(window) <= 50, f'{len(window)} requests in the second before {t:.3f} s'


@pytest.mark.parametrize(
    'respond, at_most',
    [
        (respond_always(ACCEPTED), 20.0),
        (respond_always(BUSY, 0.0), 20.0),
        (respond_always(RATE_LIMITED, 0.02), 20.0),
        (lambda rng, role: None, 20.0),  # every call fails (server down)
        (respond_at_random, 20.0),
        (respond_alternately(), 20.0),
    ],
    ids=['accepted', 'busy', 'rate-limited', 'failing', 'random', 'alternating'],
)
def test_default_parameters_stay_under_the_servers_rate_limit(respond, at_most):
    assert (DEFAULTS.rate, DEFAULTS.max_request_rate) == (5.0, 40.0)
    sent = simulate(DEFAULTS, respond)
    assert len(sent) / 60.0 <= at_most + 0.1  # four roles, five rounds a second
    assert_under_the_servers_limit(sent)


def test_retries_only_lower_the_rate():
    accepted = len(simulate(DEFAULTS, respond_always(ACCEPTED)))
    assert len(simulate(DEFAULTS, respond_always(BUSY, 0.0))) < accepted / 4
    assert len(simulate(DEFAULTS, lambda rng, role: None)) < accepted / 4


@pytest.mark.parametrize('latency', [0.0, 0.01])
def test_a_fast_control_loop_is_held_to_max_request_rate(latency):
    params = RobotParams(world='unused.yaml', rate=100.0)  # 400 role requests a second wanted
    sent = simulate(params, respond_always(ACCEPTED), seconds=10.0, latency=latency)
    assert len(sent) / 10.0 <= params.max_request_rate + 0.1
    assert_under_the_servers_limit(sent, seconds=10.0)
