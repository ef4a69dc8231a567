"""Tracking metrics on synthetic ground truth and tracks: py-motmetrics' figures and ours."""

import doctest

import numpy as np
import pytest

import drvs.sim.tracking
from drvs.sim.tracking import (
    NO_OBJECTS,
    TrackPeriod,
    TrackPoint,
    duplicates,
    evaluate,
    truth_at,
    truth_classes,
)
from drvs.sim.world_file import load_world
from drvs.testing.harness import REPO

CROSSING = load_world(REPO / 'worlds' / 'crossing.yaml')  # robot1, robot2, the human walker
HUMAN = CROSSING.robots[0].colour_models['human']
ROBOT = CROSSING.robots[0].colour_models['robot']
STAMPS = [10.0 + 0.1 * i for i in range(20)]


def walk(start, velocity):
    """Ground truth samples (t, x, y) of a body walking at ``velocity`` from ``start`` at 10 s."""
    return [(t, start[0] + velocity[0] * (t - 10.0), start[1] + velocity[1] * (t - 10.0)) for t in STAMPS]


TRUTH = {
    'walker': walk((5.6, 0.6), (0.0, 0.3)),
    'robot1': walk((1.0, 1.0), (0.5, 0.0)),
    'robot2': walk((1.0, 4.0), (0.5, -0.5)),
}


def position(body, t):
    _, x, y = min(TRUTH[body], key=lambda s: abs(s[0] - t))
    return x, y


def periods(assign, offset=(0.02, -0.01)):
    """A period per stamp; ``assign(i, t)``: its tracks [(algorithm, track id, body)], at body + offset."""
    return [
        TrackPeriod(
            t,
            tuple(
                TrackPoint(
                    algorithm, track_id, position(body, t)[0] + offset[0], position(body, t)[1] + offset[1]
                )
                for algorithm, track_id, body in assign(i, t)
            ),
        )
        for i, t in enumerate(STAMPS)
    ]


def perfect(i, t):
    return [(HUMAN, 7, 'walker'), (ROBOT, 1, 'robot1'), (ROBOT, 2, 'robot2')]


def row(block, algorithm):
    (found,) = [r for r in block['algorithms'] if r['algorithm'] == algorithm]
    return found


def test_the_world_says_which_bodies_each_algorithm_finds():
    classes = truth_classes(CROSSING)
    assert classes[HUMAN].bodies == ('walker',) and classes[HUMAN].kind == 'person'
    assert classes[ROBOT].bodies == ('robot1', 'robot2') and classes[ROBOT].roles == ('robot',)
    own = CROSSING.robots[1].colour_models
    assert classes[own['self']].bodies == ('robot2',) and classes[own['self']].roles == ('robot2.self',)
    assert classes[own['station']].bodies == ('robot2_station',) and classes[own['station']].kind == 'station'
    assert classes['colour:40,40,40,90,90,90'].bodies == ('crate',)


def test_perfect_tracking_scores_one():
    block = evaluate(CROSSING, TRUTH, periods(perfect))

    assert block['measured'] is True and block['periods'] == 20
    overall = block['overall']
    assert overall['mota'] == 1.0 and overall['idf1'] == 1.0
    assert overall['switches'] == overall['fragmentations'] == overall['duplicates'] == 0
    assert overall['matches'] == 60 and overall['misses'] == overall['false_positives'] == 0
    assert overall['position_error_p50'] == pytest.approx(np.hypot(0.02, 0.01), abs=1e-3)
    assert overall['track_seconds'] == pytest.approx(3 * 1.9)
    assert overall['switches_per_100_track_seconds'] == 0.0
    assert row(block, ROBOT)['bodies'] == ['robot1', 'robot2'] and row(block, HUMAN)['kind'] == 'people'
    assert block['kinds']['people']['matches'] == 20
    assert block['targets']['idf1']['met'] and block['targets']['duplicates']['met']
    assert block['targets']['position_error_p50_people'] == {
        'value': pytest.approx(0.022, abs=1e-3),
        'target': 0.15,
        'met': True,
        'at_most': True,
    }
    # No tagged robot in this world: its target is not measured, and so not met.
    assert block['targets']['position_error_p50_tagged_robots']['value'] is None
    assert not block['targets']['position_error_p50_tagged_robots']['met']


def test_two_tracks_swapping_bodies_is_one_id_switch_each():
    # From period 10 on, the robots' tracks trade ids: each of the two bodies switches once.
    def swapped(i, t):
        ids = (1, 2) if i < 10 else (2, 1)
        return [(ROBOT, ids[0], 'robot1'), (ROBOT, ids[1], 'robot2')]

    robots = row(evaluate(CROSSING, TRUTH, periods(swapped)), ROBOT)

    assert robots['switches'] == 2
    assert robots['idf1'] == pytest.approx(0.5)
    assert robots['mota'] == pytest.approx(1 - 2 / 40)
    assert robots['switches_per_100_track_seconds'] == pytest.approx(100 * 2 / (2 * 1.9), abs=1e-3)


def test_a_new_id_for_the_same_body_is_one_switch():
    def renamed(i, t):
        return [(HUMAN, 7 if i < 5 else 8, 'walker')]

    human = row(evaluate(CROSSING, TRUTH, periods(renamed)), HUMAN)

    assert human['switches'] == 1 and human['tracks'] == 2
    assert human['track_seconds'] == pytest.approx(0.4 + 1.4)


def test_one_body_reported_as_two_tracks_is_a_duplicate():
    def doubled(i, t):
        return perfect(i, t) + ([(HUMAN, 9, 'walker')] if i in (3, 4, 5) else [])

    block = evaluate(CROSSING, TRUTH, periods(doubled))

    human = row(block, HUMAN)
    assert human['duplicates'] == 3 and human['periods_with_duplicates'] == 3
    assert human['false_positives'] == 3
    assert block['overall']['duplicates'] == 3
    assert block['targets']['duplicates'] == {'value': 3, 'target': 0, 'met': False, 'at_most': True}


def test_a_missed_period_is_a_fragmentation():
    def gap(i, t):
        return [(HUMAN, 7, 'walker')] if i != 8 else []

    human = row(evaluate(CROSSING, TRUTH, periods(gap)), HUMAN)

    assert human['fragmentations'] == 1 and human['misses'] == 1 and human['switches'] == 0
    assert human['mota'] == pytest.approx(1 - 1 / 20)


def test_a_track_beyond_the_gate_is_a_miss_and_a_false_positive():
    block = evaluate(CROSSING, TRUTH, periods(lambda i, t: [(HUMAN, 7, 'walker')], offset=(0.6, 0.0)))

    human = row(block, HUMAN)
    assert human['matches'] == 0 and human['misses'] == 20 and human['false_positives'] == 20
    assert human['position_error_p50'] is None and human['idf1'] == 0.0


def test_an_algorithm_counts_from_its_first_track_to_its_last():
    # The robot model was asked for only from period 5 to period 14: its other periods are not misses.
    def late(i, t):
        return [(HUMAN, 7, 'walker')] + ([(ROBOT, 1, 'robot1'), (ROBOT, 2, 'robot2')] if 5 <= i < 15 else [])

    block = evaluate(CROSSING, TRUTH, periods(late))

    assert row(block, ROBOT)['periods'] == 10 and row(block, ROBOT)['misses'] == 0
    assert row(block, HUMAN)['periods'] == 20


def test_without_objects_the_block_says_so_rather_than_zeros():
    assert evaluate(CROSSING, TRUTH, []) == {'measured': False, 'reason': NO_OBJECTS, 'gate': 0.5}


def test_tracks_of_an_algorithm_the_world_does_not_name_are_listed_not_measured():
    block = evaluate(CROSSING, TRUTH, periods(lambda i, t: [('motion', 3, 'walker')]))

    assert block['measured'] is False
    assert block['not_measured'] == {'motion': '1 track(s): no role of the world file uses this algorithm'}


def test_ground_truth_is_interpolated_to_the_stamp_and_fixed_bodies_stand_still():
    truth = {'walker': [(0.0, 0.0, 0.0), (1.0, 1.0, 2.0)]}
    at = truth_at(truth, {'crate': (4.0, 2.5)}, ['walker', 'crate', 'ghost'], [0.25, 2.0])

    assert at[0, 0] == pytest.approx((0.25, 0.5)) and at[1, 0] == pytest.approx((1.0, 2.0))
    assert at[:, 1] == pytest.approx(np.array([[4.0, 2.5], [4.0, 2.5]]))
    assert np.isnan(at[:, 2]).all()


def test_two_people_side_by_side_each_with_a_track_are_no_duplicate():
    bodies = np.array([[0.0, 0.0], [0.35, 0.0]])
    assert duplicates(bodies, np.array([[0.02, 0.0], [0.33, 0.0]])) == 0
    assert duplicates(bodies, np.array([[0.02, 0.0], [-0.05, 0.0], [0.33, 0.0]])) == 1


def test_doctests():
    assert doctest.testmod(drvs.sim.tracking).failed == 0
