"""The blind robot's mission rules: which robot and schedule, what a round posts, callback stamps,
coverage timeout and exit codes (no ROS, a manual clock)."""

import doctest
import math

import pytest
from shapely.geometry import box
from test_poll_schedule import drain as drain_requests
from test_watch_schedule import drain

import drvs.robot.mission
from drvs.common.status import ACCEPTED, INVALID, UNAVAILABLE, UNSUPPORTED
from drvs.robot.controller import ARRIVED, ARRIVING, BLOCKED, FAILED, LOCALISING, MOVING
from drvs.robot.mission import (
    FAIL,
    MAX_STAMP_AGE,
    SKIP,
    USE,
    Coverage,
    MissionEnd,
    callback_stamp,
    fleet_robot,
    fused_outcome,
    fused_role,
    mission_end,
    obstacle_memory_ttl,
    post_round,
    request_schedule,
    schedule_for,
    watch_schedule,
)
from drvs.robot.params import RobotParams
from drvs.robot.perception import Fix, Region
from drvs.robot.poll_schedule import RequestSchedule
from drvs.robot.watch_schedule import NEW, RENEW, WatchSchedule
from drvs.sim.world import WorldError
from drvs.sim.world_file import load_world
from drvs.testing import ManualClock

ROLES = ('self', 'station', 'obstacle', 'human')
FLOOR = (0.0, 0.0, 7.0, 5.5)
ROI = (0.5, 0.5, 6.5, 4.0)
REGIONS = {
    'self': Region(FLOOR, FLOOR),
    'station': Region(FLOOR, FLOOR),
    'obstacle': Region(ROI, ROI),
    'human': Region(ROI, ROI),
}
PARAMS = RobotParams(world='unused.yaml')


def fix_at(position, stamp):
    x, y = position
    return Fix(position, box(x - 0.15, y - 0.15, x + 0.15, y + 0.15), stamp, 1, ('/vs1',))


def test_the_module_examples():
    result = doctest.testmod(drvs.robot.mission)
    assert result.attempted > 0 and result.failed == 0


# -- which robot, which schedule ---------------------------------------------------------------------
def test_the_robot_drives_the_worlds_robot_named_as_its_node_or_its_only_one():
    paper, fleet = load_world('worlds/localisation.yaml'), load_world('worlds/crossing.yaml')
    assert fleet_robot(paper, None, '/anything').name == 'robot'
    assert fleet_robot(fleet, None, '/robot2').name == 'robot2'
    assert fleet_robot(fleet, 'robot1', '/robot2').name == 'robot1'
    robot2 = fleet_robot(fleet, None, '/robot2')
    assert set(robot2.colour_models) == {'self', 'station', 'obstacle', 'human', 'robot'}
    with pytest.raises(WorldError) as error:
        fleet_robot(fleet, None, '/robot')
    assert "no entry named 'robot' (known: robot1, robot2)" in str(error.value)


def test_requests_watch_asks_with_a_watch_schedule_on_the_given_clock():
    clock = ManualClock(50.0)
    schedule = schedule_for(PARAMS, ROLES, clock)
    assert isinstance(schedule, WatchSchedule) and schedule.clock is clock
    assert schedule.periods == {'self': 0.2, 'station': 2.0, 'obstacle': 0.5, 'human': 0.5}  # human fused
    per_camera = schedule_for(RobotParams(world='unused.yaml', fused=False), ROLES, clock)
    assert per_camera.periods == {'self': 0.2, 'station': 2.0, 'obstacle': 0.5, 'human': 0.2}


def test_requests_poll_asks_like_the_paper_with_a_request_schedule():
    schedule = schedule_for(RobotParams(world='unused.yaml', requests='poll'), ROLES, ManualClock())
    assert isinstance(schedule, RequestSchedule)
    assert schedule.periods == {'station': 2.0}


# -- what a round posts ------------------------------------------------------------------------------
def test_a_round_asks_for_each_role_in_its_region_until_the_mission_is_over():
    clock = ManualClock()
    schedule = watch_schedule(PARAMS, ROLES, clock=clock, rng=lambda: 0.0)
    post_round(schedule, REGIONS, None, None, LOCALISING)
    calls = drain(schedule, clock)
    assert sorted((call.role, call.reason) for call in calls) == sorted((role, NEW) for role in ROLES)
    assert {call.role: call.region_of_interest for call in calls} == {r: REGIONS[r].box for r in ROLES}
    post_round(schedule, REGIONS, None, None, FAILED)
    assert sorted(call.role for call in drain(schedule, clock)) == sorted(ROLES)  # cancelled
    assert schedule.done


def test_a_robot_that_heard_nothing_of_itself_renews_its_own_watch():
    clock = ManualClock()
    schedule = watch_schedule(PARAMS, ROLES, clock=clock, rng=lambda: 0.0)
    fix = fix_at((1.0, 1.0), clock.now)
    post_round(schedule, REGIONS, fix, None, MOVING)
    drain(schedule, clock)
    clock.now += 1.0
    post_round(schedule, REGIONS, fix, None, MOVING)
    assert drain(schedule, clock) == []
    clock.now += 0.3  # a quarter of ~fix_timeout (1.25 s) since the fix's frames
    post_round(schedule, REGIONS, fix, None, MOVING)
    assert [(call.role, call.reason) for call in drain(schedule, clock)] == [('self', RENEW)]


def test_a_robot_stopped_at_its_station_asks_for_a_full_report_of_itself():
    clock = ManualClock()
    schedule = watch_schedule(PARAMS, ROLES, clock=clock, rng=lambda: 0.0)
    post_round(schedule, REGIONS, None, None, MOVING)
    drain(schedule, clock)
    clock.now += 0.2
    post_round(schedule, REGIONS, None, None, BLOCKED)
    assert drain(schedule, clock) == []
    post_round(schedule, REGIONS, None, None, ARRIVING)
    assert [(call.role, call.reason) for call in drain(schedule, clock)] == [('self', RENEW)]


def test_polling_asks_for_a_found_station_once_per_station_period():
    clock = ManualClock()
    schedule = request_schedule(PARAMS, clock=clock, rng=lambda: 0.0)
    station = fix_at((6.0, 3.5), clock.now)
    post_round(schedule, REGIONS, None, station, LOCALISING)
    first = schedule.next_request()
    assert first.region_of_interest == REGIONS[first.role].box
    schedule.on_response(first.role, ACCEPTED)
    assert sorted([first.role, *drain_requests(schedule, clock)]) == sorted(ROLES)
    clock.now += 0.2
    post_round(schedule, REGIONS, None, station, LOCALISING)
    assert sorted(drain_requests(schedule, clock)) == ['human', 'obstacle', 'self']
    clock.now += 2.0
    post_round(schedule, REGIONS, None, station, LOCALISING)
    assert 'station' in drain_requests(schedule, clock)
    post_round(schedule, REGIONS, None, station, ARRIVED)
    assert drain_requests(schedule, clock) == [] and schedule.done


# -- callback stamps ---------------------------------------------------------------------------------
@pytest.mark.parametrize(
    'stamp, kept',
    [
        (9.5, True),  # half a second old: the frames' time
        (10.0 - MAX_STAMP_AGE + 0.01, True),
        (10.0 - MAX_STAMP_AGE, False),  # too old to be believed
        (10.03, True),  # a little ahead: another host's clock
        (10.06, False),  # in the future
        (0.0, False),  # no stamp
    ],
)
def test_a_callback_stamp_in_the_future_or_too_old_is_replaced_by_its_arrival(stamp, kept):
    assert callback_stamp(stamp, 10.0) == (stamp if kept else 10.0)


# -- coverage ----------------------------------------------------------------------------------------
NOT_COVERED = 'no vision system covers the robot: DRVS forwarded its self request to none for 5.0 s'


def test_a_robot_no_vision_system_ever_covered_fails_fix_timeout_after_its_start():
    clock = ManualClock(100.0)
    coverage = Coverage(timeout=5.0, started_at=clock.now)
    assert coverage.failure(clock.now + 60.0) is None  # no answer yet: the fix timeout's business
    clock.now += 3.0
    coverage.accepted('self', 0, clock.now)
    assert not coverage.covered
    assert coverage.failure(105.0) is None
    assert coverage.failure(105.01) == NOT_COVERED


def test_a_robot_that_was_covered_fails_fix_timeout_after_it_no_longer_is():
    clock = ManualClock(100.0)
    coverage = Coverage(timeout=5.0, started_at=clock.now)
    coverage.accepted('self', 2, clock.now)
    assert coverage.covered
    clock.now += 10.0
    coverage.accepted('self', 0, clock.now)
    clock.now += 3.0
    coverage.accepted('self', 0, clock.now)  # still none: counted from the first
    assert coverage.failure(115.0) is None
    assert coverage.failure(115.01) == NOT_COVERED
    coverage.accepted('self', 1, clock.now)  # covered again
    assert coverage.failure(200.0) is None


def test_only_the_robots_own_role_counts_for_coverage():
    coverage = Coverage(timeout=5.0, started_at=0.0)
    coverage.accepted('obstacle', 0, 1.0)
    coverage.accepted('station', 3, 1.0)
    assert coverage.failure(100.0) is None
    assert not coverage.covered
    assert coverage.vision_systems == {'obstacle': 0, 'station': 3}


# -- exit codes --------------------------------------------------------------------------------------
CRASH = 'background loop control failed: KeyError: 1'


@pytest.mark.parametrize(
    'once, crash, state, end',
    [
        (True, None, ARRIVED, MissionEnd(0)),
        (False, None, ARRIVED, MissionEnd(0)),
        (True, None, FAILED, MissionEnd(1, 'no fix')),
        (False, None, FAILED, MissionEnd(0, 'no fix')),  # a server-like node: failing is not a crash
        (True, CRASH, ARRIVED, MissionEnd(1, CRASH)),  # a crashed loop is a failure, with or without ~once
        (False, CRASH, MOVING, MissionEnd(1, CRASH)),
        (True, None, MOVING, MissionEnd(1, early=True)),  # Ctrl-C before the station
        (True, None, None, MissionEnd(1, early=True)),  # never started
        (False, None, MOVING, MissionEnd(0)),
    ],
)
def test_the_exit_code(once, crash, state, end):
    assert mission_end(once, crash, state, 'no fix' if state == FAILED else '') == end


@pytest.mark.parametrize(
    'status, outcome', [(ACCEPTED, USE), (INVALID, FAIL), (UNSUPPORTED, FAIL), (UNAVAILABLE, SKIP), (9, SKIP)]
)
def test_a_fused_callback_is_used_skipped_or_fails_the_mission_by_its_status(status, outcome):
    assert fused_outcome(status) == outcome


@pytest.mark.parametrize(
    'requests, fused, ttl', [('poll', True, 1.5), ('watch', False, 20.0), ('watch', True, math.inf)]
)
def test_obstacle_outlines_stand_as_long_as_their_source_may_stay_silent(requests, fused, ttl):
    params = RobotParams(
        world='w.yaml', requests=requests, fused=fused, obstacle_ttl=1.5, watch_duration=20.0
    )
    assert obstacle_memory_ttl(params) == ttl
    assert fused_role(params, 'human') is fused and not fused_role(params, 'self')
