"""Perception bookkeeping: request ids, superseded and repeated answers, watch answers, merging,
the region-of-interest policy."""

import math

import pytest
from shapely.geometry import box

from drvs.robot.perception import (
    WATCH,
    Fix,
    Perception,
    PerceptionError,
    Region,
    RegionPolicy,
    cut_bodies,
    exclude_bodies,
    merge_outlines,
    spanned,
    whole_floor,
)

MODELS = {
    'self': 'colour:0,150,0,80,255,80',
    'station': 'colour:0,0,150,80,80,255',
    'obstacle': 'colour:40,40,40,90,90,90',
    'human': 'colour:150,0,0,255,80,80',
}


def square(cx, cy, half=0.15):
    return [(cx - half, cy - half), (cx + half, cy - half), (cx + half, cy + half), (cx - half, cy + half)]


@pytest.fixture
def perception():
    return Perception(MODELS)


def answer(perception, role, seq, vs, *outlines, stamp=1.0):
    return perception.accept(MODELS[role], f'{role}-{seq}', vs, stamp, list(outlines))


def test_request_ids_count_per_role(perception):
    assert [perception.requests.issue('self') for _ in range(2)] == ['self-1', 'self-2']
    assert perception.requests.issue('human') == 'human-1'
    assert perception.requests.parse('self-2') == ('self', 2)


def test_the_same_robot_seen_by_two_cameras_is_one_fix_at_its_centre(perception):
    perception.requests.issue('self')
    answer(perception, 'self', 1, '/vs1', square(1.0, 1.0), stamp=2.0)
    answer(perception, 'self', 1, '/vs2', square(1.02, 1.0), stamp=2.2)  # slightly different projection
    fix = perception.fix('self')
    assert fix.position == pytest.approx((1.01, 1.0))
    assert fix.vision_systems == ('/vs1', '/vs2')
    assert fix.stamp == pytest.approx(2.1)


def test_fused_the_server_answers_once_with_objects_merged_already_and_their_velocities():
    fused = Perception(MODELS, '/robot', fused=('self', 'station'))
    fused.requests.watch_id('self')
    # One callback from the server: the robot (a track moving east) and something green touching it.
    found = fused.accept(
        MODELS['self'], '/robot/self', '/drvs', 2.0, [square(1.0, 1.0), square(1.3, 1.0)], [(0.4, 0.0), None]
    )
    assert found.velocities == ((0.4, 0.0), None) and found.vision_system == '/drvs'
    fix = fused.fix('self')
    assert fix.position == pytest.approx((1.0, 1.0)) or fix.position == pytest.approx((1.3, 1.0))
    assert fix.outline.area == pytest.approx(0.09)  # one of the two: not their union
    with pytest.raises(PerceptionError, match='velocities: expected 1, one per outline, got 2'):
        fused.accept(MODELS['self'], '/robot/self', '/drvs', 2.1, [square(1.0, 1.0)], [None, None])


def test_callbacks_in_any_order_late_or_twice(perception):
    for _ in range(3):
        perception.requests.issue('self')
    answer(perception, 'self', 2, '/vs1', square(1.0, 1.0))
    answer(perception, 'self', 3, '/vs1', square(2.0, 1.0))  # newer request answered
    assert answer(perception, 'self', 2, '/vs2', square(1.0, 1.0)) is None  # late: superseded
    assert perception.fix('self').position == pytest.approx((2.0, 1.0))
    assert perception.superseded == 1
    answer(perception, 'self', 3, '/vs1', square(2.0, 1.0))  # the same callback twice
    fix = perception.fix('self')
    assert fix.position == pytest.approx((2.0, 1.0))
    assert fix.outline.area == pytest.approx(0.09)  # not doubled
    assert fix.seq == 3


def test_obstacle_answers_are_superseded_per_vision_system(perception):
    for _ in range(2):
        perception.requests.issue('obstacle')
    newer = answer(perception, 'obstacle', 2, '/vs1', square(1, 1))
    assert newer.outlines[0].area == pytest.approx(0.09)
    assert answer(perception, 'obstacle', 1, '/vs1', square(3, 3)) is None  # late answer from vs1
    late_other = answer(perception, 'obstacle', 1, '/vs2', square(3, 3))  # vs2 had not answered yet
    assert late_other is not None and late_other.vision_system == '/vs2'


def test_a_station_partly_hidden_keeps_its_fix(perception):
    """The robot drives onto its station: the cameras see less of it, and it has not moved."""
    for _ in range(3):
        perception.requests.issue('station')
    answer(perception, 'station', 1, '/vs1', square(5.0, 3.0, half=0.2))
    answer(perception, 'station', 2, '/vs1', [(4.8, 2.8), (4.9, 2.8), (4.9, 3.2), (4.8, 3.2)])  # a sliver
    assert perception.fix('station').position == pytest.approx((5.0, 3.0))
    assert perception.fix('station').seq == 1
    answer(perception, 'station', 3, '/vs1', square(5.0, 3.1, half=0.19))  # in full view again
    assert perception.fix('station').position == pytest.approx((5.0, 3.1))


def test_the_nearest_candidate_to_the_last_fix_wins(perception):
    for _ in range(2):
        perception.requests.issue('self')
    answer(perception, 'self', 1, '/vs1', square(1.0, 1.0))
    answer(perception, 'self', 2, '/vs1', square(4.0, 4.0, half=0.3), square(1.1, 1.0))
    assert perception.fix('self').position == pytest.approx((1.1, 1.0))


@pytest.mark.parametrize(
    'role, request_id, algorithm, message',
    [
        ('self', 'self-7', None, "request_id: 'self-7' was never issued by this robot"),
        (
            'self',
            'robot-1',
            None,
            "request_id: expected <role>-<number> or a watch /<role> with a role of ours, got 'robot-1'",
        ),
        (
            'self',
            'self-x',
            None,
            "request_id: expected <role>-<number> or a watch /<role> with a role of ours, got 'self-x'",
        ),
        (
            'self',
            'self-1',
            'colour:0,0,0,1,1,1',
            "algorithm: 'self-1' asked with 'colour:0,150,0,80,255,80', the answer says 'colour:0,0,0,1,1,1'",
        ),
    ],
)
def test_foreign_callbacks_are_refused(perception, role, request_id, algorithm, message):
    perception.requests.issue(role)
    with pytest.raises(PerceptionError) as error:
        perception.accept(algorithm or MODELS[role], request_id, '/vs1', 1.0, [square(1, 1)])
    assert str(error.value) == message


def test_degenerate_outlines_are_dropped(perception):
    perception.requests.issue('obstacle')
    accepted = answer(
        perception, 'obstacle', 1, '/vs1', [(0, 0), (1, 1)], [(0, 0), (1, 0), (2, 0)], square(1, 1)
    )
    assert len(accepted.outlines) == 1


def test_merge_outlines_unions_overlaps_and_keeps_separate_objects():
    merged = merge_outlines([box(0, 0, 1, 1), box(0.5, 0, 1.5, 1), box(3, 3, 4, 4)])
    assert sorted(round(p.area, 6) for p in merged) == [1.0, 1.5]


def test_the_robot_and_station_are_never_obstacles():
    robot, station = box(0, 0, 0.3, 0.3), box(5, 5, 5.4, 5.3)
    outlines = [box(0.01, 0, 0.31, 0.3), box(5, 5, 5.4, 5.3), box(1, 1, 2, 2), box(0.25, 0, 0.6, 0.3)]
    kept = exclude_bodies(outlines, [robot, station])
    assert kept == [outlines[2], outlines[3]]  # the one only touching the robot stays


def test_a_touching_robot_stays_an_obstacle_when_the_fleet_model_merges_it_with_this_one():
    me, other = box(0, 0, 0.3, 0.3), box(0.3, 0, 0.6, 0.3)  # touching: one blob in the image
    blob = merge_outlines([me, other])[0]
    trail = box(0, 0, 0.3, 0.3).buffer(0.1)  # where this robot stood lately, with a margin
    assert exclude_bodies([blob], [me, trail]) == []  # dropped whole: the other robot unseen
    (left,) = cut_bodies([blob], [me, trail])
    assert left.area == pytest.approx(other.difference(trail).area)  # the other robot, but for the margin
    assert left.within(other)
    assert not left.intersects(me)


def test_cut_bodies_keeps_untouched_outlines_and_drops_slivers():
    me = box(0, 0, 0.3, 0.3)
    far, edge = box(2, 2, 2.3, 2.3), box(0.0, 0.0, 0.33, 0.3)  # edge: my own blob, 3 cm off
    assert cut_bodies([far, edge], [me]) == [far]  # 0.009 m² of my own edge is not a body
    assert cut_bodies([far], []) == [far]


def test_roi_policy():
    assert whole_floor((7.0, 5.5)) == (0.0, 0.0, 7.0, 5.5)
    assert spanned((0.8, 2.6), (5.9, 3.5), 0.5, (7.0, 5.5)) == pytest.approx((0.3, 2.1, 6.4, 4.0))
    assert spanned((0.2, 0.1), (6.9, 5.4), 1.0, (7.0, 5.5)) == (0.0, 0.0, 7.0, 5.5)


def test_missing_colour_model_is_refused():
    with pytest.raises(PerceptionError) as error:
        Perception({'self': MODELS['self']})
    assert str(error.value) == 'colour_models: missing role(s) station, obstacle, human'


# -- watches -------------------------------------------------------------------------------------


@pytest.fixture
def watching():
    perception = Perception({**MODELS, 'robot': 'colour:0,0,0,30,30,30'}, '/robot1', watch_keep=10.0)
    for role in perception.algorithms:
        perception.requests.watch_id(role)
    return perception


def seen(perception, role, vs, *outlines, stamp):
    return perception.accept(perception.algorithms[role], f'/robot1/{role}', vs, stamp, list(outlines))


def test_a_watch_id_names_the_node_and_the_role(watching):
    assert watching.obstacle_roles == ('obstacle', 'human', 'robot')
    assert watching.cut_roles == ('robot',)
    assert Perception({**MODELS, 'obstacle': 'elevation:0.03'}).cut_roles == ('obstacle',)
    assert watching.requests.watch_id('self') == '/robot1/self'
    assert watching.requests.parse('/robot1/robot') == ('robot', WATCH)
    unsent = Perception(MODELS, '/robot1')
    with pytest.raises(PerceptionError) as error:
        unsent.accept(MODELS['self'], '/robot1/self', '/vs1', 1.0, [square(1, 1)])
    expected = "expected <role>-<number> or a watch /robot1/<role> with a role of ours, got '/robot1/self'"
    assert str(error.value) == f'request_id: {expected}'


def test_every_callback_of_a_watch_counts_in_stamp_order_per_vision_system(watching):
    seen(watching, 'self', '/vs1', square(1.0, 1.0), stamp=1.0)
    seen(watching, 'self', '/vs2', square(1.02, 1.0), stamp=1.1)
    first = watching.fix('self')
    assert (first.position[0], first.stamp, first.vision_systems) == (
        pytest.approx(1.01),
        1.1,
        ('/vs1', '/vs2'),
    )
    seen(watching, 'self', '/vs1', square(1.2, 1.0), stamp=1.3)  # it moved; vs2 had nothing new to say
    seen(watching, 'self', '/vs2', square(1.22, 1.0), stamp=1.3)
    assert watching.fix('self').position == pytest.approx((1.21, 1.0))
    assert watching.fix('self').seq == first.seq + 2  # every new answer is a new fix
    assert seen(watching, 'self', '/vs1', square(1.0, 1.0), stamp=1.2) is None  # late: superseded
    assert watching.superseded == 1
    assert watching.fix('self').position == pytest.approx((1.21, 1.0))
    seen(watching, 'self', '/vs1', square(1.2, 1.0), stamp=1.3)  # the same callback twice
    assert watching.fix('self').outline.area == pytest.approx(0.09 + 0.02 * 0.3)


def test_an_empty_watch_callback_says_that_vision_system_sees_nothing_of_it(watching):
    seen(watching, 'self', '/vs1', square(1.0, 1.0), stamp=1.0)
    seen(watching, 'self', '/vs2', square(1.1, 1.0), stamp=1.0)
    assert not watching.lost('self')
    seen(watching, 'self', '/vs1', stamp=1.2)  # it left vs1's view
    seen(watching, 'self', '/vs2', square(1.3, 1.0), stamp=1.2)
    assert watching.fix('self').position == pytest.approx((1.3, 1.0))
    assert watching.fix('self').vision_systems == ('/vs2',)
    seen(watching, 'self', '/vs2', stamp=1.4)
    assert watching.lost('self')  # nobody sees it: the fix stays, the robot looks for itself
    assert watching.fix('self').position == pytest.approx((1.3, 1.0))
    seen(watching, 'self', '/vs3', square(2.0, 1.0), stamp=1.6)
    assert not watching.lost('self')
    assert watching.fix('self').position == pytest.approx((2.0, 1.0))


def test_a_watch_answer_older_than_the_watch_duration_is_dropped(watching):
    seen(watching, 'station', '/vs1', square(5.0, 3.0), stamp=1.0)
    seen(watching, 'station', '/vs2', square(5.02, 3.0), stamp=20.0)  # vs1 left the watch since
    assert watching.fix('station').vision_systems == ('/vs2',)
    assert watching.fix('station').position == pytest.approx((5.02, 3.0))


def test_watch_answers_for_obstacles_replace_or_clear_a_vision_systems_outlines(watching):
    newer = seen(watching, 'robot', '/vs1', square(3, 3), square(4, 1), stamp=2.0)
    assert (newer.role, newer.seq, len(newer.outlines)) == ('robot', WATCH, 2)
    assert seen(watching, 'robot', '/vs1', square(2.9, 3), stamp=1.9) is None  # older frames
    assert seen(watching, 'robot', '/vs2', square(2.9, 3), stamp=1.9) is not None  # vs2's own order
    cleared = seen(watching, 'robot', '/vs1', stamp=2.2)  # nothing seen any more: the memory clears it
    assert (cleared.vision_system, cleared.outlines) == ('/vs1', ())
    assert not watching.lost('self')  # no answer for self at all: not lost, unknown


# -- the region-of-interest policy ----------------------------------------------------------------

FLOOR = (7.0, 5.5)


@pytest.fixture
def policy():
    return RegionPolicy(FLOOR, ('obstacle', 'human'), 0.2, self_margin=1.0, roi_margin=0.75, fix_timeout=4.0)


def fix_at(x, y, stamp=10.0, half=0.15):
    return Fix((x, y), box(x - half, y - half, x + half, y + half), stamp, 1, ('/vs1',))


def test_before_the_first_fix_itself_and_its_station_over_the_whole_floor(policy):
    floor = Region(whole_floor(FLOOR), whole_floor(FLOOR))
    assert policy.regions(10.0, None, None, None) == {'self': floor, 'station': floor}
    assert policy.regions(10.0, fix_at(1, 1), None, None)['station'] == floor


def test_once_found_itself_around_its_predicted_position_and_its_station_in_its_box(policy):
    station = fix_at(6.0, 3.0, half=0.2)
    regions = policy.regions(11.0, fix_at(2.0, 2.0), station, (2.1, 2.0))
    assert regions['self'].box == pytest.approx((0.9, 0.8, 3.3, 3.2))  # radius 0.2 + margin 1.0
    assert regions['self'].needed == pytest.approx((1.65, 1.55, 2.55, 2.45))  # + a quarter margin
    assert regions['station'].box == pytest.approx((4.8, 1.8, 7.0, 4.2))  # clipped to the floor
    assert regions['station'].needed == pytest.approx((5.55, 2.55, 6.45, 3.45))
    # The robot-station box plus the margin, and 1.5 margins round the robot (one needed).
    roi = Region((0.975, 0.875, 6.75, 3.75), (1.35, 1.25, 6.375, 3.375))
    assert regions['obstacle'].box == pytest.approx(roi.box)
    assert regions['obstacle'].needed == pytest.approx(roi.needed)
    assert regions['obstacle'] == regions['human']
    assert set(regions) == {'self', 'station', 'obstacle', 'human'}


def test_the_obstacle_roles_cover_the_corridor_of_the_plan(policy):
    # The plan goes round below the robot-station box: its corridor is needed, and asked with a margin.
    corridor = (2.5, 0.5, 5.5, 2.5)
    regions = policy.regions(11.0, fix_at(2.0, 2.0), fix_at(6.0, 3.0), None, corridor=corridor)
    assert regions['obstacle'].needed == pytest.approx((1.25, 0.5, 6.375, 3.375))
    assert regions['obstacle'].box == pytest.approx((0.875, 0.125, 6.75, 3.75))
    assert regions['human'] == regions['obstacle']


def test_a_moving_robots_region_reaches_half_the_margin_ahead(policy):
    regions = policy.regions(11.0, fix_at(2.0, 2.0), None, (2.0, 2.0), velocity=(0.0, -0.3))
    assert regions['self'].box == pytest.approx((0.8, 0.3, 3.2, 2.7))
    assert regions['self'].needed == pytest.approx((1.55, 1.55, 2.45, 2.45))  # around where it is


@pytest.mark.parametrize(
    'now, lost, tracked',
    [(12.0, (), True), (12.01, (), False), (11.0, ('self',), False)],
    ids=['fresh', 'fix-older-than-half-fix-timeout', 'vision-systems-see-nothing'],
)
def test_a_robot_that_loses_itself_looks_over_the_whole_floor_again(policy, now, lost, tracked):
    regions = policy.regions(now, fix_at(2.0, 2.0), fix_at(6.0, 3.0), None, lost=lost)
    assert (regions['self'].box != whole_floor(FLOOR)) == tracked
    assert regions['station'].box != whole_floor(FLOOR)
    assert regions['obstacle'].box == pytest.approx((0.875, 0.875, 6.75, 3.75))  # from the last fix


def test_each_outline_keeps_its_top_and_clearance_and_nonsense_is_unknown(perception):
    request_id = perception.requests.issue('obstacle')
    found = perception.accept(
        MODELS['obstacle'],
        request_id,
        '/vs1',
        1.0,
        [square(1.0, 1.0), [(0.0, 0.0), (1.0, 0.0)], square(2.0, 1.0)],  # the second has no area: dropped
        levels=[(0.45, 0.35), (1.0, 0.0), (math.nan, -1.0)],
    )
    assert found.levels == ((0.45, 0.35), (0.0, 0.0))
    with pytest.raises(PerceptionError, match='levels: expected 1, one per outline, got 0'):
        perception.accept(MODELS['obstacle'], request_id, '/vs1', 1.1, [square(1.0, 1.0)], levels=[])
