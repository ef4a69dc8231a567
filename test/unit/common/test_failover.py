"""The order in which a client asks several DRVS servers (replicas)."""

import doctest

import pytest

import drvs.common.failover
from drvs.common.failover import ServerList, moves_on
from drvs.common.status import BUSY, RATE_LIMITED, UNAVAILABLE


def test_doctests():
    assert doctest.testmod(drvs.common.failover).failed == 0


def test_unavailable_or_no_answer_moves_on_and_load_refusals_stay():
    assert moves_on(None) and moves_on(UNAVAILABLE)
    assert not moves_on(BUSY) and not moves_on(RATE_LIMITED)


def test_failures_go_round_the_list_in_order():
    servers = ServerList(['/a', '/b', '/c'])
    assert [servers.current] + [servers.failed() for _ in range(4)] == ['/a', '/b', '/c', '/a', '/b']
    assert ServerList(['/a']).failed() == '/a'


@pytest.mark.parametrize(
    'names, message',
    [
        ([], 'servers: empty; name at least one DRVS server'),
        (['/a', '/b', '/a'], 'servers: /a named more than once'),
    ],
)
def test_bad_lists_are_refused(names, message):
    with pytest.raises(ValueError) as caught:
        ServerList(names)
    assert str(caught.value) == message
