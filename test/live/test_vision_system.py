"""The whole path on a private roscore: world_sim, vision systems, the DRVS server and a test robot."""

import json
import threading
from pathlib import Path

import pytest
from shapely.geometry import Polygon

from drvs.ros.service_client import ServiceClient
from drvs.sim.simulation import loop_of, position_on_loop
from drvs.sim.world import box_footprint
from drvs.sim.world_file import load_world
from drvs.srv import DetectObjectBoundary, DetectObjectBoundaryRequest
from drvs.testing import echo, read_json_lines, wait_for
from drvs.testing.detect import detect as request

pytestmark = pytest.mark.shared_master  # see test/conftest.py

WORLD = 'test/worlds/small.yaml'
CALLBACK = '/robot/callback_coordinates'


def ground_truth_of(ros):
    """One message of world_sim's ground truth (std_msgs/String, JSON), decoded."""
    return json.loads(echo(ros, '/world_sim/ground_truth')['data'])


def stats_of(ros, name):
    """One message of a vision system's ``~stats`` (drvs/VisionSystemStats), with
    ``requests_by_algorithm`` ({algorithm: count}) from its two parallel arrays."""
    stats = echo(ros, f'/{name}/stats')
    stats['requests_by_algorithm'] = dict(zip(stats['algorithms'], stats['algorithm_requests'], strict=True))
    return stats


def start_recorder(ros, **params):
    output = ros.root / 'callbacks.jsonl'
    recorder = ros.start_node(
        'test/nodes/callback_recorder.py', name='recorder', params={'output': output, **params}
    )
    ros.wait_for_service(CALLBACK, node=recorder)
    return output


def callbacks_for(output, request_id, count, ros):
    return wait_for(
        lambda: len(found := [c for c in read_json_lines(output) if c['request_id'] == request_id]) >= count
        and found,
        30,
        f'{count} callback(s) for {request_id}',
        on_timeout=ros.describe,
    )


def covered_by(count, region=(2.0, 1.4, 2.1, 1.5)):
    """A condition: the server forwards a request for ``region`` to ``count`` vision systems."""
    models = load_world(WORLD).colour_models
    return (
        lambda: request('/drvs/detect_object_boundary', models['human'], region, 'probe').vision_systems
        == count
    )


def start_server(ros, **params):
    server = ros.start_node('nodes/drvs_server', name='drvs', params=params)
    ros.wait_for_service('/drvs/detect_object_boundary', node=server)
    return server


def test_the_whole_path_from_world_to_robot(graph):
    ros, world = graph, load_world(WORLD)
    start_server(ros, lease=2.0)
    world_sim = ros.start_node('nodes/world_sim', name='world_sim', params={'world': WORLD})
    for name in ('vs1', 'vs2'):
        ros.start_node('nodes/vision_system', name=name, params={'world': WORLD})
    output = start_recorder(ros)
    wait_for(covered_by(2), 30, 'vs1 and vs2 to register', on_timeout=ros.describe)

    # A static box seen by both cameras: where it stands, from each.
    reply = request('/drvs/detect_object_boundary', world.colour_models['obstacle'], (0, 0, 4, 3), 'crate')
    assert (reply.accepted, reply.vision_systems) == (True, 2)
    callbacks = callbacks_for(output, 'crate', 2, ros)
    assert sorted(c['vision_system'] for c in callbacks) == [
        '/vs1/detect_object_boundary',
        '/vs2/detect_object_boundary',
    ]
    truth = Polygon(world.objects[0].footprint())
    for callback in callbacks:
        assert callback['algorithm'] == world.colour_models['obstacle'] and len(callback['objects']) == 1
        outline = Polygon(callback['objects'][0])
        assert outline.exterior.is_ccw
        assert outline.centroid.distance(truth.centroid) <= 0.03  # 160x120: about 2 cm per pixel
        assert outline.intersection(truth).area / outline.union(truth).area >= 0.8

    # The walker, where world_sim had it when the frame was captured: all of it from vs2 right
    # above it, and from vs1 (if it sees any of it at its image's edge) no more than there is.
    ground_truth = ground_truth_of(ros)
    request('/drvs/detect_object_boundary', world.colour_models['human'], (0, 0, 4, 3), 'walker')
    walker = world.objects[1]
    loop = loop_of(walker.position, walker.waypoints)

    def walker_callbacks_with_vs2():  # vs1's, if any, may come before vs2's
        found = [c for c in read_json_lines(output) if c['request_id'] == 'walker']
        return any(c['vision_system'] == '/vs2/detect_object_boundary' for c in found) and found

    callbacks = wait_for(
        walker_callbacks_with_vs2, 30, "vs2's callback for the walker", on_timeout=ros.describe
    )
    for callback in callbacks:
        at = ground_truth['time'] + callback['stamp'] - ground_truth['stamp']
        truth = Polygon(box_footprint(position_on_loop(loop, walker.speed, at), walker.size, walker.yaw))
        (outline,) = (Polygon(o) for o in callback['objects'])
        assert truth.buffer(0.05).contains(outline)  # 0.05 m: pose and capture are not simultaneous
        if callback['vision_system'] == '/vs2/detect_object_boundary':
            assert outline.centroid.distance(truth.centroid) <= 0.05

    # Ten simultaneous requests cost one render. The connections are opened first (a refused
    # request each: no frame), so the ten arrive together rather than a lookup and handshake apart.
    clients = [ServiceClient('/vs1/detect_object_boundary', DetectObjectBoundary, 10.0) for _ in range(10)]
    for client in clients:
        assert not client.call(DetectObjectBoundaryRequest(algorithm='none')).accepted
    # ~stats come at most every 0.5 s: wait for the one that counts the ten refusals
    before = wait_for(lambda: (s := stats_of(ros, 'vs1'))['refused'] >= 10 and s, 10, 'stats')
    barrier = threading.Barrier(10)
    message = DetectObjectBoundaryRequest(
        algorithm=world.colour_models['obstacle'], callback_service=CALLBACK, request_id='burst'
    )
    message.region_of_interest.max_x, message.region_of_interest.max_y = 4.0, 3.0

    def fire(client):
        barrier.wait(10)
        client.call(message)

    threads = [threading.Thread(target=fire, args=(c,)) for c in clients]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30)
    for client in clients:
        client.close()
    callbacks_for(output, 'burst', 10, ros)
    after = wait_for(
        lambda: (s := stats_of(ros, 'vs1'))['callbacks'] >= before['callbacks'] + 10 and s,
        30,
        'stats',
    )
    assert after['requests'] - before['requests'] == 10
    obstacle = world.colour_models['obstacle']
    assert after['requests_by_algorithm'][obstacle] - before['requests_by_algorithm'].get(obstacle, 0) == 10
    assert 'none' not in after['requests_by_algorithm']  # refused requests are not counted by algorithm
    assert (after['renders'] - before['renders'], after['cache_hits'] - before['cache_hits']) == (1, 9)
    assert after['callback_bytes'] > before['callback_bytes']

    # The robot's body follows /robot/cmd_vel.
    start_x = ground_truth['robot']['position'][0]
    ros.spawn(
        'cmd_vel',
        ['rostopic', 'pub', '-r', '10', '/robot/cmd_vel', 'geometry_msgs/Twist', '{linear: {x: 0.3}}'],
    )
    wait_for(
        lambda: ground_truth_of(ros)['robot']['position'][0] > start_x + 0.1,
        30,
        'the robot to move',
        on_timeout=world_sim.describe,
    )

    # The debug view is rendered for a subscriber.
    result = ros.run('rostopic echo -n 1 /vs1/debug_image/width', timeout=30)
    assert result.stdout.split()[0] == '160'
    assert world_sim.interrupt() == 0


def test_a_vision_system_with_no_entry_in_the_world_exits_with_the_reason(ros):
    node = ros.start_node('nodes/vision_system', name='vs9', params={'world': WORLD})
    wait_for(lambda: not node.running(), 30, 'vs9 to exit')
    assert node.process.returncode == 2
    assert f"{WORLD}: vision_systems: no entry named 'vs9' (known: vs1, vs2, rover)" in node.log()


def test_a_vision_system_waits_for_the_server_survives_a_hung_robot_and_unregisters(graph):
    ros, world = graph, load_world(WORLD)
    vs1 = ros.start_node('nodes/vision_system', name='vs1', params={'world': WORLD, 'callback_timeout': 0.5})
    ros.wait_for_service('/vs1/detect_object_boundary', node=vs1)
    wait_for(lambda: 'waiting for the DRVS server' in vs1.log(), 30, 'vs1 to wait for the server')
    start_server(ros)
    output = start_recorder(ros, delay=10.0)  # a robot that hangs in every callback
    wait_for(covered_by(1), 30, 'vs1 to register once the server is up', on_timeout=ros.describe)

    reply = request('/vs1/detect_object_boundary', 'colour:1,2,3', (0, 0, 4, 3), 'bad')
    assert (reply.accepted, reply.message) == (
        False,
        'algorithm: colour PARAMS must be 6 comma-separated integers RMIN,GMIN,BMIN,RMAX,GMAX,BMAX, '
        "got 3 value(s) in '1,2,3'",
    )
    reply = request('/vs1/detect_object_boundary', world.colour_models['obstacle'], (0, 0, 4, 3), 'slow')
    assert reply.accepted
    wait_for(lambda: stats_of(ros, 'vs1')['callback_failures'] >= 1, 30, 'the hung callback to be dropped')
    assert "callback for request 'slow' dropped" in vs1.log()  # what the user reads, and why:
    assert 'timed out after 0.5 s' in vs1.log()
    callbacks_for(output, 'slow', 1, ros)
    reply = request('/vs1/detect_object_boundary', world.colour_models['obstacle'], (0, 0, 4, 3), 'after')
    assert reply.accepted and vs1.running()
    stats = wait_for(lambda: (s := stats_of(ros, 'vs1'))['callback_failures'] >= 2 and s, 30, 'stats')
    # (requests also counts the server's forwards of the probes that waited for the registration)
    assert (stats['refused'], stats['callbacks'], stats['callback_failures']) == (1, 0, 2)

    assert vs1.interrupt() == 0
    assert echo(ros, '/drvs/registry')['vision_systems'] == []  # unregistered; the lease is 10 s


def test_a_camera_on_a_moving_mount_registers_where_it_looks_and_routing_follows(graph):
    ros = graph
    start_server(ros)
    start_recorder(ros)
    rover = ros.start_node('nodes/vision_system', name='rover', params={'world': WORLD})
    ros.wait_for_service('/rover/detect_object_boundary', node=rover)
    far_end = (3.6, 1.4, 3.7, 1.6)  # seen only while the rover is beyond x = 2.6 (it loops 1 -> 3 -> 1 m)
    wait_for(covered_by(1, far_end), 30, 'the rover to see the far end', on_timeout=ros.describe)
    wait_for(covered_by(0, far_end), 30, 'the rover to leave it again', on_timeout=ros.describe)
    wait_for(covered_by(1, far_end), 30, 'the rover to come back', on_timeout=ros.describe)


def test_a_rendering_vision_system_finds_what_stands_on_the_floor_without_its_colour(graph):
    """elevation on the simulation's noisy depth (the world's ``depth_noise``) and foreground
    against the render of the empty world: the crate where it stands, elevation with its height."""
    import yaml

    ros = graph
    data = yaml.safe_load(Path(WORLD).read_text())
    data['vision_systems'] = [
        {
            'name': 'vs1',
            'position': [1.0, 1.5, 3.0],
            'fov_deg': 60,
            'resolution': [320, 240],
            'depth_noise': True,
        }
    ]
    world_path = ros.root / 'noisy.yaml'
    world_path.write_text(yaml.safe_dump(data))
    start_server(ros, lease=2.0)
    vs1 = ros.start_node('nodes/vision_system', name='vs1', params={'world': world_path})
    output = start_recorder(ros)
    ros.wait_for_service('/vs1/detect_object_boundary', node=vs1)
    crate = Polygon(box_footprint((1.2, 1.0), (0.4, 0.4), 0.0))
    region = (0.8, 0.6, 1.6, 1.4)  # around the crate only
    for request_id, algorithm in (('standing', 'elevation:0.1'), ('different', 'foreground')):
        reply = request('/vs1/detect_object_boundary', algorithm, region, request_id)
        assert reply.accepted, reply.message
        (callback,) = callbacks_for(output, request_id, 1, ros)
        (outline,) = callback['objects']
        assert Polygon(outline).intersection(crate).area / Polygon(outline).union(crate).area > (
            0.8 if algorithm.startswith('elevation') else 0.6
        ), algorithm
    standing = callbacks_for(output, 'standing', 1, ros)[0]
    assert standing['heights'] == [pytest.approx(0.5, abs=0.03)]
