"""Keeping clear of the other robots: velocities, swept floor, who gives way (no ROS)."""

import doctest
import math

import pytest
from shapely.geometry import Point, box

import drvs.robot.traffic
from drvs.robot.traffic import Mover, MoverTracker, Yielding, clear_of_people, closest_approach, swept


def square(x, y, half=0.15):
    return box(x - half, y - half, x + half, y + half)


def test_the_tracker_estimates_each_robots_velocity_from_its_successive_outlines():
    tracker = MoverTracker(smoothing=1.0)
    assert [m.velocity for m in tracker.update(0.0, [square(1, 1), square(4, 1)])] == [(0, 0), (0, 0)]
    movers = tracker.update(0.2, [square(4, 0.9), square(1.1, 1)])  # in another order
    assert [m.velocity for m in movers] == [pytest.approx((0.0, -0.5)), pytest.approx((0.5, 0.0))]
    (still,) = tracker.update(0.2, [square(4, 0.9)])  # nothing new seen since: one of them is forgotten
    assert still.velocity == pytest.approx((0.0, -0.5))
    (far,) = tracker.update(0.4, [square(2.5, 3.0)])  # nothing that near before: standing
    assert far.velocity == (0.0, 0.0)


def test_the_tracker_smooths_and_caps_and_takes_given_velocities():
    tracker = MoverTracker(smoothing=0.5, max_speed=1.0)
    tracker.update(0.0, [square(1, 1)])
    (mover,) = tracker.update(0.1, [square(1.05, 1)])
    assert mover.velocity == pytest.approx((0.25, 0.0))  # half of 0.5 m/s, half of standing
    (mover,) = tracker.update(0.2, [square(1.35, 1)])
    assert mover.speed == pytest.approx(1.0)  # (3 + 0.25) / 2 m/s, capped
    (given,) = tracker.update(0.3, [square(1.4, 1)], velocities=[(0.0, 0.3)])  # a fused track's
    assert given.velocity == (0.0, 0.3)


def test_a_moving_robot_sweeps_the_floor_ahead_of_it():
    area = swept(square(1, 1), (0.5, 0.0), 1.0)
    assert area.bounds == pytest.approx((0.85, 0.85, 1.65, 1.15))
    assert swept(square(1, 1), (0.0, 0.0), 1.0).equals(square(1, 1))


def test_closest_approach():
    assert closest_approach((2.0, 0.0), (1.0, 0.0), 3.0) == (0.0, 2.0)  # moving apart: now
    assert closest_approach((2.0, 0.0), (-1.0, 0.0), 1.0) == (1.0, 1.0)  # not within the horizon
    assert closest_approach((1.0, 1.0), (0.0, 0.0), 1.0) == (0.0, math.sqrt(2))


def yielding(patience=1.0):
    return Yielding(horizon=1.5, distance=0.47, patience=patience)


@pytest.mark.parametrize(
    'me, other, gives_way',
    [
        # Catching up with a slower robot ahead: this one gives way, not the one ahead.
        (((0, 0), (0.5, 0)), ((0.5, 0), (0.2, 0)), True),
        (((0.5, 0), (0.2, 0)), ((0, 0), (0.5, 0)), False),
        # Crossing: the one driving into the other's way gives way.
        (((0, 0), (0.5, 0)), ((0.6, -0.3), (0.0, 0.3)), True),
        (((0.6, -0.3), (0.0, 0.3)), ((0, 0), (0.5, 0)), False),
        # Head on, as fast as each other: both do.
        (((0, 0), (0.5, 0)), ((0.8, 0), (-0.5, 0)), True),
        (((0.8, 0), (-0.5, 0)), ((0, 0), (0.5, 0)), True),
        # Nobody gives way to a robot standing still (the map holds it).
        (((0, 0), (0.5, 0)), ((0.6, 0), (0.0, 0)), False),
    ],
    ids=['catching-up', 'ahead', 'crossing-into', 'crossed', 'head-on', 'head-on-other', 'standing'],
)
def test_who_gives_way(me, other, gives_way):
    (p, v), (q, w) = me, other
    rule = yielding()
    mover = Mover(square(*q), w)
    assert rule.gives_way(p, v, mover) == gives_way
    assert (rule.step(0.0, p, v, [mover]) is mover) == gives_way


def test_no_conflict_no_yield():
    rule = yielding()
    passing = Mover(square(0.5, 1.0), (0.0, 0.5))  # a metre beside, driving away
    assert rule.conflict((0, 0), (0.5, 0), [passing]) is None
    assert rule.step(0.0, (0, 0), (0.5, 0), [passing]) is None


def test_it_gives_way_while_the_conflict_lasts_and_waits_for_a_robot_standing_still_patience_at_most():
    rule = yielding(patience=1.0)
    other = Mover(square(0.8, 0), (-0.5, 0))
    assert rule.step(0.0, (0, 0), (0.5, 0), [other]) is other
    # The other gives way too: while it stands, the conflict is judged as it drove.
    stopped = Mover(square(0.78, 0), (0.0, 0))
    assert rule.step(0.5, (0, 0), (0.5, 0), [stopped]) is stopped
    assert rule.step(1.0, (0, 0), (0.5, 0), [stopped]) is stopped
    assert rule.step(1.6, (0, 0), (0.5, 0), [stopped]) is None  # it stood over 1 s: drive on
    assert rule.step(1.7, (0.05, 0), (0.5, 0), [stopped]) is None  # round it, until that conflict is over
    assert rule.step(1.8, (0.1, 0), (0.5, 0), []) is None
    assert rule.step(1.9, (0.1, 0), (0.5, 0), [other]) is other  # a new conflict
    assert rule.yields == 2


def test_it_waits_as_long_as_the_robot_it_gives_way_to_drives_by():
    rule = yielding(patience=0.5)
    held = []
    for step in range(30):  # 3 s: the other drives north across its way, 0.8 m ahead
        other = Mover(square(0.8, -0.8 + 0.05 * step), (0.0, 0.5))
        held.append(rule.step(step * 0.1, (0, 0), (0.5, 0.0), [other]) is other)
    waited = held.index(False)
    assert waited > 10 and not any(held[waited:])  # longer than its patience, then drives on
    assert rule.yields == 1


def crossing_run(first_patience, second_patience, seconds=12.0, period=0.1):
    """Two robots driving straight across each other's way, each seeing the other's true position
    and velocity; (the smallest distance between them, how often each gave way, where they end)."""
    robots = [
        {'at': (0.0, 0.0), 'to': (4.0, 0.0), 'rule': yielding(first_patience)},
        {'at': (2.0, -2.0), 'to': (2.0, 2.0), 'rule': yielding(second_patience)},
    ]
    closest = math.inf
    for step in range(int(seconds / period)):
        now = step * period
        wanted = []
        for robot in robots:
            dx, dy = robot['to'][0] - robot['at'][0], robot['to'][1] - robot['at'][1]
            norm = math.hypot(dx, dy)
            wanted.append((0.5 * dx / norm, 0.5 * dy / norm) if norm > 0.05 else (0.0, 0.0))
        commands = []
        for i, robot in enumerate(robots):
            other = robots[1 - i]
            mover = Mover(square(*other['at']), other.get('velocity', (0.0, 0.0)))
            yielded = robot['rule'].step(now, robot['at'], wanted[i], [mover])
            commands.append((0.0, 0.0) if yielded else wanted[i])
        for robot, (vx, vy) in zip(robots, commands, strict=True):
            robot['at'] = (robot['at'][0] + vx * period, robot['at'][1] + vy * period)
            robot['velocity'] = (vx, vy)
        closest = min(closest, math.dist(robots[0]['at'], robots[1]['at']))
    return closest, [r['rule'].yields for r in robots], [r['at'] for r in robots]


def test_two_robots_crossing_at_the_same_time_keep_apart_and_both_arrive():
    # Both reach the crossing together: a tie, both give way; the one with less patience goes first.
    closest, yields, ends = crossing_run(1.0, 1.5)
    assert closest > 0.47
    assert yields[0] >= 1 and yields[1] >= 1
    assert Point(ends[0]).distance(Point(4.0, 0.0)) < 0.1 and Point(ends[1]).distance(Point(2.0, 2.0)) < 0.1


def test_doctests():
    assert doctest.testmod(drvs.robot.traffic).failed == 0


def test_a_robot_in_a_persons_way_steps_out_even_when_the_first_second_is_still_in_their_margin():
    walker = Mover(box(0.8, -0.2, 1.2, 0.2), (-0.35, 0.0))  # coming west along y = 0
    margin = 0.8  # the person's way and the margin round it, all y < 0.8: not free in the map

    def free(point):
        return abs(point[1]) >= margin

    velocity, person = clear_of_people((0.0, 0.1), (0.0, 0.0), [walker], 0.2, 2.0, (0.0, -0.5), free)
    assert velocity == (0.0, 0.5) and person is walker  # aside, north: free two seconds on
    stuck, _ = clear_of_people((0.0, 0.1), (0.0, 0.0), [walker], 0.2, 2.0, (0.0, -0.5), lambda p: False)
    assert stuck != (0.0, 0.5)  # nowhere free to go: no stepping aside
