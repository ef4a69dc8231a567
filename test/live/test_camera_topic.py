"""A vision system fed by a camera topic (``_source:=topic``): the test plays the camera driver.

test/nodes/synthetic_camera.py draws, with OpenCV alone, what a camera at a known
pose sees of a box on the floor, and publishes it with its CameraInfo and a
static transform. The vision system must put the box's outline back where it is.
"""

import shlex

import numpy as np
import pytest
from shapely.geometry import Polygon

from drvs.common.status import INVALID, UNAVAILABLE, UNSUPPORTED
from drvs.testing import read_json_lines, wait_for
from drvs.testing.detect import detect
from drvs.vision.camera import PinholeCamera
from drvs.vision.optics import OPENCV_OFFSET, CameraModel, optical_pose_of

pytestmark = pytest.mark.shared_master  # see test/conftest.py

CALLBACK = '/robot/callback_coordinates'
BOX = [[1.6, 1.2], [2.4, 1.3], [2.35, 1.8], [1.55, 1.7]]  # a quadrilateral, turned
BLUE = 'colour:0,0,150,80,80,255'
DARK = 'colour:0,0,0,80,80,80'  # finds the blue box in a grey (mono8) picture too
CAMERA = {
    'eye': [2.0, 1.5, 3.0],
    'target': [2.3, 1.9, 0.0],  # tilted: not straight down
    'width': 640,
    'height': 480,
    'fx': 520.0,
    'fy': 515.0,
    'cx': 322.0,
    'cy': 236.5,
    'distortion': [-0.18, 0.04, 0.0008, -0.0006, 0.0],
    'box': BOX,
    'box_colour': [0, 0, 220],
    'frame_id': 'cam1_optical_frame',
}
TOPICS = {'image': '/synthetic_camera/image_raw', 'camera_info': '/synthetic_camera/camera_info'}
PAUSE = ['rostopic', 'pub', '/synthetic_camera/pause', 'std_msgs/Bool']


def ask(service, algorithm, request_id, region=(0.0, 0.0, 4.0, 3.0)):
    return detect(service, algorithm, region, request_id)


def start(ros, camera=None, vision=None, remap=None):
    """The server, the test's camera, a topic-fed vision system cam1 and a callback recorder."""
    server = ros.start_node('nodes/drvs_server', name='drvs', params={'lease': 2.0})
    output = ros.root / 'callbacks.jsonl'
    recorder = ros.start_node('test/nodes/callback_recorder.py', name='recorder', params={'output': output})
    ros.wait_for_service('/drvs/detect_object_boundary', node=server)
    stamps = ros.root / 'stamps.txt'
    ros.start_node(
        'test/nodes/synthetic_camera.py',
        name='synthetic_camera',
        params={**CAMERA, 'stamps': stamps, **(camera or {})},
    )
    cam1 = ros.start_node(
        'nodes/vision_system',
        name='cam1',
        params={'source': 'topic', **(vision or {})},
        remap=remap or TOPICS,
        env=without_pybullet(ros),
    )
    ros.wait_for_service(CALLBACK, node=recorder)
    wait_for(lambda: registered(), 30, 'cam1 to register its field of view', on_timeout=ros.describe)
    return cam1, output, stamps


def without_pybullet(ros) -> dict:
    """An environment in which ``import pybullet`` fails: a camera on a topic must not need it."""
    blocker = ros.root / 'no_pybullet'
    blocker.mkdir(exist_ok=True)
    (blocker / 'pybullet.py').write_text("raise ImportError('pybullet: only the simulation may import it')\n")
    return {'PYTHONPATH': f'{blocker}:{ros.env["PYTHONPATH"]}'}


def registered() -> bool:
    return ask('/drvs/detect_object_boundary', BLUE, 'probe', (2.0, 1.5, 2.01, 1.51)).vision_systems == 1


def outline_of(output, request_id, ros):
    callbacks = wait_for(
        lambda: [c for c in read_json_lines(output) if c['request_id'] == request_id],
        30,
        f'a callback for {request_id}',
        on_timeout=ros.describe,
    )
    (callback,) = callbacks
    assert callback['vision_system'] == '/cam1/detect_object_boundary'
    (outline,) = callback['objects']
    return Polygon(outline), callback


def test_a_box_drawn_by_a_distorted_camera_is_reported_where_it_lies(graph):
    ros = graph
    cam1, output, stamps = start(ros)
    reply = ask('/drvs/detect_object_boundary', BLUE, 'box')
    assert (reply.accepted, reply.vision_systems) == (True, 1)
    outline, callback = outline_of(output, 'box', ros)
    truth = Polygon(BOX)
    assert outline.exterior.is_ccw
    assert outline.hausdorff_distance(truth) <= 0.02
    published = {round(float(line), 6) for line in stamps.read_text().split()}
    assert round(callback['stamp'], 6) in published  # the image's own stamp, not the time of the request

    # The registered field of view is the image's footprint: it holds the box, and ends
    # at the horizon side of a tilted camera rather than at infinity.
    assert ask('/drvs/detect_object_boundary', BLUE, 'far', (30.0, 30.0, 31.0, 31.0)).vision_systems == 0


@pytest.mark.parametrize(
    ('camera', 'vision', 'remap', 'algorithm'),
    [
        ({'encoding': 'bgr8'}, {}, TOPICS, BLUE),
        ({'encoding': 'mono8'}, {}, TOPICS, DARK),
        ({'encoding': 'bayer_rggb8'}, {}, TOPICS, BLUE),
        (
            {'compressed': True},
            {'compressed': True},
            {'image': '/synthetic_camera/image_raw', 'camera_info': '/synthetic_camera/camera_info'},
            BLUE,
        ),
    ],
    ids=['bgr8', 'mono8', 'bayer_rggb8', 'compressed'],
)
def test_every_image_encoding_gives_the_same_outline(graph, camera, vision, remap, algorithm):
    ros = graph
    start(ros, camera=camera, vision=vision, remap=remap)
    ask('/drvs/detect_object_boundary', algorithm, 'box')
    outline, _ = outline_of(output=ros.root / 'callbacks.jsonl', request_id='box', ros=ros)
    assert outline.hausdorff_distance(Polygon(BOX)) <= 0.02


@pytest.mark.parametrize('depth_encoding', ['32FC1', '16UC1'])
def test_a_tall_box_is_reported_where_it_stands_with_depth_and_displaced_without(graph, depth_encoding):
    ros = graph
    camera = {
        'box_height': 0.8,
        'distortion': [0.0] * 5,
        'publish_depth': True,
        'depth_encoding': depth_encoding,
    }
    remap = {**TOPICS, 'depth': '/synthetic_camera/depth'}
    start(ros, camera=camera, vision={'depth': True}, remap=remap)
    ask('/drvs/detect_object_boundary', BLUE, 'tall')
    outline, _ = outline_of(ros.root / 'callbacks.jsonl', 'tall', ros)
    assert outline.hausdorff_distance(Polygon(BOX)) <= 0.02

    # The same picture without depth: the top face is met with the floor plane, so the
    # outline is the box's top seen from 3 m, stretched away from the camera by h / (H - h).
    flat = ros.start_node('nodes/vision_system', name='flat', params={'source': 'topic'}, remap=TOPICS)
    ros.wait_for_service('/flat/detect_object_boundary', node=flat)
    wait_for(lambda: ask('/flat/detect_object_boundary', BLUE, 'flat').accepted, 30, 'flat to get frames')
    flat_outline = wait_for(
        lambda: [c for c in read_json_lines(ros.root / 'callbacks.jsonl') if c['request_id'] == 'flat'],
        30,
        'a callback from flat',
    )[0]['objects'][0]
    displaced = Polygon(flat_outline)
    assert displaced.hausdorff_distance(Polygon(BOX)) > 0.1
    assert displaced.area > Polygon(BOX).area  # the top is nearer the camera: it looks larger


def test_elevation_runs_on_a_depth_topic_and_only_there(graph):
    """A camera with depth (16UC1 millimetres) registers elevation and reports the box where it
    stands with its height; a camera without depth does not register it, and says why not."""
    ros = graph
    camera = {'box_height': 0.8, 'distortion': [0.0] * 5, 'publish_depth': True, 'depth_encoding': '16UC1'}
    remap = {**TOPICS, 'depth': '/synthetic_camera/depth'}
    start(ros, camera=camera, vision={'depth': True}, remap=remap)
    reply = ask('/drvs/detect_object_boundary', 'elevation:0.1', 'standing')
    assert (reply.accepted, reply.vision_systems) == (True, 1)
    outline, callback = outline_of(ros.root / 'callbacks.jsonl', 'standing', ros)
    assert outline.hausdorff_distance(Polygon(BOX)) <= 0.03
    assert callback['heights'] == [pytest.approx(0.8, abs=0.01)]

    flat = ros.start_node('nodes/vision_system', name='flat', params={'source': 'topic'}, remap=TOPICS)
    ros.wait_for_service('/flat/detect_object_boundary', node=flat)
    reply = ask('/flat/detect_object_boundary', 'elevation', 'no depth')
    assert (reply.accepted, reply.status) == (False, INVALID)
    assert reply.message.startswith(
        "algorithm: unknown NAME 'elevation'; known: apriltag, colour, foreground,"
    )


def test_a_depth_image_of_another_size_refuses_elevation_saying_so_and_colour_goes_on(graph):
    ros = graph
    camera = {'box_height': 0.8, 'distortion': [0.0] * 5, 'publish_depth': True, 'depth_size': [320, 240]}
    start(ros, camera=camera, vision={'depth': True}, remap={**TOPICS, 'depth': '/synthetic_camera/depth'})
    reply = ask('/cam1/detect_object_boundary', 'elevation', 'misfit')
    assert (reply.accepted, reply.status) == (False, UNAVAILABLE)
    assert reply.message == (
        'elevation: /synthetic_camera/depth: depth image is 320x240, '
        'not registered to the 640x480 colour image'
    )
    ask('/cam1/detect_object_boundary', BLUE, 'colour')
    outline, _ = outline_of(ros.root / 'callbacks.jsonl', 'colour', ros)
    assert outline.intersects(Polygon(BOX))  # without depth the top is met with the floor: displaced


def test_foreground_finds_the_box_against_a_reference_file_of_the_empty_floor(graph):
    """A camera without depth: ``~reference`` (as drvs_calibrate --reference writes it) is the empty
    floor; the flat box below the camera is where it lies, and elevation is not offered."""
    import cv2

    ros = graph
    reference = ros.root / 'cam1_floor.png'
    cv2.imwrite(str(reference), np.full((480, 640, 3), 230, np.uint8))  # the synthetic camera's floor
    start(ros, camera={'distortion': [0.0] * 5}, vision={'reference': reference})
    reply = ask('/drvs/detect_object_boundary', 'foreground', 'anything')
    assert (reply.accepted, reply.vision_systems) == (True, 1)
    outline, _ = outline_of(ros.root / 'callbacks.jsonl', 'anything', ros)
    assert outline.hausdorff_distance(Polygon(BOX)) <= 0.03
    reply = ask('/drvs/detect_object_boundary', 'elevation', 'standing')
    assert (reply.accepted, reply.status) == (False, UNSUPPORTED)


def test_foreground_without_a_reference_learns_one_while_asked_and_says_so_meanwhile(graph):
    ros = graph
    start(ros)
    reply = ask('/cam1/detect_object_boundary', 'foreground', 'early')
    assert (reply.accepted, reply.status) == (False, UNAVAILABLE)
    assert reply.message.startswith('foreground: learning the reference of the empty floor ('), reply.message
    # Asked again, it learns from the stream (~motion_rate 5 Hz, 5 frames), then serves.
    wait_for(
        lambda: ask('/cam1/detect_object_boundary', 'foreground', 'later').accepted,
        30,
        'foreground to learn its reference',
        on_timeout=ros.describe,
    )


def test_a_foreground_watch_refused_while_learning_starts_the_learning_too(graph):
    """The robot asks for obstacles with a watch: its refusal must feed the stream as a request's does."""
    from drvs.ros.service_client import ServiceClient
    from drvs.srv import WatchObjectBoundary, WatchObjectBoundaryRequest

    def watch():
        message = WatchObjectBoundaryRequest(
            algorithm='foreground', callback_service=CALLBACK, request_id='/robot/obstacle', period=0.5
        )
        message.duration = 10.0
        r = message.region_of_interest
        r.min_x, r.min_y, r.max_x, r.max_y = 0.0, 0.0, 4.0, 3.0
        client = ServiceClient('/cam1/watch_object_boundary', WatchObjectBoundary, 10.0)
        try:
            return client.call(message)
        finally:
            client.close()

    ros = graph
    start(ros)
    reply = watch()
    assert (reply.accepted, reply.status) == (False, UNAVAILABLE)
    assert reply.message.startswith('foreground: learning the reference of the empty floor ('), reply.message
    wait_for(lambda: watch().accepted, 30, 'foreground to learn its reference', on_timeout=ros.describe)


def test_a_dead_feed_unregisters_and_registers_again_when_frames_return(graph):
    ros = graph
    cam1, output, _ = start(ros, vision={'stale_after': 1.0})
    paused = ros.spawn('pause', [*PAUSE, 'true'])  # latched until stopped (-1 would wait 3 s)
    wait_for(lambda: not registered(), 30, 'cam1 to unregister', on_timeout=ros.describe)
    # cam1 logs it once the server's answer is in, after the server stopped routing to it
    wait_for(lambda: 'unregistered /cam1/detect_object_boundary' in cam1.log(), 10, 'cam1 to say so')
    reply = ask('/cam1/detect_object_boundary', BLUE, 'stale')
    assert reply.status == UNAVAILABLE
    assert reply.message.startswith('/synthetic_camera/image_raw: no frame for ')

    paused.stop()
    ros.spawn('resume', [*PAUSE, 'false'])
    wait_for(registered, 30, 'cam1 to register again', on_timeout=ros.describe)
    ask('/drvs/detect_object_boundary', BLUE, 'back')
    outline, _ = outline_of(output, 'back', ros)
    assert outline.hausdorff_distance(Polygon(BOX)) <= 0.02


def test_a_topic_vision_system_without_a_pose_on_tf_says_what_is_missing(graph):
    ros = graph
    server = ros.start_node('nodes/drvs_server', name='drvs')
    ros.wait_for_service('/drvs/detect_object_boundary', node=server)
    ros.start_node(
        'test/nodes/synthetic_camera.py', name='synthetic_camera', params={**CAMERA, 'frame_id': 'nowhere'}
    )
    # cam1 looks for a frame nobody publishes on tf: it must neither register nor crash.
    cam1 = ros.start_node(
        'nodes/vision_system', name='cam1', params={'source': 'topic', 'map_frame': 'world'}, remap=TOPICS
    )
    wait_for(
        lambda: 'not registering yet: no transform world <- nowhere' in cam1.log(),
        30,
        'cam1 to explain why it does not register',
        on_timeout=cam1.describe,
    )
    assert cam1.running() and not registered()
    reply = ask('/cam1/detect_object_boundary', BLUE, 'lost')  # asked directly: refused, saying why
    assert (reply.accepted, reply.status) == (False, UNAVAILABLE)
    assert reply.message.startswith('no calibrated pose: no transform world <- nowhere at '), reply.message


def test_source_render_without_a_world_is_refused_with_the_fix(ros):
    node = ros.start_node('nodes/vision_system', name='cam1', params={'source': 'render'})
    wait_for(lambda: not node.running(), 30, 'cam1 to exit')
    assert node.process.returncode == 2
    assert '~world: required with ~source render (or use ~source topic and a camera topic)' in node.log()


def test_a_camera_calibrated_with_drvs_calibrate_and_a_static_transform_reports_the_truth(graph):
    """docs/tutorials/your-camera.md, with the test as the camera: no pose on tf until the
    user calibrates one from floor points and publishes it with the printed command."""
    ros = graph
    rotation, eye = optical_pose_of(
        PinholeCamera(
            eye=tuple(CAMERA['eye']), target=tuple(CAMERA['target']), fov_deg=60, width=640, height=480
        )
    )
    K = [[CAMERA['fx'], 0, CAMERA['cx']], [0, CAMERA['fy'], CAMERA['cy']], [0, 0, 1]]
    camera = CameraModel(
        K=np.array(K),
        D=tuple(CAMERA['distortion']),
        width=640,
        height=480,
        rotation=rotation,
        translation=eye,
    )
    floor = [(1.4, 1.5), (2.6, 1.6), (2.7, 2.5), (1.5, 2.6), (2.1, 2.0), (2.3, 1.4)]
    pixels = camera.project_3d_to_pixel([(x, y, 0.0) for x, y in floor]) - OPENCV_OFFSET
    assert np.all((pixels >= 0) & (pixels <= [639, 479]))  # every point in the picture

    server = ros.start_node('nodes/drvs_server', name='drvs', params={'lease': 2.0})
    ros.wait_for_service('/drvs/detect_object_boundary', node=server)
    ros.start_node(
        'test/nodes/synthetic_camera.py', name='synthetic_camera', params={**CAMERA, 'publish_tf': False}
    )
    points = [f'--point={u:.4f},{v:.4f}:{x},{y}' for (u, v), (x, y) in zip(pixels, floor, strict=True)]
    result = ros.run(
        shlex.join(['.venv/bin/python', 'nodes/drvs_calibrate', '--topic', TOPICS['image'], *points])
    )
    assert result.returncode == 0, result.stderr
    (command,) = [line for line in result.stdout.splitlines() if line.startswith('/usr/lib/tf2_ros/')]
    assert command.endswith(' map cam1_optical_frame')  # the frame of the image's header
    ros.spawn('static_transform_publisher', shlex.split(command))

    output = ros.root / 'callbacks.jsonl'
    ros.start_node('nodes/vision_system', name='cam1', params={'source': 'topic'}, remap=TOPICS)
    recorder = ros.start_node('test/nodes/callback_recorder.py', name='recorder', params={'output': output})
    ros.wait_for_service(CALLBACK, node=recorder)
    wait_for(registered, 30, 'cam1 to register once the pose is on tf', on_timeout=ros.describe)
    ask('/drvs/detect_object_boundary', BLUE, 'calibrated')
    outline, _ = outline_of(output, 'calibrated', ros)
    assert outline.hausdorff_distance(Polygon(BOX)) <= 0.02
