"""The robot's map building: outlines per source -> the cost grid, without the robot, its trail and
its station; forgetting, lingering and when ``~map`` is due (no ROS, a manual clock)."""

import doctest
import math

import pytest
from shapely.geometry import Point, box

import drvs.robot.mapping
from drvs.robot.dstar_lite import FREE
from drvs.robot.mapping import (
    BODY_MARGIN,
    MAX_CELLS,
    OWN_TRAIL,
    MapBuilder,
    OwnTrail,
    grid_resolution,
    own_body,
)
from drvs.robot.occupancy import LETHAL
from drvs.robot.perception import Fix
from drvs.testing import ManualClock

FLOOR = (4.0, 3.0)
SIZE = (0.3, 0.3)
RADIUS = 0.2
TTL, LINGER = 1.5, 0.5


def fix_at(position, stamp=0.0, heading=None, half=0.15):
    x, y = position
    outline = box(x - half, y - half, x + half, y + half)
    return Fix(position, outline, stamp, 1, ('/vs1',), heading)


def builder(roles=('obstacle', 'human'), map_period=1.0, **options):
    return MapBuilder(FLOOR, SIZE, RADIUS, roles, TTL, LINGER, map_period, resolution=0.05, **options)


def lethal_at(mapping, point):
    spec = mapping.grid.spec
    return mapping.grid.costs[spec.cell_of(point)] == LETHAL


def test_the_module_example():
    result = doctest.testmod(drvs.robot.mapping)
    assert result.attempted > 0 and result.failed == 0


def test_the_default_grid_is_5_cm_unless_the_floor_would_need_more_than_max_cells():
    assert grid_resolution((7.0, 5.5)) == 0.05  # the paper's floor: 15,400 cells
    resolution = grid_resolution((24.0, 14.0))  # the warehouse
    assert resolution == 0.1 and (24.0 / resolution) * (14.0 / resolution) <= MAX_CELLS
    assert MapBuilder((24.0, 14.0), SIZE, RADIUS, (), TTL, LINGER, 1.0).grid.spec.resolution == 0.1
    assert MapBuilder((24.0, 14.0), SIZE, RADIUS, (), TTL, LINGER, 1.0, 0.2).grid.spec.resolution == 0.2


def test_an_obstacle_reported_goes_into_the_grid_and_the_map_is_due():
    clock = ManualClock()
    mapping = builder()
    mapping.observe('obstacle', '/vs1', [box(2.0, 1.0, 2.4, 1.4)], clock.now)
    update = mapping.update(clock.now, fix_at((0.5, 0.5)), fix_at((3.5, 2.5)))
    assert update.changes and update.publish
    assert mapping.obstacles == 1 and lethal_at(mapping, (2.2, 1.2))
    assert {cell for cell, _ in update.changes} == {
        tuple(int(i) for i in cell) for cell in zip(*(mapping.grid.costs != FREE).nonzero(), strict=True)
    }
    clock.now += 0.2
    again = mapping.update(clock.now, fix_at((0.5, 0.5)), fix_at((3.5, 2.5)))
    assert (again.changes, again.publish) == ([], False)


def test_outlines_seen_by_two_vision_systems_are_one_obstacle():
    mapping = builder()
    mapping.observe('obstacle', '/vs1', [box(2.0, 1.0, 2.4, 1.4)], 0.0)
    mapping.observe('obstacle', '/vs2', [box(2.1, 1.1, 2.5, 1.5)], 0.0)
    mapping.observe('human', '/vs2', [box(1.0, 2.0, 1.2, 2.2)], 0.0)
    mapping.update(0.0, None, None)
    assert mapping.obstacles == 2


def test_the_robot_and_its_station_are_never_obstacles():
    mapping = builder()
    robot, station = fix_at((0.5, 0.5)), fix_at((3.5, 2.5))
    mapping.observe('obstacle', '/vs1', [robot.outline, station.outline.buffer(0.02)], 0.0)
    mapping.observe('human', '/vs1', [box(2.0, 1.0, 2.4, 1.4)], 0.0)
    mapping.update(0.0, robot, station)
    assert mapping.obstacles == 1
    assert not lethal_at(mapping, (0.5, 0.5)) and not lethal_at(mapping, (3.5, 2.5))


def test_a_tagged_robots_whole_body_is_cut_out_not_just_its_tag():
    tag = fix_at((1.0, 1.0), heading=math.pi / 4, half=0.05)  # a tag smaller than the robot
    body = own_body(tag, SIZE)
    assert body.area == pytest.approx(box(0, 0, *SIZE).buffer(BODY_MARGIN).area)
    assert body.contains(Point(1.0, 1.27))  # a corner of the yawed body (unyawed: 1.23 at most)
    assert own_body(fix_at((1.0, 1.0)), SIZE) is None  # no heading: the outline is the body
    assert own_body(None, SIZE) is None
    mapping = builder()
    mapping.observe('human', '/vs1', [box(0.85, 0.85, 1.15, 1.15)], 0.0)  # motion finds the robot moving
    mapping.update(0.0, tag, None)
    assert mapping.obstacles == 0


def test_another_robot_touching_this_one_keeps_its_own_part():
    """The fleet's ``robot`` model sees both robots as one blob: this one's body is cut out."""
    mapping = builder(roles=('obstacle', 'robot'))
    me = fix_at((1.0, 1.0))
    mapping.observe('robot', '/vs1', [box(0.85, 0.85, 1.55, 1.15)], 0.0)  # me and a robot at x 1.4
    mapping.update(0.0, me, None)
    assert mapping.obstacles == 1
    assert lethal_at(mapping, (1.45, 1.0)) and not lethal_at(mapping, (1.0, 1.0))
    plain = builder()
    plain.observe('obstacle', '/vs1', [box(0.85, 0.85, 1.55, 1.15)], 0.0)
    plain.update(0.0, me, None)
    assert plain.obstacles == 0  # another model's blob, mostly the robot (and its trail), is dropped whole


def test_other_robots_keep_a_clearance_over_the_floor_they_sweep_and_have_a_velocity():
    mapping = MapBuilder(FLOOR, SIZE, RADIUS, ('robot',), TTL, LINGER, 1.0, 0.05, clearance=0.1, horizon=1.0)
    me = fix_at((0.5, 0.5))
    mapping.observe('robot', '/vs1', [box(1.85, 1.35, 2.15, 1.65)], 0.0)
    mapping.update(0.0, me, None)
    mapping.observe('robot', '/vs1', [box(1.95, 1.35, 2.25, 1.65)], 0.2)  # 0.5 m/s east
    mapping.update(0.2, me, None)
    (other,) = mapping.movers
    assert other.velocity == pytest.approx((0.25, 0.0))  # half the new estimate (smoothing)
    # Its body, 0.25 m further east (a second at its speed), 0.1 m more round it: lethal.
    assert lethal_at(mapping, (2.45, 1.5)) and lethal_at(mapping, (2.1, 1.73))
    assert not lethal_at(mapping, (2.68, 1.5))


def test_fused_the_other_robots_velocities_are_their_tracks_and_nothing_is_merged():
    mapping = MapBuilder(
        FLOOR, SIZE, RADIUS, ('robot',), TTL, LINGER, 1.0, 0.05, horizon=1.0, fused=('robot',)
    )
    me = fix_at((0.5, 0.5))
    # The server's one callback: this robot's track (cut out), another robot's, moving north.
    tracks = [box(0.35, 0.35, 0.65, 0.65), box(1.85, 1.35, 2.15, 1.65)]
    mapping.observe('robot', '/drvs', tracks, 0.0, velocities=[(0.3, 0.0), (0.0, 0.5)])
    mapping.update(0.0, me, None)
    (other,) = mapping.movers
    assert other.velocity == (0.0, 0.5) and other.position == pytest.approx((2.0, 1.5))
    assert lethal_at(mapping, (2.0, 2.1)) and not lethal_at(mapping, (2.0, 2.25))  # its next second
    mapping.observe('robot', '/drvs', [], 0.5, velocities=[])  # gone: lingers, its velocity too
    mapping.update(0.5, me, None)
    assert [m.velocity for m in mapping.movers] == [(0.0, 0.5)]


def test_a_walking_person_holds_the_floor_it_sweeps_but_nobody_gives_way_to_it():
    mapping = MapBuilder(
        FLOOR, SIZE, RADIUS, ('human',), TTL, LINGER, 1.0, 0.05, horizon=1.0, fused=('human',)
    )
    mapping.observe('human', '/drvs', [box(1.8, 1.3, 2.2, 1.7)], 0.0, velocities=[(-0.4, 0.0)])
    mapping.update(0.0, fix_at((0.5, 0.5)), None)
    assert lethal_at(mapping, (1.45, 1.5)) and not lethal_at(mapping, (1.3, 1.5))  # 0.4 m west of it
    assert mapping.movers == []  # only robots give way to robots


def test_the_robots_own_motion_is_not_swept_ahead_of_it():
    mapping = MapBuilder(
        FLOOR, SIZE, RADIUS, ('human',), TTL, LINGER, 1.0, 0.05, horizon=1.0, fused=('human',)
    )
    me = fix_at((1.0, 1.0))
    # A motion model's blob of this robot driving east, larger than its outline: not dropped, not swept.
    mapping.observe('human', '/drvs', [box(0.7, 0.7, 1.6, 1.3)], 0.0, velocities=[(0.4, 0.0)])
    mapping.update(0.0, me, None)
    assert lethal_at(mapping, (1.55, 1.0)) and not lethal_at(mapping, (1.8, 1.0))


def test_where_the_robot_believes_it_is_is_no_obstacle_when_its_fix_is_late():
    mapping = builder()
    late = fix_at((1.0, 1.0))
    mapping.observe('human', '/vs1', [box(1.85, 0.85, 2.15, 1.15)], 0.0)  # motion finds it moving, 1 m on
    mapping.update(0.0, late, None)
    assert mapping.obstacles == 1
    mapping.update(0.1, late, None, position=(2.0, 1.0))
    assert mapping.obstacles == 0


def test_the_robots_ghost_where_it_stood_is_not_an_obstacle_for_a_while():
    clock = ManualClock(0.0)
    mapping = builder()
    mapping.update(clock.now, fix_at((1.0, 1.0)), None)  # it stood here...
    clock.now += 1.0
    ghost = [box(0.9, 0.9, 1.1, 1.1)]  # ...and a background model reports the floor it uncovered
    mapping.observe('human', '/vs1', ghost, clock.now)
    mapping.update(clock.now, fix_at((2.0, 1.0), clock.now), None)
    assert mapping.obstacles == 0
    clock.now += OWN_TRAIL  # the trail forgets where it stood; a ghost still reported is in the way
    mapping.observe('human', '/vs1', ghost, clock.now)
    mapping.update(clock.now, fix_at((2.0, 1.0), clock.now), None)
    assert mapping.obstacles == 1


def test_the_trail_remembers_new_positions_for_keep_seconds():
    trail = OwnTrail(radius=0.1, keep=4.0)
    assert trail.update(0.0, None).is_empty
    trail.update(0.0, fix_at((1.0, 1.0)))
    shape = trail.update(1.0, fix_at((2.0, 1.0)))
    assert shape.contains(Point(1.0, 1.0)) and shape.contains(Point(2.0, 1.0))
    assert trail.update(2.0, fix_at((2.0, 1.0))) is shape  # the same fix again: nothing to redo
    later = trail.update(4.5, None)
    assert not later.contains(Point(1.0, 1.0)) and later.contains(Point(2.0, 1.0))
    assert trail.update(5.5, None).is_empty


def test_a_source_not_heard_from_within_ttl_is_forgotten():
    clock = ManualClock(0.0)
    mapping = builder()
    mapping.observe('obstacle', '/vs1', [box(2.0, 1.0, 2.4, 1.4)], clock.now)
    mapping.update(clock.now, None, None)
    clock.now += TTL
    assert mapping.update(clock.now, None, None).changes == []
    clock.now += 0.01
    update = mapping.update(clock.now, None, None)
    assert update.changes and mapping.obstacles == 0 and not lethal_at(mapping, (2.2, 1.2))


def test_an_obstacle_reported_gone_lingers_a_little():
    clock = ManualClock(0.0)
    mapping = builder()
    mapping.observe('human', '/vs1', [box(2.0, 1.0, 2.4, 1.4)], clock.now)
    clock.now += 0.5
    mapping.observe('human', '/vs1', [], clock.now)  # a person who stopped fades out of a motion model
    mapping.update(clock.now + LINGER, None, None)
    assert mapping.obstacles == 1
    mapping.update(clock.now + LINGER + 0.01, None, None)
    assert mapping.obstacles == 0


def test_the_map_goes_out_at_most_once_per_period_while_it_changes():
    mapping = builder(map_period=1.0)
    published = []
    for tick in range(20):
        now = tick * 0.1
        mapping.observe('obstacle', '/vs1', [box(1.0 + 0.1 * tick, 1.0, 1.3 + 0.1 * tick, 1.3)], now)
        if mapping.update(now, None, None).publish:
            published.append(now)
    assert published == pytest.approx([0.0, 1.0])


def test_elevation_around_the_robot_keeps_the_obstacle_it_touches():
    """elevation finds the robot, its station and a cart it stands against as one region: the
    robot and station are cut out, the cart's part stays (a colour model's blob would be dropped)."""
    mapping = builder(roles=('obstacle',), cut_roles=('obstacle',))
    me, station = fix_at((1.0, 1.0)), fix_at((3.5, 2.5))
    merged = box(0.85, 0.85, 1.55, 1.15)  # me and a cart from x 1.2 to 1.55
    mapping.observe('obstacle', '/vs1', [merged, station.outline.buffer(0.02)], 0.0)
    mapping.update(0.0, me, station)
    assert mapping.obstacles == 1
    assert lethal_at(mapping, (1.5, 1.0)) and not lethal_at(mapping, (1.0, 1.0))
    assert not lethal_at(mapping, (3.5, 2.5))


# -- heights: what the robot drives under, and the other robots in elevation's regions ------------------
ELEVATION = ('obstacle', 'robot')
CUT = dict(roles=ELEVATION, cut_roles=ELEVATION)
SHELF = box(2.0, 0.5, 2.5, 2.5)  # a shelf 0.45 m high across the floor


def test_a_shelf_with_room_for_the_robot_is_no_obstacle_and_cuts_a_top_only_view_of_it():
    """vs1 saw floor under it (clearance 0.35 m, the robot is 0.2 m high: 0.25 needed); vs2 saw only
    its top (0: unknown), a few centimetres off: its outline loses vs1's, rim and all."""
    mapping = builder(robot_height=0.2, **CUT)
    mapping.observe('obstacle', '/vs1', [SHELF], 0.0, levels=[(0.45, 0.35)])
    mapping.observe('obstacle', '/vs2', [box(1.97, 0.48, 2.53, 2.52)], 0.0, levels=[(0.46, 0.0)])
    mapping.update(0.0, fix_at((0.5, 0.5)), None)
    assert (mapping.obstacles, mapping.passable) == (0, 1)
    assert not (mapping.grid.costs == LETHAL).any()


@pytest.mark.parametrize(
    'level, why',
    [((0.45, 0.2), 'as high as the robot: no room to spare'), ((0.45, 0.0), 'nobody saw under it')],
)
def test_a_shelf_without_room_for_the_robot_is_an_obstacle(level, why):
    mapping = builder(robot_height=0.2, **CUT)
    mapping.observe('obstacle', '/vs1', [SHELF], 0.0, levels=[level])
    mapping.update(0.0, fix_at((0.5, 0.5)), None)
    assert lethal_at(mapping, (2.25, 1.5)), why


def test_a_higher_outline_over_a_shelf_is_something_else_and_stays():
    """vs2's outline reaches 1 m: the shelf merged with a box on it or beside it. Not cut."""
    mapping = builder(robot_height=0.2, **CUT)
    mapping.observe('obstacle', '/vs1', [SHELF], 0.0, levels=[(0.45, 0.35)])
    mapping.observe('obstacle', '/vs2', [box(2.0, 0.5, 2.5, 3.0)], 0.0, levels=[(1.0, 0.0)])
    mapping.update(0.0, fix_at((0.5, 0.5)), None)
    assert lethal_at(mapping, (2.25, 1.5)) and lethal_at(mapping, (2.25, 2.8))


def test_by_default_the_robot_drives_under_nothing():
    mapping = builder(**CUT)
    mapping.observe('obstacle', '/vs1', [SHELF], 0.0, levels=[(2.0, 1.8)])
    mapping.update(0.0, fix_at((0.5, 0.5)), None)
    assert lethal_at(mapping, (2.25, 1.5))


def test_a_shelf_the_robot_is_under_stays_passable_though_its_camera_now_sees_the_robot_under_it():
    """Once the robot is under it (or in front of it), the camera that proved room under the shelf
    sees the robot as part of it, standing on the floor: the earlier proof cuts that outline,
    but not an outline of it that does not hold the robot (something else came under it)."""
    clock = ManualClock()
    mapping = builder(robot_height=0.2, **CUT)
    mapping.observe('obstacle', '/vs1', [SHELF], clock.now, levels=[(0.45, 0.35)])
    mapping.update(clock.now, fix_at((0.5, 1.5)), None)
    clock.now += 3.0
    under = fix_at((2.2, 1.5), stamp=clock.now)
    mapping.observe('obstacle', '/vs1', [SHELF], clock.now, levels=[(0.45, 0.0)])
    mapping.update(clock.now, under, None)
    assert (mapping.obstacles, mapping.passable) == (0, 0)  # cut by the proof, not passable now
    clock.now += 5.0  # the robot's trail has left the shelf too
    mapping.observe('obstacle', '/vs1', [SHELF], clock.now, levels=[(0.45, 0.0)])
    mapping.update(clock.now, fix_at((0.5, 2.8), stamp=clock.now), None)
    assert lethal_at(mapping, (2.25, 1.5))


def test_other_robots_are_cut_out_of_elevations_regions_where_they_are_and_were():
    """elevation finds the other robot as a static region, standing until its camera reports again:
    the fleet's outline of it, now and in the last seconds, is cut out; a box it touches stays."""
    clock = ManualClock()
    mapping = builder(**CUT)
    me = fix_at((0.5, 0.5))
    other = box(1.85, 1.35, 2.15, 1.65)
    crate = box(2.15, 1.3, 2.6, 1.7)
    mapping.observe('robot', '/drvs', [other], clock.now)
    mapping.observe('obstacle', '/vs1', [other.union(crate)], clock.now, levels=[(0.5, 0.0)])
    mapping.update(clock.now, me, None)
    assert lethal_at(mapping, (2.4, 1.5))  # the crate
    clock.now += 1.0  # the other robot drove off north; elevation's old region of it stands
    mapping.observe('robot', '/drvs', [box(1.85, 2.35, 2.15, 2.65)], clock.now)
    mapping.update(clock.now, me, None)
    assert lethal_at(mapping, (2.4, 1.5)) and lethal_at(mapping, (2.0, 2.5))
    assert not lethal_at(mapping, (1.95, 1.5))  # no ghost where it stood
    without = builder(roles=('obstacle',), cut_roles=('obstacle',))  # no fleet model: it stays
    without.observe('obstacle', '/vs1', [other], 0.0)
    without.update(0.0, me, None)
    assert lethal_at(without, (2.0, 1.5))


def test_a_person_walking_over_the_robots_trail_is_still_a_person():
    clock = ManualClock(0.0)
    mapping = MapBuilder(
        FLOOR, SIZE, RADIUS, ('human',), TTL, LINGER, 1.0, 0.05, horizon=1.0, fused=('human',)
    )
    for x in (1.0, 1.3, 1.6):  # the robot drives east along y = 1.0: its trail
        clock.now += 0.5
        mapping.update(clock.now, fix_at((x, 1.0), clock.now), None)
    # A walker coming south, a third of its outline on the floor the robot has just left.
    walker = box(1.05, 1.05, 1.35, 1.35)
    mapping.observe('human', '/drvs', [walker], clock.now, velocities=[(0.0, -0.3)])
    mapping.update(clock.now, fix_at((1.6, 1.0), clock.now), None)
    assert [p.velocity for p in mapping.people] == [(0.0, -0.3)]
