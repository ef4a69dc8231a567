"""The blind robot's watch schedule: new watches, renewals, regions that move, retries, cancels (no ROS)."""

import doctest
import math

import pytest
from shapely.geometry import box

import drvs.robot.watch_schedule
from drvs.common.status import ACCEPTED, BUSY, INVALID, UNAVAILABLE, UNSUPPORTED
from drvs.robot.mission import request_schedule, watch_schedule
from drvs.robot.params import RobotParams
from drvs.robot.perception import Fix, Region, RegionPolicy
from drvs.robot.poll_schedule import ACCEPT, GIVE_UP, RETRY, Outcome
from drvs.robot.watch_schedule import CANCEL, NEW, REGION, RENEW, WatchCall, WatchSchedule
from drvs.testing import ManualClock

FLOOR = (0.0, 0.0, 7.0, 5.5)
AROUND = (1.0, 1.0, 3.0, 3.0)
ROI = (0.5, 0.5, 6.5, 4.0)
PERIODS = {'self': 0.2, 'station': 2.0, 'obstacle': 0.5, 'human': 0.2}
ROLES = ('self', 'station', 'obstacle', 'human')


def whole(region=FLOOR):
    return Region(region, region)


@pytest.fixture
def clock():
    return ManualClock()


@pytest.fixture
def schedule(clock):
    return WatchSchedule(PERIODS, 10.0, clock=clock, rng=lambda: 0.0)


def accept(schedule, call, granted=None):
    duration = call.duration if granted is None else granted
    return schedule.on_response(call.role, ACCEPTED, duration=duration)


def drain(schedule, clock, respond=accept):
    """Every call due now (stepping over the rate spacing), each answered by ``respond``."""
    calls = []
    while True:
        call = schedule.next_request()
        if call is None:
            wait = schedule.wait_time()
            if wait is None or wait > schedule.min_interval + 1e-9:
                return calls
            clock.now += wait
            continue
        calls.append(call)
        respond(schedule, call)


def test_the_module_example():
    result = doctest.testmod(drvs.robot.watch_schedule)
    assert result.attempted > 0 and result.failed == 0


def test_one_new_watch_per_role_then_nothing_until_its_renewal(schedule, clock):
    assert schedule.next_request() is None and schedule.wait_time() is None  # nothing posted
    schedule.post({'self': whole(), 'station': whole()})
    assert drain(schedule, clock) == [
        WatchCall('self', FLOOR, 0.2, 10.0, NEW),
        WatchCall('station', FLOOR, 2.0, 10.0, NEW),
    ]
    assert (schedule.sent, schedule.standing) == (2, 2)
    for _ in range(5):  # the same regions posted every tick: no call
        clock.now += 0.2
        schedule.post({'self': whole(), 'station': whole()})
        assert schedule.next_request() is None
    assert schedule.sent == 2


def test_renewal_at_half_the_granted_duration(schedule, clock):
    schedule.post({'self': whole(), 'station': whole()})
    start = clock.now
    accept(schedule, schedule.next_request(), granted=2.0)  # the server grants less than asked
    clock.now += 0.1
    accept(schedule, schedule.next_request())
    renewals = []
    for step in range(1, 200):
        clock.now = start + step * 0.05
        call = schedule.next_request()
        if call is not None:
            renewals.append((call.role, call.reason, round(clock.now - start, 2)))
            accept(schedule, call, granted=2.0 if call.role == 'self' else None)
    assert renewals == [
        ('self', RENEW, 1.0),
        ('self', RENEW, 2.0),
        ('self', RENEW, 3.0),
        ('self', RENEW, 4.0),
        ('self', RENEW, 5.0),
        ('station', RENEW, 5.1),  # sent 0.1 s after self: half its granted 10 s later
        ('self', RENEW, 6.0),
        ('self', RENEW, 7.0),
        ('self', RENEW, 8.0),
        ('self', RENEW, 9.0),
    ]
    assert schedule.standing == 2


def test_a_role_that_hears_nothing_of_itself_is_renewed_after_its_keep_alive(clock):
    """With changes_only a robot standing still gets no callback: a renewal asks for a full report."""
    schedule = WatchSchedule({'self': 0.2}, 10.0, keep_alive={'self': 1.25}, clock=clock, rng=lambda: 0.0)
    schedule.post({'self': whole()})  # nothing heard yet (no fix): no keep-alive
    start = clock.now
    accept(schedule, schedule.next_request())
    assert schedule.wait_time() == pytest.approx(5.0)
    clock.now = start + 2.0
    schedule.post({'self': whole()}, heard={'self': start + 1.5})  # a callback 0.5 s ago
    assert schedule.next_request() is None
    assert schedule.wait_time() == pytest.approx(0.75)
    clock.now = start + 2.75
    call = schedule.next_request()
    assert call.reason == RENEW
    accept(schedule, call)
    clock.now = start + 3.5
    assert schedule.next_request() is None  # the renewal was 0.75 s ago: its report may be on its way
    clock.now = start + 4.0
    assert schedule.next_request().reason == RENEW  # still nothing heard: renewed again


def test_a_role_posted_fresh_is_renewed_at_once_and_once(schedule, clock):
    """The robot stopped at its station: a full report taken since confirms the arrival."""
    schedule.post({'self': whole()})
    accept(schedule, schedule.next_request())
    clock.now += 1.0
    schedule.post({'self': whole()}, fresh=('self',))
    call = schedule.next_request()
    assert call.reason == RENEW
    accept(schedule, call)
    clock.now += 1.0
    schedule.post({'self': whole()}, fresh=('self',))
    assert schedule.next_request() is None  # already renewed since it asked
    schedule.post({'self': whole()})  # it drove on...
    clock.now += 1.0
    schedule.post({'self': whole()}, fresh=('self',))  # ...and stopped again
    assert schedule.next_request().reason == RENEW


def test_a_moving_robot_moves_its_watches_seldom(schedule, clock):
    regions = RegionPolicy(
        FLOOR[2:], ('obstacle',), robot_radius=0.2, self_margin=1.0, roi_margin=0.75, fix_timeout=5.0
    )
    station = Fix((6.0, 3.5), box(5.8, 3.35, 6.2, 3.65), 0.0, 1, ('/vs1',))
    sent = []
    for tick in range(100):  # 20 s at 5 ticks a second, driving +x at 0.3 m/s
        clock.now = 100.0 + tick * 0.2
        here = (0.5 + 0.3 * tick * 0.2, 2.0)
        fix = Fix(here, box(here[0] - 0.15, 1.85, here[0] + 0.15, 2.15), clock.now, tick, ('/vs1',))
        schedule.post(regions.regions(clock.now, fix, station, here, velocity=(0.3, 0.0)))
        sent.extend((call.role, call.reason) for call in drain(schedule, clock))
    assert sorted(set(sent)) == [
        ('obstacle', NEW),
        ('obstacle', REGION),
        ('obstacle', RENEW),
        ('self', NEW),
        ('self', REGION),
        ('station', NEW),
        ('station', RENEW),
    ]
    assert sent.count(('self', REGION)) == 4  # 5.9 m: moved 1.25 m ahead each time it came near the edge
    assert sent.count(('obstacle', REGION)) == 1  # the box halved; renewals carry the smaller box too
    assert sent.count(('station', RENEW)) == sent.count(('obstacle', RENEW)) == 3  # every 5 s
    assert len(sent) == 14  # polling: 4 roles, 5 rounds a second, 400 requests


def test_a_box_that_shrinks_a_little_is_kept(schedule, clock):
    schedule.post({'obstacle': Region(ROI, (1.0, 1.0, 6.0, 3.5))})
    accept(schedule, schedule.next_request())
    clock.now += 1.0
    schedule.post({'obstacle': Region((2.0, 0.5, 6.5, 4.0), (2.5, 1.0, 6.0, 3.5))})  # 75 % of its area
    assert schedule.next_request() is None
    schedule.post({'obstacle': Region((4.0, 0.5, 6.5, 4.0), (4.5, 1.0, 6.0, 3.5))})  # 42 %
    assert schedule.next_request() == WatchCall('obstacle', (4.0, 0.5, 6.5, 4.0), 0.5, 10.0, REGION)


def test_a_role_may_keep_its_box_until_it_shrank_further(clock):
    schedule = WatchSchedule({'obstacle': 0.5}, 10.0, shrink={'obstacle': 0.25}, clock=clock, rng=lambda: 0.0)
    schedule.post({'obstacle': Region(ROI, (1.0, 1.0, 6.0, 3.5))})
    accept(schedule, schedule.next_request())
    clock.now += 1.0
    schedule.post({'obstacle': Region((4.0, 0.5, 6.5, 4.0), (4.5, 1.0, 6.0, 3.5))})  # 42 %
    assert schedule.next_request() is None
    schedule.post({'obstacle': Region((5.5, 0.5, 6.5, 4.0), (5.6, 1.0, 6.0, 3.5))})  # 17 %
    assert schedule.next_request() == WatchCall('obstacle', (5.5, 0.5, 6.5, 4.0), 0.5, 10.0, REGION)
    with pytest.raises(ValueError, match=r"shrink\['obstacle'\]: must be in \(0, 1\], got 0"):
        WatchSchedule({'obstacle': 0.5}, 10.0, shrink={'obstacle': 0})


def test_a_temporary_refusal_is_retried_after_retry_after_while_the_old_watch_stands(schedule, clock):
    schedule.post({'self': Region(AROUND, AROUND)})
    accept(schedule, schedule.next_request())
    clock.now += 0.5
    moved = (2.0, 1.0, 4.0, 3.0)
    schedule.post({'self': Region(moved, moved)})
    assert schedule.next_request() == WatchCall('self', moved, 0.2, 10.0, REGION)
    outcome = schedule.on_response('self', BUSY, retry_after=0.3, message='busy')
    assert outcome == Outcome(RETRY, 0.3)
    assert schedule.refused == {'BUSY': 1}
    assert schedule.standing == 1  # the granted watch still stands
    assert schedule.next_request() is None
    assert schedule.wait_time() == pytest.approx(0.3)
    clock.now += 0.3
    assert schedule.next_request() == WatchCall('self', moved, 0.2, 10.0, REGION)
    assert schedule.on_failure('self') == Outcome(RETRY, 0.2)  # backing off: 0.1 s doubled
    assert schedule.failed == 1
    clock.now += 0.2
    assert accept(schedule, schedule.next_request()) == Outcome(ACCEPT)
    clock.now += 0.5
    schedule.post({'self': Region(moved, moved)})
    assert schedule.next_request() is None  # it stands where it should


def test_retries_back_off_up_to_the_cap(clock):
    schedule = WatchSchedule({'self': 0.2}, 10.0, cap=1.0, clock=clock, rng=lambda: 0.0)
    schedule.post({'self': whole()})
    delays = []
    for _ in range(6):
        clock.now += 10.0
        schedule.next_request()
        delays.append(schedule.on_response('self', UNAVAILABLE).delay)
    assert delays == pytest.approx([0.1, 0.2, 0.4, 0.8, 1.0, 1.0])
    assert schedule.standing == 0


def test_an_expired_watch_is_sent_anew(schedule, clock):
    schedule.post({'self': whole()})
    accept(schedule, schedule.next_request(), granted=2.0)
    clock.now += 1.0
    call = schedule.next_request()
    assert call.reason == RENEW
    schedule.on_failure('self')
    clock.now += 1.0  # past the granted 2 s: gone
    assert schedule.standing == 0
    assert schedule.next_request().reason == NEW


@pytest.mark.parametrize('code', [INVALID, UNSUPPORTED], ids=['INVALID', 'UNSUPPORTED'])
def test_a_final_refusal_gives_up_with_the_servers_message(schedule, clock, code):
    schedule.post({'self': whole(), 'station': whole()})
    message = 'period: must be positive, got -1.0'
    schedule.next_request()
    assert schedule.on_response('self', code, message=message) == Outcome(GIVE_UP)
    assert schedule.invalid == ('self', message)
    clock.now += 1.0
    assert schedule.next_request() is None
    assert schedule.wait_time() is None


def test_stop_cancels_every_watch_that_may_stand_once(schedule, clock):
    schedule.post({role: whole() for role in ROLES})
    accept(schedule, schedule.next_request())  # self
    clock.now += 0.1
    accept(schedule, schedule.next_request())  # station
    clock.now += 0.1
    schedule.on_failure(schedule.next_request().role)  # obstacle: it may stand
    clock.now += 0.1
    schedule.on_response(schedule.next_request().role, BUSY, retry_after=1.0)  # human: never granted
    schedule.stop()
    assert not schedule.done
    answers = {'self': ACCEPTED, 'station': UNAVAILABLE, 'obstacle': ACCEPTED}
    cancels = drain(schedule, clock, respond=lambda s, call: s.on_response(call.role, answers[call.role]))
    assert cancels == [
        WatchCall('self', FLOOR, 0.2, 0.0, CANCEL),
        WatchCall('station', FLOOR, 2.0, 0.0, CANCEL),
        WatchCall('obstacle', FLOOR, 0.5, 0.0, CANCEL),
    ]
    assert schedule.done
    assert (schedule.standing, schedule.sent) == (0, 7)
    assert schedule.refused == {'BUSY': 1, 'UNAVAILABLE': 1}  # the refused cancel is not repeated
    clock.now += 20.0
    assert schedule.next_request() is None and schedule.wait_time() is None


def test_a_call_in_flight_at_stop_is_cancelled_after_its_answer(schedule, clock):
    schedule.post({'self': whole()})
    call = schedule.next_request()
    schedule.stop()
    assert schedule.next_request() is None and not schedule.done
    accept(schedule, call)
    clock.now += 0.1
    assert schedule.next_request().reason == CANCEL
    schedule.on_failure('self')  # best effort
    assert schedule.done and schedule.failed == 1


@pytest.mark.parametrize(
    'kwargs, message',
    [
        ({'max_rate': 0}, 'max_rate: must be positive, got 0'),
        ({'periods': {'self': 0.0}}, "periods['self']: must be a positive number of seconds, got 0.0"),
        ({'duration': math.inf}, 'duration: must be a positive number of seconds, got inf'),
        (
            {'keep_alive': {'self': -1.0}},
            "keep_alive['self']: must be a positive number of seconds, got -1.0",
        ),
        ({'keep_alive': {'robot': 1.0}}, 'keep_alive: expected roles of periods (self)'),
        ({'cap': -1.0}, 'cap: must not be negative, got -1.0'),
    ],
)
def test_bad_settings_are_refused(kwargs, message):
    with pytest.raises(ValueError) as error:
        WatchSchedule(**{'periods': {'self': 0.2}, 'duration': 10.0, **kwargs})
    assert str(error.value) == message


def test_a_region_for_a_role_without_a_period_is_refused(schedule):
    with pytest.raises(ValueError) as error:
        schedule.post({'robot': whole()})
    assert str(error.value) == 'regions: no period for role(s) robot'


# -- the robot's watches ---------------------------------------------------------------------------


def test_the_robots_watches():
    schedule = watch_schedule(RobotParams(world='unused.yaml', fused=False), (*ROLES, 'robot'))
    assert schedule.periods == {'self': 0.2, 'station': 2.0, 'obstacle': 0.5, 'human': 0.2, 'robot': 0.2}
    assert (schedule.duration, schedule.keep_alive) == (20.0, {'self': 1.25})
    assert schedule.min_interval == 1 / 40


@pytest.mark.parametrize('roles', [ROLES, (*ROLES, 'robot')], ids=['paper', 'fleet'])
def test_watches_send_ten_times_fewer_calls_than_polling(roles):
    """A mission with the schedules' defaults: a second to find itself and its station, 5.3 m to
    the station at 0.4 m/s (the paper's obstacles world), a second to confirm its arrival, then
    its watches are cancelled. Every call is accepted at once."""
    params = RobotParams(world='unused.yaml')
    clock = ManualClock()
    watches = watch_schedule(params, roles, clock=clock, rng=lambda: 0.0)
    polls = request_schedule(params, clock=clock, rng=lambda: 0.0)
    regions = RegionPolicy(FLOOR[2:], roles[2:], 0.21, params.self_margin, params.roi_margin, 5.0)
    start, goal, speed = (0.8, 2.6), (6.0, 3.5), 0.4
    station = Fix(goal, box(goal[0] - 0.2, goal[1] - 0.15, goal[0] + 0.2, goal[1] + 0.15), 0.0, 1, ('/vs1',))
    driving = math.dist(start, goal) / speed
    ticks = int((1.0 + driving + 1.0) * params.rate)
    for tick in range(ticks):
        now = clock.now = 100.0 + tick / params.rate
        f = min(max(now - 101.0, 0.0) / driving, 1.0)
        moving = 0.0 < f < 1.0
        velocity = tuple(
            moving * speed * (g - s) / math.dist(start, goal) for g, s in zip(goal, start, strict=True)
        )
        here = (start[0] + f * (goal[0] - start[0]), start[1] + f * (goal[1] - start[1]))
        stamp = min(now, 101.0 + driving)  # standing still at the station: no callback
        fix = Fix(here, box(here[0] - 0.15, here[1] - 0.15, here[0] + 0.15, here[1] + 0.15), stamp, 0, ())
        found = tick >= 3
        wanted = regions.regions(now, fix if found else None, station if found else None, here, velocity)
        watches.post(wanted, heard={'self': stamp} if found else None)
        polls.post(
            {role: region.box for role, region in wanted.items()}, found=('self', 'station')[: 2 * found]
        )
        for schedule in (watches, polls):
            drain(schedule, clock, respond=lambda s, call: s.on_response(call.role, ACCEPTED))
    watches.stop()
    cancels = drain(watches, clock, respond=lambda s, call: s.on_response(call.role, ACCEPTED))
    assert sorted(call.role for call in cancels) == sorted(roles)
    assert polls.sent >= 10 * watches.sent, (polls.sent, watches.sent)


def test_after_a_move_to_another_server_every_standing_watch_is_renewed_at_once(schedule, clock):
    """~servers: the robot moved on; its watches stand at the new server without waiting for their renewal."""
    schedule.post({'self': whole(), 'station': whole()})
    drain(schedule, clock)
    clock.now += 1.0
    call = schedule.next_request()
    assert call is None and schedule.wait_time() > 3.0
    schedule.reissue()
    assert schedule.wait_time() == 0.0
    assert [(c.role, c.reason) for c in drain(schedule, clock)] == [('self', RENEW), ('station', RENEW)]
    assert schedule.next_request() is None and schedule.wait_time() > 3.0
