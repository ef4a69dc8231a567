"""Clients of two drvs_server replicas on one database (~servers, docs/registry.md "Replicas"): kill -9 of
the replica they use while a blind robot drives and two vision systems renew; both move to the other."""

import os
import signal
import time

import psycopg
import pytest

from drvs.msg import BoundingBox
from drvs.ros.service_client import ServiceClient
from drvs.sim.world_file import load_world
from drvs.srv import DetectObjectBoundary, DetectObjectBoundaryRequest
from drvs.testing import echo, wait_for

WORLD = 'test/worlds/small.yaml'
LEASE = 4.0  # the servers' lease, and the robot's ~watch_duration
SERVERS = ['/drvs', '/drvs_b']
CAMERAS = ('/vs1/detect_object_boundary', '/vs2/detect_object_boundary')


def owners(connection):
    """(the replica each camera renews through, the owner of each of the robot's live watches)."""
    cameras = dict(connection.execute('SELECT service_name, replica FROM drvs_vision_systems').fetchall())
    watches = [
        row[0]
        for row in connection.execute(
            'SELECT owner FROM drvs_watches WHERE caller = %s AND expires_at > '
            'extract(epoch FROM clock_timestamp())',
            (b'/robot',),
        )
    ]
    return cameras, watches


def through(replica, cameras, watches):
    """Whether both cameras renew, and the robot's watches (some) stand, through ``replica``."""
    return (
        sorted(cameras) == list(CAMERAS)
        and all(owner.startswith(f'{replica}@') for owner in cameras.values())
        and len(watches) >= 2
        and all(owner.startswith(f'{replica}@') for owner in watches)
    )


@pytest.mark.slow  # 12-35 s: a world, two cameras, a robot, two servers, two leases after the kill
def test_a_robot_and_vision_systems_move_to_the_other_replica_within_a_lease_of_a_kill_9(
    graph, postgres, request
):
    ros = graph
    postgres.empty()
    server = {
        'registry': postgres.dsn,
        'lease': LEASE,
        'watch_takeover': 60.0,
        'unavailable_retry_after': 0.5,
    }
    first = ros.start_node('nodes/drvs_server', name='drvs', params=server)
    second = ros.start_node('nodes/drvs_server', name='drvs_b', params=server)
    ros.wait_for_service('/drvs/detect_object_boundary', node=first)
    ros.wait_for_service('/drvs_b/detect_object_boundary', node=second)
    ros.start_node('nodes/world_sim', name='world_sim', params={'world': WORLD})
    for name in ('vs1', 'vs2'):
        ros.start_node('nodes/vision_system', name=name, params={'world': WORLD, 'servers': SERVERS})
    robot = ros.start_node(
        'nodes/blind_robot',
        name='robot',
        params={'world': WORLD, 'servers': SERVERS, 'speed': 0.1, 'watch_duration': LEASE},
    )
    database = psycopg.connect(postgres.dsn, autocommit=True)
    request.addfinalizer(database.close)
    wait_for(lambda: through('/drvs', *owners(database)), 60, 'all through /drvs', 0.2, ros.describe)

    os.killpg(first.pid, signal.SIGKILL)
    killed = time.monotonic()
    first.process.wait(10)
    wait_for(lambda: through('/drvs_b', *owners(database)), 30, 'all through /drvs_b', 0.1, ros.describe)
    moved = time.monotonic() - killed
    assert moved < LEASE, f'the clients moved {moved:.1f} s after the kill; the lease is {LEASE:g} s'

    before = echo(ros, '/robot/status')
    wait_for(
        lambda: echo(ros, '/robot/status')['callbacks'] > before['callbacks'], 10, 'callbacks after the move'
    )
    status = echo(ros, '/robot/status')
    assert status['state_name'] != 'failed' and status['watches'] >= 2, status
    # Two leases after the kill nothing registered through the first has expired: both cameras
    # renew through the second, which matches them.
    region = load_world(WORLD).floor_size
    client = ServiceClient('/drvs_b/detect_object_boundary', DetectObjectBoundary, 5.0)
    try:
        wait_for(lambda: time.monotonic() - killed > 2 * LEASE, 3 * LEASE, 'two leases')
        answer = client.call(
            DetectObjectBoundaryRequest(
                algorithm=load_world(WORLD).colour_models['obstacle'],
                region_of_interest=BoundingBox(0.0, 0.0, *region),
                callback_service='/robot/callback_coordinates',
                request_id='probe',
            )
        )
    finally:
        client.close()
    assert answer.vision_systems == 2, answer.message
    assert through('/drvs_b', *owners(database))
    assert robot.running()
