"""A vision system's watches (no ROS): one frame per period, changes only, "gone", renewal, expiry."""

import doctest
import math

import pytest

import drvs.vision.watch_runner
from drvs.algorithms import AlgorithmError
from drvs.common.status import BUSY, Refusal
from drvs.common.validation import ValidationError
from drvs.vision.watch_runner import WatchRunner, outline_distance, outlines_changed, parse_watch

CALLBACK = '/robot/callback_coordinates'
COLOUR = 'colour:0,0,150,80,80,255'
FLOOR = (0.0, 0.0, 4.0, 3.0)


def square(x, y, size=0.4):
    return [(x, y), (x + size, y), (x + size, y + size), (x, y + size)]


def terms(request_id='w', period=1.0, changes_only=False, region=FLOOR, algorithm=COLOUR):
    return parse_watch(algorithm, region, CALLBACK, request_id, period, 30.0, changes_only)


@pytest.fixture
def runner():
    return WatchRunner(min_period=0.1, max_duration=60.0, change_tolerance=0.03, max_watches=3)


def evaluate_due(runner, now, found):
    """The vision system's tick: what each due watch sends for ``found`` {request_id: found}."""
    return {t.request_id: runner.evaluate(t, found.get(t.request_id, [])) for t in runner.due(now)}


def test_doctests():
    assert doctest.testmod(drvs.vision.watch_runner).failed == 0


def test_one_frame_per_tick_for_all_watches_that_are_due(runner):
    runner.stand(terms('fast', period=1.0), 60.0, now=0.0)
    runner.stand(terms('slow', period=1.5), 60.0, now=0.0)
    frames, evaluations = [], {'fast': 0, 'slow': 0}
    now = 0.0
    while now < 6.0:  # the node's loop: it takes a frame only when something is due
        due = runner.due(now)
        if due:
            frames.append(now)
        for t in due:
            evaluations[t.request_id] += 1
        now += 0.25
    assert frames == [0.0, 1.0, 1.5, 2.0, 3.0, 4.0, 4.5, 5.0]  # 10 evaluations on 8 frames
    assert evaluations == {'fast': 6, 'slow': 4}


def test_the_next_due_time_is_the_next_grid_point_or_expiry(runner):
    assert runner.next_due() is None
    runner.stand(terms(period=0.5), 1.2, now=0.3)
    assert runner.next_due() == 0.3  # a new watch: at once
    runner.due(0.3)
    assert runner.next_due() == 0.5  # then on the grid of its period
    runner.due(1.0)
    assert runner.next_due() == pytest.approx(1.5)  # expiry at 1.5 (1.2 s from 0.3) equals the next due
    assert runner.due(1.5) == [] and len(runner) == 0


def test_the_grant_bounds_period_and_duration(runner):
    grant = runner.stand(terms(period=0.01), 3600.0, now=0.0)
    assert (grant.period, grant.duration, grant.new) == (0.1, 60.0, True)
    grant = runner.stand(terms(period=2.0), 5.0, now=1.0)
    assert (grant.period, grant.duration, grant.new) == (2.0, 5.0, False)
    assert len(runner) == 1


def test_without_changes_only_it_calls_back_every_period_something_is_found(runner):
    runner.stand(terms('w'), 60.0, now=0.0)
    crate = [(square(1, 1), '')]
    assert evaluate_due(runner, 0.0, {'w': crate}) == {'w': crate}
    assert evaluate_due(runner, 1.0, {'w': crate}) == {'w': crate}  # unchanged: sent again
    assert evaluate_due(runner, 2.0, {'w': []}) == {'w': None}  # nothing found: no callback
    assert evaluate_due(runner, 3.0, {'w': []}) == {'w': None}


def test_a_fused_watch_calls_back_every_period_even_with_nothing_found(runner):
    fused = parse_watch(COLOUR, FLOOR, CALLBACK, 'f', 1.0, 30.0, False, fused=True)
    runner.stand(fused, 60.0, now=0.0)
    crate = [(square(1, 1), '')]
    assert evaluate_due(runner, 0.0, {'f': crate}) == {'f': crate}
    assert evaluate_due(runner, 1.0, {'f': []}) == {'f': []}  # the fusion stage hears "nothing here"
    assert evaluate_due(runner, 2.0, {'f': []}) == {'f': []}


def test_changes_only_calls_back_on_changes_beyond_the_tolerance(runner):
    runner.stand(terms('w', changes_only=True), 60.0, now=0.0)
    crate = [(square(1, 1), '')]
    assert evaluate_due(runner, 0.0, {'w': crate}) == {'w': crate}
    assert evaluate_due(runner, 1.0, {'w': crate}) == {'w': None}
    jitter = [([(1.01, 1.0), (1.2, 0.99), (1.4, 1.0), (1.4, 1.41), (1.0, 1.4)], '')]  # another vertex count
    assert evaluate_due(runner, 2.0, {'w': jitter}) == {'w': None}
    moved = [(square(1.05, 1), '')]
    assert evaluate_due(runner, 3.0, {'w': moved}) == {'w': moved}
    assert evaluate_due(runner, 4.0, {'w': moved}) == {'w': None}
    second = [*moved, (square(3, 2), '')]
    assert evaluate_due(runner, 5.0, {'w': second}) == {'w': second}  # one more object
    assert evaluate_due(runner, 6.0, {'w': second[::-1]}) == {'w': None}  # listed the other way round


def test_slow_drift_is_reported_once_it_adds_up_beyond_the_tolerance(runner):
    runner.stand(terms('w', changes_only=True), 60.0, now=0.0)
    sent = [evaluate_due(runner, float(t), {'w': [(square(1 + 0.008 * t, 1), '')]})['w'] for t in range(9)]
    assert [t for t, objects in enumerate(sent) if objects is not None] == [0, 4, 8]  # each 0.032 m on


def test_gone_is_sent_exactly_once(runner):
    runner.stand(terms('w', changes_only=True), 60.0, now=0.0)
    assert evaluate_due(runner, 0.0, {'w': []}) == {'w': None}  # nothing reported: nothing gone
    crate = [(square(1, 1), '')]
    evaluate_due(runner, 1.0, {'w': crate})
    assert evaluate_due(runner, 2.0, {'w': []}) == {'w': []}
    assert evaluate_due(runner, 3.0, {'w': []}) == {'w': None}
    assert evaluate_due(runner, 4.0, {'w': crate}) == {'w': crate}  # back: reported again


def test_a_failed_callback_is_made_good_at_the_next_evaluation(runner):
    runner.stand(terms('w', changes_only=True), 60.0, now=0.0)
    crate = [(square(1, 1), '')]
    (due,) = runner.due(0.0)
    runner.evaluate(due, crate)
    runner.callback_failed(due)
    assert evaluate_due(runner, 1.0, {'w': crate}) == {'w': crate}  # unchanged, but the robot may not know
    (due,) = runner.due(2.0)
    assert runner.evaluate(due, []) == []
    runner.callback_failed(due)
    assert evaluate_due(runner, 3.0, {'w': []}) == {'w': []}  # "gone" again: the first did not arrive
    assert evaluate_due(runner, 4.0, {'w': []}) == {'w': None}


def test_a_renewal_forces_a_full_report_and_keeps_the_schedule(runner):
    runner.stand(terms('w', changes_only=True), 10.0, now=0.0)
    crate = [(square(1, 1), '')]
    evaluate_due(runner, 0.0, {'w': crate})
    assert evaluate_due(runner, 1.0, {'w': crate}) == {'w': None}
    runner.stand(terms('w', changes_only=True), 10.0, now=1.2)
    assert runner.next_due() == 2.0  # same region and period: due as before
    assert evaluate_due(runner, 2.0, {'w': crate}) == {'w': crate}  # unchanged, yet reported in full
    assert evaluate_due(runner, 3.0, {'w': crate}) == {'w': None}


def test_a_new_region_is_due_at_once_and_reported_in_full(runner):
    runner.stand(terms('w', changes_only=True, region=(0, 0, 2, 3)), 10.0, now=0.0)
    crate = [(square(1, 1), '')]
    evaluate_due(runner, 0.0, {'w': crate})
    runner.stand(terms('w', changes_only=True, region=(0, 0, 4, 3)), 10.0, now=0.5)
    (due,) = runner.due(0.5)
    assert due.region == (0.0, 0.0, 4.0, 3.0)
    assert runner.evaluate(due, crate) == crate


def test_an_evaluation_of_terms_replaced_meanwhile_sends_nothing(runner):
    runner.stand(terms('w', changes_only=True), 10.0, now=0.0)
    (due,) = runner.due(0.0)
    runner.stand(terms('w', changes_only=True, region=(0, 0, 1, 1)), 10.0, now=0.1)  # while evaluating
    assert runner.evaluate(due, [(square(1, 1), '')]) is None
    runner.cancel(due.key)
    assert runner.evaluate(due, [(square(1, 1), '')]) is None


def test_a_watch_expires_unless_renewed(runner):
    runner.stand(terms('kept'), 5.0, now=0.0)
    runner.stand(terms('left'), 5.0, now=0.0)
    runner.stand(terms('kept'), 5.0, now=4.0)  # renewed: until 9
    assert sorted(t.request_id for t in runner.due(5.0)) == ['kept']
    assert len(runner) == 1
    assert runner.due(9.0) == [] and len(runner) == 0


def test_cancel(runner):
    runner.stand(terms('w'), 5.0, now=0.0)
    assert runner.cancel((CALLBACK, 'w', ''))
    assert not runner.cancel((CALLBACK, 'w', ''))  # unknown: nothing to do
    assert runner.due(1.0) == [] and runner.next_due() is None


def test_new_watches_beyond_the_limit_are_refused_busy_until_one_expires(runner):
    for index in range(3):
        runner.stand(terms(f'w{index}'), 10.0 + index, now=0.0)
    with pytest.raises(Refusal) as refusal:
        runner.stand(terms('w3'), 10.0, now=4.0)
    assert (refusal.value.status, str(refusal.value), refusal.value.retry_after) == (
        BUSY,
        'busy: 3 watches stand already; try again later',
        6.0,
    )
    assert not runner.stand(terms('w0'), 10.0, now=4.0).new  # a renewal is never refused


@pytest.mark.parametrize(
    ('fields', 'error', 'message'),
    [
        (
            {'request_id': ''},
            ValidationError,
            'request_id: empty; it names the watch (renew or cancel it with the same)',
        ),
        (
            {'request_id': 'w' * 257},
            ValidationError,
            'request_id: 257 characters, longer than the limit of 256',
        ),
        (
            {'callback_service': 'robot/callback'},
            ValidationError,
            "callback_service: 'robot/callback' is not a global ROS name (it must start with /)",
        ),
        (
            {'period': 0.0},
            ValidationError,
            'period: 0; expected a finite number of seconds greater than 0',
        ),
        (
            {'period': math.nan},
            ValidationError,
            'period: nan; expected a finite number of seconds greater than 0',
        ),
        (
            {'duration': -1.0},
            ValidationError,
            'duration: -1; expected a finite number of seconds, 0 to cancel',
        ),
        (
            {'duration': math.inf},
            ValidationError,
            'duration: inf; expected a finite number of seconds, 0 to cancel',
        ),
        (
            {'box': (2.0, 0.0, 1.0, 1.0)},
            ValidationError,
            'region_of_interest: min_x 2 is greater than max_x 1',
        ),
        (
            {'algorithm': ''},
            AlgorithmError,
            'algorithm: empty; expected NAME:PARAMS, e.g. colour:0,0,150,80,80,255',
        ),
    ],
)
def test_bad_fields_are_refused_naming_the_field(fields, error, message):
    request = {
        'algorithm': COLOUR,
        'box': FLOOR,
        'callback_service': CALLBACK,
        'request_id': 'w',
        'period': 1.0,
        'duration': 5.0,
        'changes_only': False,
        **fields,
    }
    with pytest.raises(error) as raised:
        parse_watch(**request)
    assert str(raised.value) == message


def test_a_cancel_looks_only_at_its_name():
    assert parse_watch('', (9, 9, 0, 0), CALLBACK, 'w', math.nan, 0.0, False) is None


def test_outline_distance_ignores_start_direction_and_collinear_vertices():
    a = square(0, 0, 1.0)
    b = [(1.0, 1.0), (1.0, 0.5), (1.0, 0.0), (0.0, 0.0), (0.0, 1.0)]  # clockwise, from another corner
    assert outline_distance(a, b) == 0.0
    assert outline_distance(a, square(0.02, 0, 1.0)) == pytest.approx(0.02)
    assert outline_distance(a, square(0, 0, 1.1)) == pytest.approx(0.1 * math.sqrt(2))  # corner to corner


def test_tags_compare_their_corners_in_order():
    tag = square(1, 1, 0.2)
    turned = tag[1:] + tag[:1]  # a quarter turn on the spot: same square, corner 0 elsewhere
    assert not outlines_changed([(tag, '')], [(turned, '')], 0.03)
    assert outlines_changed([(tag, 'tag36h11:3')], [(turned, 'tag36h11:3')], 0.03)
    assert outlines_changed([(tag, 'tag36h11:3')], [(tag, 'tag36h11:4')], 0.03)  # another tag


def test_changes_only_is_not_fooled_by_confidence_jitter(runner):
    """The confidence (a third member) varies from frame to frame; only outlines and labels count."""
    runner.stand(terms(changes_only=True), 30.0, now=0.0)
    first = [(square(1, 1), '', 0.9)]
    assert evaluate_due(runner, 0.0, {'w': first}) == {'w': first}
    assert evaluate_due(runner, 1.0, {'w': [(square(1, 1), '', 0.4)]}) == {'w': None}
    assert not outlines_changed([(square(1, 1), '', 0.9)], [(square(1, 1), '')], 0.03)
    moved = [(square(1.1, 1), '', 0.4)]
    assert evaluate_due(runner, 2.0, {'w': moved}) == {'w': moved}


def test_robots_of_two_sites_with_one_name_hold_two_watches(runner):
    here = parse_watch(COLOUR, FLOOR, CALLBACK, 'w', 1.0, 30.0, False)
    there = parse_watch(COLOUR, FLOOR, CALLBACK, 'w', 1.0, 30.0, False, callback_uri='rosrpc://robot-a:4100')
    assert there.callback_uri == 'rosrpc://robot-a:4100' and here.key != there.key
    runner.stand(here, 5.0, now=0.0)
    runner.stand(there, 5.0, now=0.0)
    assert len(runner) == 2
    assert runner.cancel(there.key) and len(runner) == 1


def test_a_callback_uri_that_is_not_a_rosrpc_address_is_refused():
    with pytest.raises(
        ValidationError, match="^callback_uri: 'robot-a:4100' is not a rosrpc://HOST:PORT address$"
    ):
        parse_watch(COLOUR, FLOOR, CALLBACK, 'w', 1.0, 30.0, False, callback_uri='robot-a:4100')
