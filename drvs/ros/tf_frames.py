"""Poses as tf transforms: a camera's optical frame and a body on the floor, in ``map``.

Shared by the nodes that put the simulation on tf: sim_camera and a vision system in
render mode (``map`` -> ``<camera>_optical_frame``, :func:`camera_transform`) and
world_sim (``map`` -> ``<body name>``, :func:`body_transform`). The optical frame
follows REP-103 (z forward, x right, y down; :func:`drvs.vision.optics.optical_pose_of`);
a body's frame stands on the floor at its centre, x along its heading.
"""

from __future__ import annotations

import math

import rospy
from geometry_msgs.msg import TransformStamped

from drvs.common.transforms import quaternion_from_matrix
from drvs.vision.camera import PinholeCamera
from drvs.vision.optics import optical_pose_of

__all__ = ['MAP_FRAME', 'body_transform', 'camera_transform', 'optical_frame', 'transform_message']

MAP_FRAME = 'map'


def optical_frame(camera_name: str) -> str:
    """The tf frame of a camera's images: ``vs1`` -> ``vs1_optical_frame``."""
    return f'{camera_name}_optical_frame'


def transform_message(rotation, translation, parent: str, child: str, stamp: rospy.Time) -> TransformStamped:
    """``child``'s pose in ``parent`` (rotation: 3x3, columns are child's axes in parent)."""
    message = TransformStamped()
    message.header.stamp = stamp
    message.header.frame_id = parent
    message.child_frame_id = child
    t = message.transform.translation
    t.x, t.y, t.z = (float(v) for v in translation)
    q = message.transform.rotation
    q.x, q.y, q.z, q.w = (float(v) for v in quaternion_from_matrix(rotation))
    return message


def camera_transform(camera: PinholeCamera, frame: str, stamp: rospy.Time) -> TransformStamped:
    """``map`` -> ``frame``: the optical frame of ``camera`` where it is."""
    rotation, translation = optical_pose_of(camera)
    return transform_message(rotation, translation, MAP_FRAME, frame, stamp)


def body_transform(name: str, pose, stamp: rospy.Time) -> TransformStamped:
    """``map`` -> ``name``: a body at ``pose`` (x, y, yaw) on the floor (z = 0)."""
    x, y, yaw = (float(v) for v in pose)
    message = TransformStamped()
    message.header.stamp = stamp
    message.header.frame_id = MAP_FRAME
    message.child_frame_id = name
    message.transform.translation.x, message.transform.translation.y = x, y
    message.transform.rotation.z, message.transform.rotation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    return message
