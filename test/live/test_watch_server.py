"""Watches through the DRVS server, live: a private master, the server, a callback recorder and
two fake vision systems (``test/nodes/fake_vision_system.py``), one with a watch service and
one with the paper's interface only."""

import doctest

import pytest
from test_server import CALLBACK, COLOUR, square

import drvs.ros.server_forwarding
from drvs.common.status import ACCEPTED, INVALID, UNSUPPORTED
from drvs.msg import BoundingBox
from drvs.ros.service_client import ServiceClient
from drvs.srv import WatchObjectBoundary
from drvs.testing import echo, wait_for

pytestmark = pytest.mark.shared_master  # see test/conftest.py

WATCH = '/drvs/watch_object_boundary'
ROBOT = '/robot_test'  # the test's caller id: watches are keyed by it
BOTH = (0.5, 0.5, 3.5, 1.5)  # meets vw's square(0, 0, 2, 2) and vp's square(2, 0, 4, 2)
VW_ONLY = (0.5, 0.5, 1.5, 1.5)


class Watcher:
    """Calls ``/drvs/watch_object_boundary`` as ``caller``."""

    def __init__(self, caller=ROBOT):
        self.client = ServiceClient(WATCH, WatchObjectBoundary, 10.0, caller_id=caller)

    def __call__(self, request_id, region=BOTH, period=0.2, duration=30.0, **fields):
        fields = {'algorithm': COLOUR, 'callback_service': CALLBACK, 'changes_only': True, **fields}
        request = WatchObjectBoundary._request_class(
            region_of_interest=BoundingBox(*region),
            request_id=request_id,
            period=period,
            duration=duration,
            **fields,
        )
        return self.client.call(request)

    def close(self):
        self.client.close()


@pytest.fixture
def watcher():
    made = Watcher()
    yield made
    made.close()


def outcome(answer):
    return answer.accepted, answer.status, answer.vision_systems, answer.message


def test_doctests():
    assert doctest.testmod(drvs.ros.server_forwarding).failed == 0  # watch_service_of


def test_a_watch_reaches_both_kinds_of_vision_system_follows_them_and_expires(ros, make_graph, watcher):
    graph = make_graph()
    graph.camera('vw', square(0, 0, 2, 2), watch=True)
    graph.camera('vp', square(2, 0, 4, 2))
    assert 'registered /vw/detect_object_boundary by /vw: field of view' in graph.server.log()
    assert '; a watch service' in graph.server.log()
    assert 'no watch service (watches by one-shot requests)' in graph.server.log()

    answer = watcher('w1')
    assert outcome(answer) == (True, ACCEPTED, 2, "watch 'w1' started; 2 vision systems serve it")
    assert (answer.period, answer.duration) == (pytest.approx(0.2), 30.0)

    def watch_forwards():
        return [(r['request_id'], r['duration']) for r in graph.records('vw', 'watch')]

    wait_for(lambda: watch_forwards(), 10, 'the watch forward to vw', on_timeout=ros.describe)
    (first,) = graph.records('vw', 'watch')
    assert {k: v for k, v in first.items() if k not in ('period', 'duration')} == {
        'kind': 'watch',
        'algorithm': COLOUR,
        'region_of_interest': list(BOTH),
        'callback_service': CALLBACK,
        'request_id': 'w1',
        'caller': '/drvs',
        'changes_only': True,
    }
    assert (first['period'], first['duration']) == (pytest.approx(0.2), pytest.approx(30.0, abs=0.5))
    # The paper-only vision system gets one-shot requests every period, named like the watch.
    wait_for(lambda: len(graph.forwards('vp')) >= 3, 10, 'one-shots to vp', on_timeout=ros.describe)
    assert {(r['request_id'], r['callback_service'], r['caller']) for r in graph.forwards('vp')} == {
        ('w1', CALLBACK, '/drvs')
    }

    # vw moves away: withdrawn; it moves back: forwarded again, with the time left.
    ros.master.call('setParam', '/vw/field_of_view', square(10, 0, 12, 2))
    wait_for(lambda: watch_forwards()[1:] == [('w1', 0.0)], 10, 'the withdrawal', on_timeout=ros.describe)
    ros.master.call('setParam', '/vw/field_of_view', square(0, 0, 2, 2))
    wait_for(lambda: len(watch_forwards()) == 3, 10, 'the forward to vw, back', on_timeout=ros.describe)
    assert 0 < watch_forwards()[2][1] < 30
    # A renewal renews it on vw (vp's one-shots just go on).
    assert outcome(watcher('w1')) == (True, ACCEPTED, 2, "watch 'w1' renewed; 2 vision systems serve it")
    wait_for(lambda: len(watch_forwards()) == 4, 10, 'the renewal', on_timeout=ros.describe)
    assert watch_forwards()[3] == ('w1', pytest.approx(30.0))
    # vw unregisters: withdrawn.
    ros.master.call('setParam', '/vw/field_of_view', [])
    wait_for(lambda: len(watch_forwards()) == 5, 10, 'the withdrawal', on_timeout=ros.describe)
    assert watch_forwards()[4] == ('w1', 0.0)
    assert outcome(watcher('w1', duration=0.0)) == (True, ACCEPTED, 0, "watch 'w1' cancelled")

    # A watch not renewed expires and is withdrawn.
    ros.master.call('setParam', '/vw/field_of_view', square(0, 0, 2, 2))
    wait_for(lambda: len(graph.registrations('vw')) == 5, 10, 'vw back', on_timeout=ros.describe)
    short = watcher('short', region=VW_ONLY, duration=1.0)
    assert outcome(short) == (True, ACCEPTED, 1, "watch 'short' started; 1 vision system serves it")
    wait_for(
        lambda: watch_forwards()[-2:] == [('short', pytest.approx(1.0)), ('short', 0.0)],
        10,
        'the expiry',
        on_timeout=ros.describe,
    )
    assert f"watch 'short' of {ROBOT} expired (not renewed within 1 s)" in graph.server.log()
    assert f"watch 'w1' of {ROBOT} cancelled" in graph.server.log()

    # Every counter, once all has settled.
    def settled():
        stats = echo(ros, '/drvs/stats')
        expected = {
            'requests': 0,
            'watch_requests': 4,
            'refused': 0,
            'forwards': len(graph.forwards('vp')),
            'watch_forwards': len(watch_forwards()),
            'forward_failures': 0,
            'watches': 0,
            'fallback_forwards': len(graph.forwards('vp')),
        }
        return stats if {key: stats[key] for key in expected} == expected else None

    wait_for(settled, 30, 'the stats', on_timeout=ros.describe)
    assert graph.server.running()


def test_bad_watch_calls_are_refused_naming_the_field(ros, make_graph, watcher):
    graph = make_graph()
    assert outcome(watcher('early')) == (
        True,
        ACCEPTED,
        0,
        "watch 'early' started; 0 vision systems serve it",
    )
    graph.camera('vw', square(0, 0, 2, 2), watch=True)
    wait_for(lambda: graph.records('vw', 'watch'), 10, 'a watch that stood before vw registered')
    assert graph.records('vw', 'watch')[0]['request_id'] == 'early'

    cases = [
        (
            {'request_id': ''},
            INVALID,
            'request_id: empty; it names the watch (renew or cancel it with the same)',
        ),
        (
            {'period': float('nan')},
            INVALID,
            'period: nan; expected a finite number of seconds greater than 0',
        ),
        ({'duration': -1.0}, INVALID, 'duration: -1; expected a finite number of seconds, 0 to cancel'),
        ({'region': (2, 0, 1, 1)}, INVALID, 'region_of_interest: min_x 2 is greater than max_x 1'),
        (
            {'callback_service': '/nobody/callback'},
            INVALID,
            'callback_service: /nobody/callback is not known to the ROS master',
        ),
        (
            {'algorithm': 'sift:1'},
            UNSUPPORTED,
            "algorithm: no registered vision system runs 'sift'; available: apriltag, colour, motion",
        ),
    ]
    for fields, status, message in cases:
        answer = watcher(fields.pop('request_id', 'bad'), **fields)
        assert outcome(answer) == (False, status, 0, message)
    # The pair (callback_service, request_id) belongs to the first caller.
    other = Watcher('/other_robot')
    try:
        assert outcome(other('early')) == (
            False,
            INVALID,
            0,
            f"request_id: 'early' with callback_service {CALLBACK} already names a watch of {ROBOT}; "
            'vision systems could not tell the two apart: choose another request_id',
        )
        # A cancel of a watch that does not stand is accepted: it is gone either way.
        assert outcome(other('early', duration=0.0)) == (
            True,
            ACCEPTED,
            0,
            "no watch 'early' stands: nothing to cancel",
        )
    finally:
        other.close()
    # The last vision system running the watch's algorithm stops running it: a renewal still
    # stands (for the vision systems to come), a new watch with that algorithm is UNSUPPORTED.
    ros.master.call('setParam', '/vw/algorithms', ['apriltag'])
    wait_for(lambda: graph.registrations('vw')[-1]['algorithms'] == ['apriltag'], 10, 'vw runs apriltag only')
    assert outcome(watcher('early')) == (
        True,
        ACCEPTED,
        0,
        "watch 'early' renewed; 0 vision systems serve it",
    )
    assert outcome(watcher('new'))[:3] == (False, UNSUPPORTED, 0)
    ros.master.call('setParam', '/vw/algorithms', [])
    wait_for(lambda: graph.registrations('vw')[-1]['algorithms'] == [], 10, 'vw runs the built-ins again')
    # As rosservice calls it, with YAML fields.
    fields = (
        f"{{algorithm: '{COLOUR}', region_of_interest: {{min_x: 0, min_y: 0, max_x: 1, max_y: 1}}, "
        f"callback_service: '{CALLBACK}', request_id: 'cli', period: -1.0, duration: 5.0, "
        'changes_only: false}'
    )
    result = ros.run(f'rosservice call {WATCH} "{fields}"')
    assert result.returncode == 0, result.stderr
    assert 'status: 1' in result.stdout
    assert 'period: -1; expected a finite number of seconds greater than 0' in result.stdout
    assert "watch call 'cli' from" in graph.server.log()
    assert graph.server.running()
