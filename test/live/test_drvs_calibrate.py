"""drvs_calibrate from a running graph: the image and its intrinsics taken from topics.

The image files, the refusals and the solving are tested without a master in
test/unit/vision/test_calibration.py, on the same rendered scene (drvs.testing.tags).
"""

import json
import sys

import cv2
import numpy as np
import pytest

from drvs.sim.scene import TINY_RENDERER_SAMPLE
from drvs.testing import RosHarness
from drvs.testing.tags import (
    ANGLE_TOLERANCE,
    CAMERAS,
    POSITION_TOLERANCE,
    TAGS,
    pose_errors,
    render_floor_tags,
    tag_args,
    write_camera_info,
)
from drvs.vision.optics import intrinsics_of

pytestmark = pytest.mark.shared_master  # see test/conftest.py

CAMERA = CAMERAS['from_the_north_east']


@pytest.fixture(scope='module')
def view(tmp_path_factory):
    """The camera's rendered view of the tags, saved as PNG (BGR on disk, as cv2.imwrite writes)."""
    folder = tmp_path_factory.mktemp('view')
    rgb = render_floor_tags(CAMERA, TAGS, folder / 'textures')
    path = folder / 'from_the_north_east.png'
    cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return path


def test_calibrates_from_a_camera_topic_and_its_camera_info(ros: RosHarness, view):
    K = intrinsics_of(CAMERA, TINY_RENDERER_SAMPLE)
    info = write_camera_info(ros.root / 'cam1.yaml', K)
    params = {'image': view, 'camera_info': info, 'frame_id': 'cam1_optical'}
    driver = ros.start_node('test/nodes/still_camera.py', name='cam1', params=params)
    output = ros.root / 'pose.json'
    result = ros.run(
        f'{sys.executable} nodes/drvs_calibrate --topic /cam1/image_raw {" ".join(tag_args(TAGS))} '
        f'--timeout 30 --json {output}',
        timeout=60,
    )
    assert (result.returncode, result.stderr) == (0, ''), result.stderr + ros.describe()
    assert driver.running()
    pose = json.loads(output.read_text())
    assert pose['frame'] == 'cam1_optical'  # the image's frame_id
    assert pose['command'].endswith(' map cam1_optical')
    assert np.asarray(pose['intrinsics']['K']) == pytest.approx(K)  # from /cam1/camera_info
    position_error, angle_error = pose_errors(CAMERA, pose['rotation'], pose['position'])
    assert position_error <= POSITION_TOLERANCE and angle_error <= ANGLE_TOLERANCE

    # An image file with the intrinsics (and the frame) of a CameraInfo topic.
    result = ros.run(
        f'{sys.executable} nodes/drvs_calibrate --image {view} '
        f'--camera-info /cam1/camera_info {" ".join(tag_args(TAGS))} --timeout 30 --json {output}',
        timeout=60,
    )
    assert (result.returncode, result.stderr) == (0, ''), result.stderr + ros.describe()
    again = json.loads(output.read_text())
    assert again['frame'] == 'cam1_optical'
    assert again['position'] == pytest.approx(pose['position'], abs=1e-9)


def test_a_topic_nobody_publishes_times_out_with_a_clear_message(ros: RosHarness):
    result = ros.run(f'{sys.executable} nodes/drvs_calibrate --topic /cam9/image_raw --tag 0:1,1 --timeout 1')
    assert (result.returncode, result.stdout) == (2, '')
    assert result.stderr == (
        'drvs_calibrate: error: no sensor_msgs/Image on /cam9/image_raw within 1 s (no publisher; '
        'sensor_msgs/Image topics: none): is the camera running? (rostopic hz /cam9/image_raw)\n'
    )
