"""Watches on a live vision system (render, test/worlds/small.yaml), called directly: no server."""

import pytest

from drvs.ros.service_client import ServiceCallError, ServiceClient
from drvs.sim.world_file import load_world
from drvs.srv import (
    DetectObjectBoundary,
    DetectObjectBoundaryRequest,
    WatchObjectBoundary,
    WatchObjectBoundaryRequest,
)
from drvs.testing import echo, read_json_lines, wait_for

pytestmark = pytest.mark.shared_master  # see test/conftest.py

WORLD = 'test/worlds/small.yaml'
CALLBACK = '/robot/callback_coordinates'
SERVICE = '/vs1/watch_object_boundary'


def watch(request_id, algorithm='', period=0.2, duration=30.0, changes_only=False, region=(0, 0, 4, 3)):
    message = WatchObjectBoundaryRequest(
        algorithm=algorithm,
        callback_service=CALLBACK,
        request_id=request_id,
        period=period,
        duration=duration,
        changes_only=changes_only,
    )
    r = message.region_of_interest
    r.min_x, r.min_y, r.max_x, r.max_y = region
    client = ServiceClient(SERVICE, WatchObjectBoundary, 10.0)
    try:
        return client.call(message)
    finally:
        client.close()


def test_watches_call_back_every_period_or_on_changes_and_stop_when_cancelled(graph):
    ros, obstacle = graph, load_world(WORLD).colour_models['obstacle']
    output = ros.root / 'callbacks.jsonl'
    recorder = ros.start_node('test/nodes/callback_recorder.py', name='recorder', params={'output': output})
    vs1 = ros.start_node('nodes/vision_system', name='vs1', params={'world': WORLD})
    ros.wait_for_service(CALLBACK, node=recorder)
    ros.wait_for_service(SERVICE, node=vs1)

    def callbacks(request_id):
        return [c for c in read_json_lines(output) if c['request_id'] == request_id]

    def wait_callbacks(request_id, count):
        return wait_for(
            lambda: len(found := callbacks(request_id)) >= count and found,
            30,
            f'{count} callback(s) for {request_id}',
            on_timeout=vs1.describe,
        )

    wrong = ServiceClient(SERVICE, DetectObjectBoundary, 10.0)  # a caller of the wrong type: refused
    with pytest.raises(ServiceCallError, match='md5sums do not match'):
        wrong.call(DetectObjectBoundaryRequest(algorithm=obstacle))
    wrong.close()
    reply = watch('bad', obstacle, period=0.0)
    assert (reply.accepted, reply.message) == (
        False,
        'period: 0; expected a finite number of seconds greater than 0',
    )

    # Without changes_only: a callback every period while the crate is there.
    reply = watch('crate', obstacle, period=0.01, duration=3600.0)
    assert (reply.accepted, reply.vision_systems) == (True, 1)
    assert (reply.period, reply.duration) == (pytest.approx(0.1), 60.0)  # ~min/max_watch_*: the grant
    assert watch('crate', obstacle, period=0.2).period == pytest.approx(0.2)  # renewed, slower
    for callback in wait_callbacks('crate', 3):
        assert (callback['algorithm'], callback['vision_system']) == (obstacle, '/vs1/detect_object_boundary')
        assert len(callback['objects']) == 1

    # changes_only on a static scene: one callback, then none while the frames keep coming.
    assert watch('still', obstacle, changes_only=True).accepted
    wait_callbacks('still', 1)
    wait_callbacks('crate', len(callbacks('crate')) + 5)  # both are due on the same ticks
    assert len(callbacks('still')) == 1

    # A cancel stops the callbacks (one may be on its way); cancelling an unknown watch is fine too.
    reply = watch('crate', duration=0.0)
    assert (reply.accepted, reply.vision_systems) == (True, 0)
    cancelled_at = len(callbacks('crate'))
    assert watch('never was', duration=0.0).accepted
    assert watch('ticker', obstacle).accepted
    wait_callbacks('ticker', 5)
    assert len(callbacks('crate')) <= cancelled_at + 1
    assert len(callbacks('still')) == 1

    # ~stats come at most every 0.5 s: wait for the one that counts every watch call above
    stats = wait_for(lambda: (s := echo(ros, '/vs1/stats'))['watch_calls'] >= 6 and s, 10, 'stats')
    assert (stats['watch_calls'], stats['watches']) == (6, 2)  # crate x2, still, cancels x2, ticker
    assert 0 < stats['callbacks'] <= len(read_json_lines(output))
    frames = stats['renders'] + stats['cache_hits']
    assert 0 < frames < stats['watch_evaluations']  # one frame for all the watches due together
    assert stats['requests'] == 0
