"""The server's watch bookkeeping: who serves each watch, and what to send them (no ROS)."""

import doctest

import pytest

import drvs.server.watch_table
from drvs.common.validation import ValidationError
from drvs.server.dispatch import Busy
from drvs.server.watch_table import (
    CANCELLED,
    NEW,
    NOT_STANDING,
    ONE_SHOT,
    RENEWAL,
    RENEWED,
    STARTED,
    WITHDRAWAL,
    WatchTable,
    watch_terms,
)
from drvs.testing import ManualClock

CALLBACK = '/robot/callback_coordinates'
COLOUR = 'colour:0,0,150,80,80,255'
LEFT = (0.5, 0.5, 1.5, 1.5)  # inside square(0, 0)
RIGHT = (4.5, 0.5, 5.5, 1.5)  # inside square(4, 0)


def square(x, y, size=2.0):
    return [(x, y), (x + size, y), (x + size, y + size), (x, y + size)]


def service(name):
    return f'/{name}/detect_object_boundary'


def sent(forwards):
    """Forwards as (kind, camera name, duration) tuples."""
    return [(f.kind, f.vision_system.split('/')[1], f.duration) for f in forwards]


@pytest.fixture
def clock():
    return ManualClock(100.0)


@pytest.fixture
def registry(clock, new_registry):
    """A registry of each backend (memory, PostgreSQL: test/unit/server/conftest.py)."""
    return new_registry(lease=1000.0, clock=clock)


@pytest.fixture
def table(registry, clock):
    return WatchTable(registry, clock, min_period=0.1, max_duration=60.0, max_watches=3, retry_delay=1.0)


def camera(registry, name, field_of_view, watch_service=True, algorithms=()):
    return registry.register(service(name), field_of_view, algorithms=algorithms, watch_service=watch_service)


def watch(table, request_id='w1', region=LEFT, duration=10.0, period=0.5, caller='/robot', **fields):
    fields = {'algorithm': COLOUR, 'callback_service': CALLBACK, 'changes_only': False, **fields}
    name = fields['algorithm'].partition(':')[0]
    return table.request(
        caller,
        request_id,
        fields['algorithm'],
        name,
        region,
        fields['callback_service'],
        period,
        duration,
        fields['changes_only'],
    )


def test_doctests():
    assert doctest.testmod(drvs.server.watch_table).failed == 0


@pytest.mark.parametrize(
    'request_id, period, duration, message',
    [
        ('', 0.5, 10.0, 'request_id: empty; it names the watch (renew or cancel it with the same)'),
        ('w' * 257, 0.5, 10.0, 'request_id: 257 characters, longer than the limit of 256'),
        ('w', 0.5, -1.0, 'duration: -1; expected a finite number of seconds, 0 to cancel'),
        ('w', 0.5, float('inf'), 'duration: inf; expected a finite number of seconds, 0 to cancel'),
        ('w', 0.5, float('nan'), 'duration: nan; expected a finite number of seconds, 0 to cancel'),
        ('w', 0.0, 10.0, 'period: 0; expected a finite number of seconds greater than 0'),
        ('w', -0.5, 10.0, 'period: -0.5; expected a finite number of seconds greater than 0'),
        ('w', float('nan'), 10.0, 'period: nan; expected a finite number of seconds greater than 0'),
    ],
)
def test_bad_terms_are_refused_naming_the_field(request_id, period, duration, message):
    with pytest.raises(ValidationError) as caught:
        watch_terms(request_id, period, duration)
    assert str(caught.value) == message


def test_a_cancel_needs_only_request_id_and_duration():
    assert watch_terms('w' * 256, 0.5, 10.0) is True
    assert watch_terms('w', float('nan'), 0.0) is False


def test_a_new_watch_goes_to_the_cameras_that_cover_it_and_run_its_algorithm(table, registry):
    camera(registry, 'a', square(0, 0), algorithms=['colour'])
    camera(registry, 'sifter', square(0, 0), algorithms=['sift'])
    camera(registry, 'far', square(4, 0))
    answer = watch(table)
    assert (answer.change, answer.period, answer.duration) == (STARTED, 0.5, 10.0)
    assert sent(answer.forwards) == [(NEW, 'a', 10.0)]
    assert table.serving(('/robot', 'w1')) == [service('a')]
    assert table.get(('/robot', 'w1')).expires_at == 110.0
    assert table.sync() == []  # nothing changed


def test_the_grant_bounds_period_and_duration(table, clock):
    answer = watch(table, period=0.01, duration=600.0)
    assert (answer.period, answer.duration) == (0.1, 60.0)
    clock.now += 59.9
    assert table.sync() == [] and len(table) == 1
    clock.now += 0.1
    table.sync()
    assert len(table) == 0


def test_cameras_that_appear_or_move_in_later_get_the_watch_with_the_time_it_has_left(table, registry, clock):
    answer = watch(table)
    assert (answer.change, answer.forwards, table.serving(('/robot', 'w1'))) == (STARTED, [], [])
    clock.now += 2.0
    camera(registry, 'a', square(0, 0))
    assert sent(table.sync()) == [(NEW, 'a', 8.0)]
    camera(registry, 'b', square(4, 0))
    assert table.sync() == []
    clock.now += 1.0
    camera(registry, 'b', square(0.5, 0))  # moves in
    assert sent(table.sync()) == [(NEW, 'b', 7.0)]
    assert table.sync() == []
    assert table.serving(('/robot', 'w1')) == [service('a'), service('b')]


def test_cameras_that_leave_or_stop_covering_get_a_withdrawal(table, registry):
    for name in 'abc':
        camera(registry, name, square(0, 0))
    assert sent(watch(table).forwards) == [(NEW, 'a', 10.0), (NEW, 'b', 10.0), (NEW, 'c', 10.0)]
    camera(registry, 'a', square(4, 0))  # moves away
    assert sent(table.sync()) == [(WITHDRAWAL, 'a', 0.0)]
    registry.unregister(service('b'))
    assert sent(table.sync()) == [(WITHDRAWAL, 'b', 0.0)]
    camera(registry, 'c', square(0, 0), algorithms=['sift'])  # no longer runs colour
    assert sent(table.sync()) == [(WITHDRAWAL, 'c', 0.0)]
    assert table.serving(('/robot', 'w1')) == []
    assert len(table) == 1  # the watch stands for cameras to come


def test_a_watch_not_renewed_expires_and_is_withdrawn(table, registry, clock):
    camera(registry, 'a', square(0, 0))
    camera(registry, 'paper', square(0, 0), watch_service=False)
    watch(table, duration=10.0, period=5.0)
    clock.now += 5.0
    assert sent(table.sync()) == [(ONE_SHOT, 'paper', 0.0)]
    renewed = watch(table, duration=10.0, period=5.0)  # at 105: stands until 115
    assert (renewed.change, sent(renewed.forwards)) == (RENEWED, [(RENEWAL, 'a', 10.0)])
    clock.now += 9.9
    assert sent(table.sync()) == [(ONE_SHOT, 'paper', 0.0)]
    assert table.next_due() == pytest.approx(115.0)
    clock.now += 0.1
    assert sent(table.sync()) == [(WITHDRAWAL, 'a', 0.0)]  # nothing to withdraw from a one-shot camera
    assert len(table) == 0 and table.next_due() is None
    assert table.sync() == []


def test_a_renewal_with_a_new_region_forwards_to_new_withdraws_from_old_and_renews_the_rest(
    table, registry, clock
):
    camera(registry, 'old', square(0, 0))
    camera(registry, 'both', square(0, 0, size=6.0))
    camera(registry, 'new', square(4, 0))
    assert sent(watch(table, region=LEFT).forwards) == [(NEW, 'both', 10.0), (NEW, 'old', 10.0)]
    clock.now += 5.0
    answer = watch(table, region=RIGHT, duration=20.0)
    assert answer.change == RENEWED
    assert sent(answer.forwards) == [(WITHDRAWAL, 'old', 0.0), (RENEWAL, 'both', 20.0), (NEW, 'new', 20.0)]
    assert [f.watch.region for f in answer.forwards] == [RIGHT] * 3
    assert table.serving(('/robot', 'w1')) == [service('both'), service('new')]


def test_cancel_withdraws_from_all_and_an_unknown_cancel_is_accepted(table, registry):
    camera(registry, 'a', square(0, 0))
    camera(registry, 'b', square(0, 0))
    camera(registry, 'paper', square(0, 0), watch_service=False)
    watch(table)
    answer = watch(table, duration=0.0)
    assert (answer.change, answer.duration) == (CANCELLED, 0.0)
    assert sent(answer.forwards) == [(WITHDRAWAL, 'a', 0.0), (WITHDRAWAL, 'b', 0.0)]
    assert len(table) == 0 and table.sync() == []
    again = watch(table, duration=0.0)
    assert (again.change, again.forwards) == (NOT_STANDING, [])
    # The pair is free again for another caller.
    assert watch(table, caller='/other').change == STARTED


def test_a_camera_without_a_watch_service_gets_a_one_shot_every_period(table, registry, clock):
    camera(registry, 'paper', square(0, 0), watch_service=False)
    camera(registry, 'a', square(0, 0))
    answer = watch(table, period=0.5)
    assert sent(answer.forwards) == [(NEW, 'a', 10.0), (ONE_SHOT, 'paper', 0.0)]  # the first at once
    one_shot = answer.forwards[1].watch
    assert (one_shot.request_id, one_shot.callback_service, one_shot.algorithm) == ('w1', CALLBACK, COLOUR)
    assert table.serving(('/robot', 'w1')) == [service('a'), service('paper')]
    assert table.sync() == []
    assert table.next_due() == 100.5
    clock.now += 0.4
    assert table.sync() == []
    clock.now += 0.1
    assert sent(table.sync()) == [(ONE_SHOT, 'paper', 0.0)]
    clock.now += 2.0  # late: one, not four to catch up
    assert sent(table.sync()) == [(ONE_SHOT, 'paper', 0.0)]
    assert table.next_due() == pytest.approx(103.0)
    camera(registry, 'paper', square(4, 0), watch_service=False)  # moves away: the one-shots stop
    clock.now += 0.5
    assert table.sync() == []
    assert table.serving(('/robot', 'w1')) == [service('a')]


def test_a_camera_registered_anew_gets_its_watches_again(table, registry, clock):
    camera(registry, 'a', square(0, 0))
    camera(registry, 'paper', square(0, 0), watch_service=False)
    watch(table, period=5.0)
    clock.now += 1.0
    assert table.sync() == []
    table.forget(service('a'))  # it restarted
    table.forget(service('paper'))
    assert sent(table.sync()) == [(NEW, 'a', 9.0), (ONE_SHOT, 'paper', 0.0)]
    # A camera that restarts with a watch service is no longer served by one-shots.
    registry.unregister(service('paper'))
    camera(registry, 'paper', square(0, 0), watch_service=True)
    table.forget(service('paper'))
    assert sent(table.sync()) == [(NEW, 'paper', 9.0)]
    clock.now += 5.0
    assert table.sync() == []


def test_two_callers_may_not_share_a_callback_and_request_id(table):
    watch(table, caller='/robot')
    with pytest.raises(ValidationError) as caught:
        watch(table, caller='/intruder')
    assert str(caught.value) == (
        f"request_id: 'w1' with callback_service {CALLBACK} already names a watch of /robot; "
        'vision systems could not tell the two apart: choose another request_id'
    )
    assert watch(table, caller='/intruder', callback_service='/intruder/callback').change == STARTED
    assert watch(table, caller='/robot').change == RENEWED  # the owner renews as usual


def test_a_renewal_with_a_new_callback_is_withdrawn_under_the_old_one(table, registry):
    camera(registry, 'a', square(0, 0))
    watch(table)
    answer = watch(table, callback_service='/robot/other_callback')
    assert sent(answer.forwards) == [(WITHDRAWAL, 'a', 0.0), (NEW, 'a', 10.0)]
    assert [f.watch.callback_service for f in answer.forwards] == [CALLBACK, '/robot/other_callback']
    assert watch(table, caller='/other').change == STARTED  # the old pair is free


def test_an_undelivered_forward_is_sent_again_after_the_retry_delay(table, registry, clock):
    camera(registry, 'a', square(0, 0))
    camera(registry, 'b', square(0, 0))
    new_a, new_b = watch(table).forwards
    assert table.sync() == []
    table.undelivered(new_a)
    assert table.serving(('/robot', 'w1')) == [service('b')]
    assert table.next_due() == 101.0
    clock.now += 0.9
    assert table.sync() == []
    clock.now += 0.1
    assert sent(table.sync()) == [(NEW, 'a', 9.0)]
    assert table.sync() == []
    # A lost withdrawal is not sent again (the camera drops the watch when its duration runs out).
    (withdrawal,) = watch(table, region=RIGHT).forwards[:1]
    assert withdrawal.kind == WITHDRAWAL
    table.undelivered(withdrawal)
    clock.now += 5.0
    assert table.sync() == []


def test_at_most_max_watches_stand(table):
    for number in range(3):
        watch(table, request_id=f'w{number}')
    with pytest.raises(Busy) as caught:
        watch(table, request_id='w3')
    assert (str(caught.value), caught.value.retry_after) == (
        'busy: 3 watches stand, the most this server keeps; try again later',
        0.5,
    )
    assert watch(table, request_id='w0').change == RENEWED  # renewals still pass
    watch(table, request_id='w0', duration=0.0)
    assert watch(table, request_id='w3').change == STARTED


def test_an_adopted_watch_is_forwarded_at_the_next_sync_and_expires_on_its_own_time(table, registry, clock):
    """A watch taken over from a replica gone silent (docs/registry.md)."""
    from drvs.server.shared_registry import adopted_watch, stored_watch
    from drvs.server.watch_table import Watch

    camera(registry, 'cam1', square(0, 0))
    taken = Watch('/robot', 'w1', COLOUR, 'colour', LEFT, CALLBACK, 0.5, 30.0, False, clock.now + 20.0)
    assert stored_watch(taken, clock.now).left == 20.0
    watch = adopted_watch(stored_watch(taken, clock.now), clock.now)
    assert watch == taken
    assert table.adopt(watch) is True
    assert table.adopt(watch) is False  # it stands here already
    assert sent(table.sync()) == [(NEW, 'cam1', 20.0)]
    renewed = table.request('/robot', 'w1', COLOUR, 'colour', LEFT, CALLBACK, 0.5, 30.0, False)
    assert (renewed.change, renewed.duration) == (RENEWED, 30.0)  # the robot renews it here
    clock.now += 30.0
    assert sent(table.sync()) == [(WITHDRAWAL, 'cam1', 0.0)]
