"""sim_camera: the simulated cameras on ROS topics and tf, checked against renders of the same scene.

The live tests subscribe through a grabber node (test/nodes/frame_grabber.py):
it records the topics it is given, as serialized messages, one JSON line each,
and for every image looks the image's frame up in ``map`` at the image's stamp,
as a consumer would. The test process itself never
initialises rospy (one master per test; rospy binds to one for life).
"""

from __future__ import annotations

import base64
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import roslib.message
import yaml
from geometry_msgs.msg import TransformStamped
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header

from drvs.common.transforms import matrix_from_quaternion
from drvs.ros.messages import body_poses_from_msg
from drvs.ros.params import read_params
from drvs.ros.sim_camera import (
    SimCameraNode,
    SimCameraParams,
    camera_info_message,
    compressed_message,
    image_message,
    selected_cameras,
)
from drvs.ros.tf_frames import transform_message
from drvs.sim.scene import TINY_RENDERER_SAMPLE, Scene
from drvs.sim.world_file import load_world
from drvs.testing import read_json_lines, wait_for
from drvs.vision.camera import PinholeCamera
from drvs.vision.optics import intrinsics_of, optical_pose_of

pytestmark = pytest.mark.shared_master  # see test/conftest.py

WORLD = 'test/worlds/small.yaml'
LENS_WORLD = 'test/worlds/small_lens.yaml'
DISTORTION = [-0.2, 0.05, 0.001, -0.001, 0.0]  # vs1's in LENS_WORLD
UNKNOWN_CAMERA = f"~cameras: no vision system named 'vs9' in {WORLD} (known: vs1, vs2, rover)"


def start_grabber(ros, counts, name='grabber'):
    """Start a grabber for ``counts`` ({topic: messages to record}); return its output file."""
    output = ros.root / f'{name}.jsonl'
    params = {'output': output, 'counts': json.dumps(counts)}
    ros.start_node('test/nodes/frame_grabber.py', name=name, params=params)
    return output


def received(output, topic):
    """[(message, entry)] recorded on ``topic`` so far."""
    found = []
    for entry in read_json_lines(output):
        if entry['topic'] == topic:
            message = roslib.message.get_message_class(entry['type'])()
            found.append((message.deserialize(base64.b64decode(entry['data'])), entry))
    return found


def wait_for_messages(ros, output, counts, timeout=60):
    """Wait until ``output`` holds ``counts[topic]`` messages of each topic; return them by topic."""
    wait_for(
        lambda: all(len(received(output, topic)) >= n for topic, n in counts.items()),
        timeout,
        f'messages {counts}',
        interval=0.2,
        on_timeout=ros.describe,
    )
    return {topic: received(output, topic) for topic in counts}


def start_sim_camera(ros, world, **params):
    return ros.start_node('nodes/sim_camera', name='sim_camera', params={'world': world, **params})


def stamp_of(message) -> float:
    return message.header.stamp.to_sec()


def with_stamp(found, stamp):
    """The message of ``found`` (list of (message, entry)) stamped ``stamp``."""
    (match,) = [message for message, _ in found if abs(stamp_of(message) - stamp) < 1e-6]
    return match


def pixels(image: Image) -> np.ndarray:
    assert (image.encoding, image.is_bigendian) in (('rgb8', 0), ('32FC1', 0))
    channels, dtype = (3, np.uint8) if image.encoding == 'rgb8' else (1, np.float32)
    assert image.step == image.width * channels * np.dtype(dtype).itemsize
    array = np.frombuffer(image.data, dtype).reshape(image.height, image.width, channels)
    return array[..., 0] if channels == 1 else array


def assert_pose(lookup, camera, stamp):
    rotation, translation = optical_pose_of(camera)
    assert lookup['stamp'] == pytest.approx(stamp, abs=1e-6)
    assert lookup['translation'] == pytest.approx(translation, abs=1e-6)
    assert matrix_from_quaternion(lookup['rotation']) == pytest.approx(rotation, abs=1e-6)


# -- live --------------------------------------------------------------------------------------
def test_a_static_world_looks_as_the_scene_renders_it(ros):
    world = load_world(WORLD)
    vs1, rover = world.camera('vs1'), world.camera('rover')
    sim = start_sim_camera(ros, WORLD)
    topics = {
        '/vs1/image_raw': 2,
        '/vs1/camera_info': 2,
        '/vs1/depth/image_raw': 2,
        '/vs1/image_raw/compressed': 2,
        '/rover/image_raw': 2,
    }
    output = start_grabber(ros, {**topics, '/vs2/camera_info': 1})
    found = wait_for_messages(ros, output, topics)

    camera = PinholeCamera.from_config(vs1)
    with Scene(world) as scene:
        expected = scene.render(camera)
        image, entry = found['/vs1/image_raw'][-1]
        stamp = stamp_of(image)
        assert (image.width, image.height, image.header.frame_id) == (160, 120, 'vs1_optical_frame')
        assert np.array_equal(pixels(image), expected.rgb)
        assert_pose(entry['lookup'], camera, stamp)  # from /tf_static

        depth = with_stamp(found['/vs1/depth/image_raw'], stamp)
        assert (depth.encoding, depth.header.frame_id) == ('32FC1', 'vs1_optical_frame')
        assert pixels(depth) == pytest.approx(expected.depth, abs=1e-6)

        info = with_stamp(found['/vs1/camera_info'], stamp)
        assert (info.width, info.height, info.header.frame_id) == (160, 120, 'vs1_optical_frame')
        assert (info.distortion_model, list(info.D)) == ('plumb_bob', [0.0] * 5)
        K = intrinsics_of(camera, TINY_RENDERER_SAMPLE)
        assert np.reshape(info.K, (3, 3)) == pytest.approx(K, abs=1e-9)
        assert list(info.R) == np.eye(3).flatten().tolist()
        assert np.reshape(info.P, (3, 4)) == pytest.approx(np.hstack([K, np.zeros((3, 1))]), abs=1e-9)

        compressed = with_stamp(found['/vs1/image_raw/compressed'], stamp)
        assert compressed.format == 'rgb8; jpeg compressed bgr8'
        decoded = cv2.cvtColor(cv2.imdecode(np.frombuffer(compressed.data, np.uint8), 1), cv2.COLOR_BGR2RGB)
        assert decoded.shape == (120, 160, 3)
        assert np.mean(np.abs(decoded.astype(int) - expected.rgb)) < 3  # quality 90

        # The rover's mount moves: its tf on /tf, with each image's stamp, and the image is the
        # view from where that tf puts it.
        base = PinholeCamera.from_config(rover)
        for image, entry in found['/rover/image_raw']:
            assert 'lookup' in entry, entry.get('lookup_error')
            x, y, z = entry['lookup']['translation']
            assert 1.0 <= x <= 3.0 and (y, z) == pytest.approx((1.5, 2.0), abs=1e-9)
            moved = base.moved_to(x, y)
            assert_pose(entry['lookup'], moved, stamp_of(image))
            assert np.array_equal(pixels(image), scene.render(moved).rgb)

    assert received(output, '/vs2/camera_info') == []  # nobody watches vs2: not rendered
    assert sim.interrupt() == 0, sim.describe()


def test_frames_are_stamped_with_the_poses_they_show(ros):
    world = load_world(WORLD)
    ros.start_node('nodes/world_sim', name='world_sim', params={'world': WORLD})
    start_sim_camera(ros, WORLD, cameras='vs2,rover', depth=False, rate=5)
    counts = {'/vs2/image_raw': 3, '/rover/image_raw': 3, '/world_sim/poses': 90}
    found = wait_for_messages(ros, start_grabber(ros, counts), counts)

    published = [topic for topic, nodes in ros.master.system_state()[0] if '/sim_camera' in nodes]
    assert '/vs2/image_raw' in published and '/vs2/depth/image_raw' not in published  # ~depth false
    poses = dict(body_poses_from_msg(m) for m, _ in found['/world_sim/poses'])
    vs2 = PinholeCamera.from_config(world.camera('vs2'))
    rover = PinholeCamera.from_config(world.camera('rover'))
    with Scene(world) as scene:
        for topic in ('/vs2/image_raw', '/rover/image_raw'):
            image, entry = found[topic][-1]
            stamp = stamp_of(image)
            (shown,) = [poses[s] for s in poses if abs(s - stamp) < 1e-6]  # a published poses stamp
            scene.apply_poses(shown)
            camera = vs2
            if topic == '/rover/image_raw':
                assert 'lookup' in entry, entry.get('lookup_error')
                camera = rover.moved_to(*entry['lookup']['translation'][:2])
            assert_pose(entry['lookup'], camera, stamp)
            assert np.array_equal(pixels(image), scene.render(camera).rgb)


def test_a_lens_distorts_the_published_frames_and_its_coefficients_are_in_camera_info(ros):
    from drvs.sim.lens import Lens

    world = load_world(LENS_WORLD)
    start_sim_camera(ros, LENS_WORLD, cameras=['vs1'], compression='png')
    counts = {
        '/vs1/image_raw': 1,
        '/vs1/camera_info': 2,
        '/vs1/depth/image_raw': 2,
        '/vs1/image_raw/compressed': 2,
    }
    found = wait_for_messages(ros, start_grabber(ros, counts), counts)

    lens = Lens(PinholeCamera.from_config(world.camera('vs1')), tuple(DISTORTION), TINY_RENDERER_SAMPLE)
    with Scene(world) as scene:
        expected = lens.apply(scene.render(lens.canvas))
    image, entry = found['/vs1/image_raw'][0]
    stamp = stamp_of(image)
    assert (image.width, image.height) == (160, 120)
    assert np.array_equal(pixels(image), expected.rgb)
    assert_pose(entry['lookup'], PinholeCamera.from_config(world.camera('vs1')), stamp)

    info = with_stamp(found['/vs1/camera_info'], stamp)
    assert list(info.D) == pytest.approx(DISTORTION, abs=1e-12)
    assert np.reshape(info.K, (3, 3)) == pytest.approx(np.asarray(lens.model.K), abs=1e-9)
    assert (info.width, info.height, info.header.frame_id) == (160, 120, 'vs1_optical_frame')

    depth = pixels(with_stamp(found['/vs1/depth/image_raw'], stamp))
    assert np.allclose(depth, expected.depth, atol=1e-6, equal_nan=True)

    compressed = with_stamp(found['/vs1/image_raw/compressed'], stamp)
    assert compressed.format == 'rgb8; png compressed bgr8'
    decoded = cv2.imdecode(np.frombuffer(compressed.data, np.uint8), cv2.IMREAD_COLOR)
    assert np.array_equal(cv2.cvtColor(decoded, cv2.COLOR_BGR2RGB), expected.rgb)  # lossless


def test_bad_parameters_exit_2_naming_the_parameter(ros):
    refused = {
        'bad_rate': ({'rate': -1}, '~rate: must be positive, got -1.0'),
        'bad_camera': ({'cameras': 'vs1,vs9'}, UNKNOWN_CAMERA),
    }
    nodes = {
        name: ros.start_node('nodes/sim_camera', name=name, params={'world': WORLD, **params})
        for name, (params, _) in refused.items()
    }
    for name, node in nodes.items():
        wait_for(lambda node=node: not node.running(), 60, f'{name} to exit', on_timeout=node.describe)
        assert node.process.returncode == 2, node.describe()
        assert '[FATAL] ' in node.log() and refused[name][1] in node.log(), node.describe()


# -- pure --------------------------------------------------------------------------------------
def serialize_deserialize(message):
    from io import BytesIO

    buffer = BytesIO()
    message.serialize(buffer)
    return type(message)().deserialize(buffer.getvalue())


def test_images_round_trip_through_their_messages():
    header = Header(frame_id='vs1_optical_frame')
    noise = np.random.default_rng(1).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    depth = np.linspace(0.5, 3.0, 35, dtype=np.float32).reshape(5, 7)
    assert np.array_equal(pixels(serialize_deserialize(image_message(noise, 'rgb8', header))), noise)
    assert np.array_equal(pixels(serialize_deserialize(image_message(depth, '32FC1', header))), depth)
    rgb = np.full((16, 24, 3), (255, 255, 255), np.uint8)  # flat colours, as the scene's
    rgb[:, 8:16] = (220, 0, 0)
    for compression, tolerance in (('png', 0), ('jpeg', 4)):  # mean error; JPEG blurs colour edges
        message = serialize_deserialize(compressed_message(rgb, header, compression, 95))
        assert isinstance(message, CompressedImage) and message.header.frame_id == 'vs1_optical_frame'
        assert message.format == f'rgb8; {compression} compressed bgr8'
        decoded = cv2.cvtColor(cv2.imdecode(np.frombuffer(message.data, np.uint8), 1), cv2.COLOR_BGR2RGB)
        assert np.mean(np.abs(decoded.astype(int) - rgb)) <= tolerance


def test_camera_info_and_transform_round_trip():
    K = np.array([[100.0, 0, 79.5], [0, 100.0, 59.5], [0, 0, 1]])
    info = serialize_deserialize(camera_info_message(K, DISTORTION, 160, 120, Header(frame_id='f')))
    assert isinstance(info, CameraInfo)
    assert list(info.D) == DISTORTION and list(info.K) == K.flatten().tolist()
    assert list(info.P) == [100.0, 0, 79.5, 0, 0, 100.0, 59.5, 0, 0, 0, 1, 0]
    camera = PinholeCamera(eye=(1.0, 2.0, 3.0), target=(1.5, 2.5, 0.0), fov_deg=50, width=64, height=48)
    rotation, translation = optical_pose_of(camera)
    message = serialize_deserialize(transform_message(rotation, translation, 'map', 'c', Header().stamp))
    assert isinstance(message, TransformStamped)
    assert (message.header.frame_id, message.child_frame_id) == ('map', 'c')
    q = message.transform.rotation
    assert matrix_from_quaternion((q.x, q.y, q.z, q.w)) == pytest.approx(rotation, abs=1e-12)


def params_from(**given):
    return read_params(SimCameraParams, get=lambda name, default: given.get(name.lstrip('~'), default))


@pytest.mark.parametrize(
    'cameras, names',
    [(None, ('vs1', 'vs2', 'rover')), ('rover, vs1', ('rover', 'vs1')), (['vs2', 'vs2'], ('vs2',))],
)
def test_cameras_are_a_comma_separated_string_or_a_list(cameras, names):
    params = params_from(world=WORLD) if cameras is None else params_from(world=WORLD, cameras=cameras)
    assert tuple(c.name for c in selected_cameras(load_world(WORLD), params.camera_names)) == names


@pytest.mark.parametrize(
    'given, message',
    [
        ({'rate': -1}, '~rate: must be positive, got -1.0'),
        ({'rate': 'fast'}, "~rate: expected a number, got 'fast'"),
        ({'jpeg_quality': 0}, '~jpeg_quality: must be 1 to 100, got 0'),
        ({'jpeg_quality': 101}, '~jpeg_quality: must be 1 to 100, got 101'),
        ({'compression': 'bmp'}, "~compression: must be one of jpeg, png, got 'bmp'"),
        ({'depth': 'yes'}, "~depth: expected true or false, got 'yes'"),
        (
            {'cameras': 'vs1,vs9'},
            f"~cameras: no vision system named 'vs9' in {WORLD} (known: vs1, vs2, rover)",
        ),
        ({'cameras': [1, 2]}, '~cameras: expected a string or a list of strings, got [1, 2]'),
        ({'world': None}, '~world: required, not given (add _world:=VALUE to the command line)'),
        (
            {'world': 'test/worlds/none.yaml'},
            'test/worlds/none.yaml: cannot read the world file: No such file or directory',
        ),
    ],
)
def test_bad_values_are_refused_naming_the_parameter(given, message):
    given = {'world': WORLD, **given}
    if given['world'] is None:
        del given['world']
    with pytest.raises(ValueError) as error:
        SimCameraNode(params_from(**given))  # the constructor loads the world and its lenses only
    assert str(error.value) == message


def test_a_lens_that_folds_over_is_refused_naming_the_camera(tmp_path):
    data = yaml.safe_load(Path(LENS_WORLD).read_text())
    data['vision_systems'][0]['distortion'] = [-1.0, 0.0, 0.0, 0.0, 0.0]  # r(1 - r^2) turns at r = 0.58
    path = tmp_path / 'folding.yaml'
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError) as error:
        SimCameraNode(params_from(world=str(path)))
    prefix = f'{path}: vision_systems vs1: Lens: distortion [-1.0, 0.0, 0.0, 0.0, 0.0] cannot be undone'
    assert str(error.value).startswith(prefix)  # the rest is drvs.sim.lens's
