"""The registry: register, move, renew, unregister, leases, failure counts and algorithms (no ROS)."""

import doctest

import pytest

import drvs.server.registry
from drvs.common.status import UNAVAILABLE, Refusal
from drvs.server.registry import Registry, ValidationError, algorithm_names
from drvs.server.spatial_index import FieldOfViewIndex
from drvs.testing import ManualClock


def square(x, y, size=1.0):
    return [(x, y), (x + size, y), (x + size, y + size), (x, y + size)]


def names(entries):
    return [entry.service_name for entry in entries]


@pytest.fixture
def clock():
    return ManualClock()


@pytest.fixture
def registry(clock, new_registry):
    """A registry of each backend (memory, PostgreSQL: test/unit/server/conftest.py)."""
    return new_registry(lease=10.0, max_failures=3, clock=clock)


def test_register_move_renew_unregister(registry):
    assert registry.register('/a', square(0, 0)) == 'registered'
    assert registry.match((0.5, 0.5, 0.6, 0.6)) == ['/a']
    version = registry.version
    assert registry.register('/a', square(0, 0)) == 'renewed'
    assert registry.version == version  # a renewal changes nothing listed
    assert registry.register('/a', square(5, 5)) == 'moved'
    assert registry.match((0.5, 0.5, 0.6, 0.6)) == []
    assert registry.match((5.5, 5.5, 5.6, 5.6)) == ['/a']
    assert registry.entries()[0].field_of_view == ((5.0, 5.0), (6.0, 5.0), (6.0, 6.0), (5.0, 6.0))
    assert registry.register('/a', []) == 'unregistered'
    assert registry.register('/a', []) == 'not registered'
    assert registry.match((5.5, 5.5, 5.6, 5.6)) == []
    assert len(registry) == 0


def test_invalid_field_of_view_changes_nothing(registry):
    registry.register('/a', square(0, 0))
    with pytest.raises(ValidationError, match='^field_of_view: 2 vertices; a polygon needs at least 3$'):
        registry.register('/a', [(0, 0), (1, 1)])
    assert registry.match((0.5, 0.5, 0.6, 0.6)) == ['/a']


def test_lease_expires_unless_renewed(registry, clock):
    registry.register('/a', square(0, 0))
    registry.register('/b', square(0, 0))
    clock.now += 6
    registry.register('/b', square(0, 0))  # renewed: lasts until now + 10
    clock.now += 4
    assert registry.match((0, 0, 1, 1)) == ['/b']  # /a expired: no more requests, even before expire()
    assert names(registry.expire()) == ['/a']
    assert '/a' not in registry
    clock.now += 5.9
    assert registry.expire() == []
    clock.now += 0.1
    assert names(registry.expire()) == ['/b']
    assert registry.match((0, 0, 1, 1)) == []


def test_moved_entry_keeps_its_new_lease(registry, clock):
    registry.register('/a', square(0, 0))
    clock.now += 9
    registry.register('/a', square(3, 3))
    clock.now += 2
    assert registry.expire() == []
    assert registry.match((3, 3, 4, 4)) == ['/a']


def test_consecutive_failures_remove_and_eject(registry, clock):
    registry.register('/a', square(0, 0))
    assert registry.record_failure('/a') is None
    assert registry.record_failure('/a') is None
    registry.record_success('/a')  # resets the run of failures
    removed = [registry.record_failure('/a') for _ in range(3)]
    assert removed[:2] == [None, None] and removed[2].service_name == '/a'
    assert '/a' not in registry
    assert registry.record_failure('/a') is None
    with pytest.raises(Refusal) as caught:
        registry.register('/a', square(0, 0))
    assert (caught.value.status, caught.value.retry_after) == (UNAVAILABLE, 10.0)
    assert str(caught.value) == (
        'service_name: /a was removed after 3 failed forwards in a row and is ejected for 10.0 s more '
        '(ejection 1); make its DetectObjectBoundary answer, or restart it, then register again'
    )
    clock.now += 10
    assert registry.register('/a', square(0, 0)) == 'registered'
    assert registry.failures('/a') == 0
    assert registry.match((0, 0, 1, 1)) == ['/a']


def test_a_restarted_instance_is_not_ejected(registry):
    """The ejection holds for the process that failed; a new one (new address) registers at once."""
    registry.register('/a', square(0, 0), instance='rosrpc://host:1')
    for _ in range(3):
        registry.record_failure('/a')
    with pytest.raises(Refusal):
        registry.register('/a', square(0, 0), instance='rosrpc://host:1')
    assert registry.register('/a', square(0, 0), instance='rosrpc://host:2') == 'registered'
    assert registry.get('/a').instance == 'rosrpc://host:2'
    for _ in range(3):
        registry.record_failure('/a')
    with pytest.raises(Refusal) as caught:  # the count is kept: the second ejection is longer
        registry.register('/a', square(0, 0), instance='rosrpc://host:2')
    assert caught.value.retry_after == 20.0


def test_renewals_do_not_reset_failures(registry, clock):
    """A hung camera that keeps renewing is still removed after max_failures forwards."""
    registry.register('/a', square(0, 0))
    for _ in range(2):
        assert registry.record_failure('/a') is None
        clock.now += 5
        assert registry.register('/a', square(0, 0)) == 'renewed'
    assert registry.failures('/a') == 2
    assert registry.record_failure('/a').service_name == '/a'


def test_a_move_resets_failures(registry):
    registry.register('/a', square(0, 0))
    registry.record_failure('/a')
    registry.record_failure('/a')
    assert registry.register('/a', square(2, 2)) == 'moved'
    assert registry.failures('/a') == 0


def test_ejection_grows_with_each_ejection_up_to_the_cap(clock):
    registry = Registry(
        lease=10.0,
        max_failures=1,
        clock=clock,
        ejection_time=10.0,
        max_ejection_time=25.0,
    )
    for expected in (10.0, 20.0, 25.0, 25.0):
        clock.now += 100
        registry.register('/a', square(0, 0))
        assert registry.record_failure('/a') is not None
        assert registry.ejected_until('/a') == clock.now + expected
        with pytest.raises(Refusal) as caught:
            registry.register('/a', square(0, 0))
        assert caught.value.retry_after == expected
    clock.now += 25
    registry.register('/a', square(0, 0))
    registry.record_success('/a')  # a healthy forward forgets past ejections
    registry.record_failure('/a')
    assert registry.ejected_until('/a') == clock.now + 10.0


def test_entry_keeps_provider_and_one_client_until_removed(registry):
    made = []

    class Client:
        closed = False

        def close(self):
            self.closed = True

    def make_client(name, uri):
        made.append(Client())
        return made[-1]

    registry.register('/a', square(0, 0), provider='/vs1', make_client=make_client)
    registry.register('/a', square(0, 0), provider='/vs1', make_client=make_client)
    registry.register('/a', square(3, 3), provider='/vs1', make_client=make_client)
    assert len(made) == 1
    entry = registry.get('/a')
    assert (entry.provider, entry.client) == ('/vs1', made[0])
    assert registry.unregister('/a') is entry and not made[0].closed  # the remover closes it
    registry.register('/a', square(0, 0), provider='/vs1', make_client=make_client)
    assert registry.register('/a', []) == 'unregistered' and made[1].closed


@pytest.mark.parametrize(
    'lease, max_failures, message',
    [(0, 3, 'lease: must be positive, got 0'), (1, 0, 'max_failures: must be at least 1, got 0')],
)
def test_bad_settings(lease, max_failures, message):
    with pytest.raises(ValueError) as caught:
        Registry(lease=lease, max_failures=max_failures)
    assert str(caught.value) == message


def test_many_moves_route_correctly(clock):
    index = FieldOfViewIndex()
    registry = Registry(lease=10.0, clock=clock, index=index)
    for step in range(5):
        for n in range(40):
            registry.register(f'/c{n}', square(n * 2 + step * 100, 0))
        for n in range(0, 40, 7):
            registry.unregister(f'/c{n}')
        expected = sorted(f'/c{n}' for n in range(40) if n % 7)
        assert registry.match((step * 100 - 1, -1, step * 100 + 100, 2)) == expected
        assert registry.match((step * 100 - 50, -1, step * 100 - 2, 2)) == []
    assert len(index) == len(registry) == 34


def test_a_move_is_seen_by_the_next_match():
    """No rebuild, nothing in the background: every change routes at once."""
    registry = Registry(lease=60.0)
    for n in range(500):
        registry.register(f'/c{n}', square(n, 0, 0.5))
    for n in range(500):
        registry.register(f'/c{n}', square(n, 10, 0.5))
        assert registry.match((n, 10, n + 0.5, 10.5)) == [f'/c{n}']
        assert registry.match((n, 0, n + 0.5, 0.5)) == []
    assert registry.match((-1, -1, 600, 1)) == []
    assert len(registry.match((-1, 9, 600, 11))) == 500


def test_registration_keeps_the_outline_as_sent(registry):
    """A closing vertex repeated at the end, or a clockwise outline: the same field of view."""
    registry.register('/cw', [(0, 0), (0, 1), (1, 1), (1, 0), (0, 0)])
    assert registry.get('/cw').field_of_view == ((0.0, 0.0), (0.0, 1.0), (1.0, 1.0), (1.0, 0.0), (0.0, 0.0))
    assert registry.match((0.5, 0.5, 2, 2)) == ['/cw']
    assert registry.match((1, 0, 2, 1)) == []


# -- algorithms ---------------------------------------------------------------------------------


def test_doctests():
    assert doctest.testmod(drvs.server.registry).failed == 0


def test_an_empty_algorithm_list_means_the_built_ins():
    assert algorithm_names([]) == frozenset({'apriltag', 'colour', 'motion'})
    assert algorithm_names(['sift', 'colour', 'sift']) == frozenset({'colour', 'sift'})
    assert algorithm_names(['a' * 64, 'B_2']) == frozenset({'a' * 64, 'B_2'})


NAME_RULE = '(a letter, then letters, digits or _, without :PARAMS)'


@pytest.mark.parametrize(
    'names, message',
    [
        (['colour', 'colour:1,2'], f"algorithms[1]: 'colour:1,2' is not an algorithm NAME {NAME_RULE}"),
        ([''], f"algorithms[0]: '' is not an algorithm NAME {NAME_RULE}"),
        (['2d'], f"algorithms[0]: '2d' is not an algorithm NAME {NAME_RULE}"),
        (['sift\n'], f"algorithms[0]: 'sift\\n' is not an algorithm NAME {NAME_RULE}"),
        (['ok', 'a' * 65], 'algorithms[1]: 65 characters, longer than the limit of 64'),
        (['ok', 7], 'algorithms[1]: expected a string, got int'),
        ([f'a{n}' for n in range(65)], 'algorithms: 65 names, more than the limit of 64'),
    ],
)
def test_bad_algorithm_names_are_refused_and_change_nothing(registry, names, message):
    with pytest.raises(ValidationError) as caught:
        algorithm_names(names)
    assert str(caught.value) == message
    registry.register('/a', square(0, 0), algorithms=['colour'])
    with pytest.raises(ValidationError) as caught:
        registry.register('/a', square(0, 0), algorithms=names)
    assert str(caught.value) == message
    assert registry.get('/a').algorithms == frozenset({'colour'})


def test_match_only_the_vision_systems_that_run_the_algorithm(registry):
    registry.register('/plain', square(0, 0), algorithms=['colour'])
    registry.register('/tags', square(0, 0), algorithms=['colour', 'apriltag'])
    registry.register('/plugin', square(0, 0), algorithms=['sift'])
    registry.register('/builtin', square(5, 5))
    region = (0.5, 0.5, 0.6, 0.6)
    assert registry.match(region) == ['/plain', '/plugin', '/tags']
    assert registry.match(region, 'colour') == ['/plain', '/tags']
    assert registry.match(region, 'apriltag') == ['/tags']
    assert registry.match(region, 'sift') == ['/plugin']
    assert registry.match(region, 'motion') == []
    assert registry.match((5.5, 5.5, 5.6, 5.6), 'motion') == ['/builtin']
    assert registry.get('/builtin').algorithms == frozenset({'apriltag', 'colour', 'motion'})
    assert registry.available_algorithms() == ['apriltag', 'colour', 'motion', 'sift']


def test_available_algorithms_are_those_of_live_entries(registry, clock):
    assert registry.available_algorithms() == []
    registry.register('/a', square(0, 0), algorithms=['sift'])
    clock.now += 6
    registry.register('/b', square(0, 0), algorithms=['surf'])
    assert registry.available_algorithms() == ['sift', 'surf']
    clock.now += 4  # /a's lease ran out, though expire() has not removed it yet
    assert registry.available_algorithms() == ['surf']
    assert registry.match((0, 0, 1, 1), 'sift') == []
    registry.unregister('/b')
    assert registry.available_algorithms() == []


def test_a_new_algorithm_list_is_a_change_and_the_same_one_a_renewal(registry, clock):
    assert registry.register('/a', square(0, 0), algorithms=['colour', 'sift']) == 'registered'
    version = registry.version
    assert registry.register('/a', square(0, 0), algorithms=['sift', 'colour', 'sift']) == 'renewed'
    assert registry.version == version
    registry.record_failure('/a')
    registry.record_failure('/a')
    assert registry.register('/a', square(0, 0), algorithms=['sift']) == 'changed'
    assert registry.version == version + 1
    assert registry.failures('/a') == 0  # like a move
    assert registry.match((0, 0, 1, 1), 'colour') == []
    assert registry.match((0, 0, 1, 1), 'sift') == ['/a']
    clock.now += 9
    assert registry.register('/a', square(3, 3), algorithms=[]) == 'moved'  # both: a move
    assert registry.match((3, 3, 4, 4), 'colour') == ['/a']
    assert registry.register('/a', square(3, 3), algorithms=['apriltag', 'colour', 'motion']) == 'renewed'
    clock.now += 9.5
    assert registry.expire() == []  # each registration renewed the lease


def test_ejected_counts_the_vision_systems_refused_now(registry, clock):
    assert registry.ejected() == 0
    for name in ('/a', '/b'):
        registry.register(name, square(0, 0))
        for _ in range(3):
            registry.record_failure(name)
    assert registry.ejected() == 2
    clock.now += 10  # the first ejection lasts ejection_time: both end
    assert registry.ejected() == 0


def test_each_entry_records_the_site_it_registered_at(clock, new_registry):
    registry = new_registry(lease=10.0, clock=clock, site='hall-a')
    assert registry.register('/a', square(0, 0), instance='rosrpc://h:1') == 'registered'
    registry.sync()
    assert [(e.service_name, e.site) for e in registry.entries()] == [('/a', 'hall-a')]
    assert registry.register('/a', square(0, 0), instance='rosrpc://h:1') == 'renewed'


def test_a_site_name_is_checked(clock):
    with pytest.raises(ValueError, match="^must be letters, digits, _ or -, at most 64 of them, got 'a b'$"):
        Registry(clock=clock, site='a b')
