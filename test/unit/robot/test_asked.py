"""Which floor the robot asked its obstacle roles about and heard back on (no ROS)."""

import doctest

import pytest

import drvs.robot.asked
from drvs.robot.asked import NOTHING, AskedFloor, inside, intersection

ROLES = ('obstacle', 'human')


def both(floor, region, now, vision_systems=2):
    for role in ROLES:
        floor.accepted(role, region, now - 0.05, now, vision_systems)


def test_nothing_is_known_before_every_role_was_answered():
    floor = AskedFloor(ROLES, settle=0.5)
    assert floor.known(0.0) is NOTHING
    floor.accepted('obstacle', (0, 0, 4, 3), sent=0.95, now=1.0, vision_systems=1)
    assert floor.known(5.0) is NOTHING  # human never asked
    floor.accepted('human', (1, 0, 5, 3), sent=4.95, now=5.0, vision_systems=1)
    assert floor.known(5.4) is NOTHING
    assert floor.known(5.5) == (1, 0, 4, 3)  # what both roles were asked about


def test_answers_are_in_once_every_vision_system_called_back_or_after_settle():
    floor = AskedFloor(ROLES, settle=0.5)
    both(floor, (0, 0, 4, 3), now=1.0)
    floor.heard('obstacle', '/vs1', 0.9)  # frames taken before the call was sent: for the old region
    floor.heard('obstacle', '/vs1', 0.96)
    floor.heard('human', '/vs1', 1.1)
    floor.heard('human', '/vs2', 1.2)
    assert floor.known(1.2) is NOTHING  # vs2 not heard about obstacles yet
    floor.heard('obstacle', '/vs2', 1.2)
    assert floor.known(1.2) == (0, 0, 4, 3)


def test_a_call_that_reached_no_vision_system_is_answered_at_once():
    floor = AskedFloor(ROLES, settle=0.5)
    both(floor, (0, 0, 4, 3), now=1.0, vision_systems=0)
    assert floor.known(1.0) == (0, 0, 4, 3)


def test_while_a_new_region_waits_only_what_it_keeps_of_the_answered_one_is_known():
    floor = AskedFloor(ROLES, settle=0.5)
    both(floor, (0, 0, 4, 3), now=1.0)
    assert floor.known(2.0) == (0, 0, 4, 3)
    both(floor, (2, 0, 6, 3), now=3.0)  # the watch moved east
    assert floor.known(3.1) == (2, 0, 4, 3)
    assert (floor.region('obstacle'), floor.region('human')) == ((2, 0, 6, 3), (2, 0, 6, 3))
    assert floor.known(3.5) == (2, 0, 6, 3)


def test_polling_a_new_region_every_tick_keeps_the_newest_answered_one():
    floor = AskedFloor(ROLES, settle=0.5)
    for tick in range(10):  # a region a little smaller each 0.2 s
        both(floor, (tick * 0.1, 0, 4, 3), now=tick * 0.2)
    assert floor.known(1.9) == (0.9, 0, 4, 3)  # the newest, asked at 1.8: its part of the one of 1.4
    assert floor.known(2.3) == (0.9, 0, 4, 3)


def test_boxes():
    assert intersection((0, 0, 2, 2), (1, 1, 3, 3)) == (1, 1, 2, 2)
    assert intersection((0, 0, 1, 1), (2, 2, 3, 3)) is NOTHING
    assert inside(NOTHING, (0, 0, 1, 1)) and not inside((0, 0, 1, 1), NOTHING)


def test_a_negative_settle_is_refused():
    with pytest.raises(ValueError, match='settle: must be >= 0 seconds, got -1'):
        AskedFloor(ROLES, settle=-1)


def test_doctests():
    assert doctest.testmod(drvs.robot.asked).failed == 0
