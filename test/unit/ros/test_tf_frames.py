"""drvs.ros.tf_frames: a camera's optical frame and a body on the floor as tf transforms (no master)."""

import math

import pytest
import rospy
from geometry_msgs.msg import TransformStamped

from drvs.common.transforms import matrix_from_quaternion
from drvs.ros.tf_frames import body_transform, camera_transform, optical_frame
from drvs.testing.messages import round_trip
from drvs.vision.camera import PinholeCamera
from drvs.vision.optics import optical_pose_of


def rotation_of(message: TransformStamped):
    q = message.transform.rotation
    return matrix_from_quaternion((q.x, q.y, q.z, q.w))


def test_a_cameras_optical_frame_in_map():
    camera = PinholeCamera(eye=(1.0, 2.0, 3.0), target=(1.5, 2.5, 0.0), fov_deg=50, width=64, height=48)
    message = round_trip(camera_transform(camera, optical_frame('vs1'), rospy.Time(7, 5)))
    rotation, translation = optical_pose_of(camera)
    assert (message.header.frame_id, message.child_frame_id) == ('map', 'vs1_optical_frame')
    assert message.header.stamp == rospy.Time(7, 5)
    t = message.transform.translation
    assert (t.x, t.y, t.z) == pytest.approx(tuple(translation), abs=1e-12)
    assert rotation_of(message) == pytest.approx(rotation, abs=1e-12)


@pytest.mark.parametrize('yaw', [0.0, math.pi / 2, -2.5, math.pi])
def test_a_body_stands_on_the_floor_facing_its_yaw(yaw):
    message = round_trip(body_transform('robot', (0.5, 1.5, yaw), rospy.Time(3)))
    assert (message.header.frame_id, message.child_frame_id) == ('map', 'robot')
    t = message.transform.translation
    assert (t.x, t.y, t.z) == (0.5, 1.5, 0.0)
    x_axis = rotation_of(message)[:, 0]
    assert x_axis == pytest.approx([math.cos(yaw), math.sin(yaw), 0.0], abs=1e-12)
