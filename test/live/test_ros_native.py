"""A running DRVS as stock ROS tools see it: /diagnostics, ``rostopic echo``, RViz markers and tf.

Each test reads the graph the way a ROS user would: the health statuses as
``rqt_robot_monitor`` gets them (a subscriber to /diagnostics records them), the typed
topics through Debian's ``rostopic echo -n 1``, /drvs/markers as RViz gets it, and
tf through a tf2 listener (test/nodes/tf_lookup.py).
"""

import json
import math
import socket
from dataclasses import dataclass
from pathlib import Path

import pytest
from shapely.geometry import Polygon

from drvs.common.health import ERROR, OK, WARN
from drvs.common.transforms import matrix_from_quaternion
from drvs.msg import BodyPoses, Registry, RobotStatus, VisionSystemStats
from drvs.ros.markers import DETECTION_LIFETIME, algorithm_colour
from drvs.sim.world_file import load_world
from drvs.testing import RosHarness, echo, read_json_lines, seconds, wait_for
from drvs.testing.detect import detect
from drvs.vision.camera import PinholeCamera
from drvs.vision.optics import optical_pose_of

pytestmark = pytest.mark.shared_master  # see test/conftest.py

WORLD = 'test/worlds/small.yaml'
CALLBACK = '/robot/callback_coordinates'
LINE_STRIP, DELETEALL = 4, 3  # visualization_msgs/Marker type and action
SMALL_CAMERA = {  # test/nodes/synthetic_camera.py, straight down over a blue box
    'eye': [2.0, 1.5, 3.0],
    'target': [2.0, 1.5, 0.0],
    'width': 160,
    'height': 120,
    'fx': 130.0,
    'fy': 130.0,
    'box': [[1.8, 1.3], [2.2, 1.3], [2.2, 1.7], [1.8, 1.7]],
    'frame_id': 'cam1_optical_frame',
}
CAMERA_TOPICS = {'image': '/synthetic_camera/image_raw', 'camera_info': '/synthetic_camera/camera_info'}


# -- helpers ---------------------------------------------------------------------------------------


def start_server(ros, **params):
    server = ros.start_node('nodes/drvs_server', name='drvs', params=params)
    ros.wait_for_service('/drvs/detect_object_boundary', node=server)
    return server


def start_recorder(ros, topic: str) -> Path:
    """A subscriber that records every message of ``topic`` (test/nodes/topic_recorder.py)."""
    name = topic.strip('/').replace('/', '_')
    output = ros.root / f'{name}.jsonl'
    ros.start_node(
        'test/nodes/topic_recorder.py', name=f'{name}_recorder', params={'topic': topic, 'output': output}
    )
    return output


def statuses(output: Path, name: str) -> list[dict]:
    """Every recorded /diagnostics status named ``name``, oldest first, its values as a dict."""
    found = []
    for line in read_json_lines(output):
        for status in line['data']['status']:
            if status['name'] == name:
                found.append({**status, 'values': {pair['key']: pair['value'] for pair in status['values']}})
    return found


def wait_status(ros, output: Path, name: str, condition, what: str, timeout: float = 30.0) -> dict:
    """The newest status named ``name`` once ``condition(status)`` holds for it."""

    def newest():
        found = statuses(output, name)
        return found[-1] if found and condition(found[-1]) else None

    return wait_for(
        newest,
        timeout,
        f'{name}: {what}',
        interval=0.2,
        on_timeout=lambda: f'newest status: {statuses(output, name)[-1:]}\n{ros.describe()}',
    )


def registered(count: int) -> bool:
    """Whether the server forwards a request for vs1's part of the floor to ``count`` vision systems."""
    reply = detect('/drvs/detect_object_boundary', 'colour:0,0,150,80,80,255', (1.0, 1.4, 1.1, 1.5), 'probe')
    return reply.vision_systems == count


def tf_lookup(ros, *pairs: tuple[str, str]) -> dict[str, dict]:
    """Each (parent, child) looked up on tf: {child: {'stamp', 'translation', 'rotation'}}."""
    frames = ' '.join(f'{parent} {child}' for parent, child in pairs)
    result = ros.run(f'python test/nodes/tf_lookup.py --timeout 20 {frames}', timeout=60)
    assert result.returncode == 0, f'{result.stderr}\n{ros.describe()}'
    return {line['child']: line for line in map(json.loads, result.stdout.splitlines())}


def echoed_fields(ros, topic: str, message_class) -> dict:
    """``rostopic echo -n 1 topic``, checked to show every field of ``message_class`` and no other."""
    shown = echo(ros, topic)
    assert sorted(shown) == sorted(message_class.__slots__), topic
    return shown


# -- /diagnostics ----------------------------------------------------------------------------------


def test_the_server_and_a_rendering_camera_report_their_health_until_the_server_goes(graph):
    ros = graph
    diagnostics = start_recorder(ros, '/diagnostics')
    server = start_server(ros, lease=2.0)  # renewed every second: a lost server shows soon

    status = wait_status(ros, diagnostics, 'drvs: /drvs', lambda s: True, 'a first status')
    assert (status['level'], status['message']) == (WARN, 'no vision system registered')
    assert status['hardware_id'] == socket.gethostname()
    assert status['values']['registered vision systems'] == '0'
    assert status['values']['refused BUSY (since start)'] == '0'

    ros.start_node('nodes/vision_system', name='vs1', params={'world': WORLD})
    status = wait_status(ros, diagnostics, 'drvs: /vs1', lambda s: s['level'] == OK, 'OK once registered')
    assert (status['message'], status['hardware_id']) == ('ok', 'vs1')
    values = status['values']
    assert (values['registered'], values['source'], values['frame age (s)']) == ('yes', 'render', 'none')
    assert values['queue size'] == '32'
    status = wait_status(ros, diagnostics, 'drvs: /drvs', lambda s: s['level'] == OK, 'OK with vs1')
    assert status['values']['registered vision systems'] == '1'

    # RViz: one field of view (and its name) per registered camera, after a DELETEALL.
    markers = wait_for(
        lambda: m if len((m := echo(ros, '/drvs/markers'))['markers']) == 3 else None,
        30,
        'the field of view of vs1 on /drvs/markers',
    )['markers']
    assert markers[0]['action'] == DELETEALL
    assert [(m['ns'], m['type'], m['header']['frame_id']) for m in markers[1:2]] == [
        ('fields_of_view', LINE_STRIP, 'map')
    ]
    assert markers[2]['text'] == 'vs1'

    server.stop()  # the server is gone: vs1 cannot renew, and its lease runs out
    status = wait_status(ros, diagnostics, 'drvs: /vs1', lambda s: s['level'] != OK, 'a warning')
    assert status['level'] == WARN
    assert status['message'].startswith('not registered: service /drvs/register_vision_service: ')
    assert (status['values']['registered'], status['values']['last registration refusal']) == ('no', 'none')


def test_a_topic_camera_whose_feed_stops_reports_an_error(graph):
    ros = graph
    diagnostics = start_recorder(ros, '/diagnostics')
    start_server(ros, lease=2.0)
    camera = ros.start_node('test/nodes/synthetic_camera.py', name='synthetic_camera', params=SMALL_CAMERA)
    ros.start_node(
        'nodes/vision_system',
        name='cam1',
        params={'source': 'topic', 'stale_after': 1.0},
        remap=CAMERA_TOPICS,
    )
    status = wait_status(ros, diagnostics, 'drvs: /cam1', lambda s: s['level'] == OK, 'OK with frames')
    assert (status['hardware_id'], status['values']['source']) == ('cam1', 'topic')
    assert status['values']['frame age (s)'] != 'none'

    camera.stop()
    status = wait_status(ros, diagnostics, 'drvs: /cam1', lambda s: s['level'] == ERROR, 'an error')
    assert status['message'].startswith('camera feed stale: last frame ')
    assert '(stale after 1 s)' in status['message']
    assert status['values']['stale after (s)'] == '1.00'


def test_the_blind_robot_reports_its_state_and_echo_shows_its_status(ros):
    from test_blind_robot import NEAR, start, write_world

    diagnostics = start_recorder(ros, '/diagnostics')
    start(ros, write_world(ros.root, [], start=NEAR), robot_params={'once': False})
    status = wait_status(
        ros, diagnostics, 'drvs: /robot', lambda s: s['values']['state'] == 'arrived', 'arrived', timeout=60
    )
    assert (status['level'], status['message'], status['hardware_id']) == (OK, 'ok', 'robot')
    assert (status['values']['covered'], status['values']['fix timeout (s)']) == ('yes', '5.00')
    assert status['values']['fix age (s)'] != 'none'
    assert {s['values']['state'] for s in statuses(diagnostics, 'drvs: /robot')} <= {
        'localising',
        'moving',
        'blocked',
        'arriving',
        'arrived',
    }

    shown = echoed_fields(ros, '/robot/status', RobotStatus)
    assert (shown['state'], shown['state_name'], shown['reason']) == (RobotStatus.ARRIVED, 'arrived', '')
    assert shown['header']['frame_id'] == 'map' and shown['has_position'] is True
    assert set(shown['roles']) >= {'self', 'station'}

    # Its belief, for RViz: where its status says it is, in map.
    pose = echo(ros, '/robot/pose')
    assert pose['header']['frame_id'] == 'map'
    believed = (pose['pose']['position']['x'], pose['pose']['position']['y'])
    assert math.dist(believed, (shown['position']['x'], shown['position']['y'])) < 0.05


# -- one stack: world_sim, the server, vs1 ---------------------------------------------------------


@dataclass
class Stack:
    ros: RosHarness
    callbacks: Path
    markers: Path


@pytest.fixture(scope='module')
def stack():
    with pytest.MonkeyPatch.context() as monkeypatch, RosHarness() as ros:
        monkeypatch.setenv('ROS_MASTER_URI', ros.master.uri)
        monkeypatch.setenv('ROS_HOSTNAME', '127.0.0.1')
        start_server(ros)
        ros.start_node('nodes/world_sim', name='world_sim', params={'world': WORLD})
        ros.start_node('nodes/vision_system', name='vs1', params={'world': WORLD})
        callbacks = ros.root / 'callbacks.jsonl'
        recorder = ros.start_node(
            'test/nodes/callback_recorder.py', name='robot', params={'output': callbacks}
        )
        ros.wait_for_service(CALLBACK, node=recorder)
        markers = start_recorder(ros, '/drvs/markers')
        wait_for(lambda: registered(1), 30, 'vs1 to register', on_timeout=ros.describe)
        yield Stack(ros, callbacks, markers)


def test_rostopic_echo_shows_the_fields_of_the_registry_the_stats_and_the_poses(stack):
    ros = stack.ros
    registry = echoed_fields(ros, '/drvs/registry', Registry)
    (entry,) = registry['vision_systems']
    assert (entry['service_name'], entry['provider']) == ('/vs1/detect_object_boundary', '/vs1')
    assert entry['algorithms'] == ['apriltag', 'colour', 'elevation', 'foreground', 'motion']
    assert len(entry['field_of_view']['points']) >= 3 and seconds(entry['lease_expiry']) > 0

    stats = echoed_fields(ros, '/vs1/stats', VisionSystemStats)
    assert stats['registrations'] >= 1 and len(stats['algorithms']) == len(stats['algorithm_requests'])

    poses = echoed_fields(ros, '/world_sim/poses', BodyPoses)
    assert poses['header']['frame_id'] == 'map' and seconds(poses['header']['stamp']) > 0
    assert set(poses['names']) == {'robot', 'station', 'crate', 'walker'}
    robot = poses['poses'][poses['names'].index('robot')]
    assert (robot['x'], robot['y']) == pytest.approx((0.5, 1.5), abs=0.01)  # nothing moves it
    assert set(robot) == {'x', 'y', 'theta'}


def test_a_callback_shows_its_outlines_on_the_markers_coloured_by_algorithm(stack):
    ros, world = stack.ros, load_world(WORLD)
    obstacle = world.colour_models['obstacle']
    asked = []

    def detection_markers():
        arrays = [line['data']['markers'] for line in read_json_lines(stack.markers)]
        found = [m for array in arrays for m in array if m['ns'].startswith('detections/')]
        if not found:  # vs1 publishes only once it sees the recorder subscribed: ask again
            asked.append(f'markers-{len(asked)}')
            detect('/drvs/detect_object_boundary', obstacle, (0.0, 0.0, 4.0, 3.0), asked[-1])
        return found

    marker = wait_for(detection_markers, 30, 'detection markers', interval=0.5, on_timeout=ros.describe)[0]
    assert {c['request_id'] for c in read_json_lines(stack.callbacks)} & set(asked)  # a callback was sent
    assert marker['ns'] == f'detections/vs1/detect_object_boundary/{obstacle}'
    assert (marker['id'], marker['type'], marker['header']['frame_id']) == (0, LINE_STRIP, 'map')
    assert seconds(marker['lifetime']) == DETECTION_LIFETIME
    colour = marker['color']
    assert [colour['r'], colour['g'], colour['b']] == pytest.approx(algorithm_colour(obstacle)[:3], abs=1e-6)
    ring = [(p['x'], p['y']) for p in marker['points']]
    assert ring[0] == ring[-1]  # closed
    crate = Polygon(world.objects[0].footprint())
    assert crate.buffer(0.05).contains(Polygon(ring))


def test_tf_has_the_rendering_cameras_optical_frame_and_every_body(stack):
    world = load_world(WORLD)
    pairs = [('map', frame) for frame in ('vs1_optical_frame', 'robot', 'walker', 'station', 'crate')]
    found = tf_lookup(stack.ros, *pairs)
    rotation, eye = optical_pose_of(PinholeCamera.from_config(world.camera('vs1')))
    camera = found['vs1_optical_frame']
    assert camera['translation'] == pytest.approx(list(eye), abs=1e-9)
    assert matrix_from_quaternion(camera['rotation']) == pytest.approx(rotation, abs=1e-9)
    robot = found['robot']
    assert robot['translation'] == pytest.approx([0.5, 1.5, 0.0], abs=0.01) and robot['stamp'] > 0
    walker = found['walker']['translation']
    assert walker[0] == pytest.approx(3.0, abs=0.01) and 0.9 - 0.01 <= walker[1] <= 2.1 + 0.01
    # The bodies that never move come once, on /tf_static.
    assert found['station']['translation'] == pytest.approx([3.5, 2.5, 0.0], abs=1e-9)
    assert found['crate']['translation'] == pytest.approx([1.2, 1.0, 0.0], abs=1e-9)
