"""Perception bookkeeping: request ids, superseded and repeated answers, merging, ROI policy."""

import pytest
from shapely.geometry import box

from drvs.perception import (
    Perception,
    PerceptionError,
    exclude_bodies,
    merge_outlines,
    obstacle_roi,
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
        ('self', 'robot-1', None, "request_id: expected <role>-<number> with a role of ours, got 'robot-1'"),
        ('self', 'self-x', None, "request_id: expected <role>-<number> with a role of ours, got 'self-x'"),
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


def test_roi_policy():
    assert whole_floor((7.0, 5.5)) == (0.0, 0.0, 7.0, 5.5)
    assert obstacle_roi((0.8, 2.6), (5.9, 3.5), 0.5, (7.0, 5.5)) == pytest.approx((0.3, 2.1, 6.4, 4.0))
    assert obstacle_roi((0.2, 0.1), (6.9, 5.4), 1.0, (7.0, 5.5)) == (0.0, 0.0, 7.0, 5.5)


def test_missing_colour_model_is_refused():
    with pytest.raises(PerceptionError) as error:
        Perception({'self': MODELS['self']})
    assert str(error.value) == 'colour_models: missing role(s) station, obstacle, human'
