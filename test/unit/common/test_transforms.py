"""Rotation matrix <-> quaternion (drvs.common.transforms): round trips, every branch, refusals."""

import doctest
import math

import numpy as np
import pytest

import drvs.common.transforms
from drvs.common.transforms import matrix_from_quaternion, quaternion_from_matrix
from drvs.vision.camera import PinholeCamera
from drvs.vision.optics import optical_pose_of


def axis_angle(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.array([*(axis * math.sin(angle / 2)), math.cos(angle / 2)])


def test_doctest():
    assert doctest.testmod(drvs.common.transforms).failed == 0


@pytest.mark.parametrize(
    'axis, angle',
    [
        ((1, 0, 0), 0.0),  # trace branch
        ((0, 0, 1), 0.3),
        ((1, 0, 0), math.pi),  # x largest: w = 0
        ((0, 1, 0), math.pi),  # y largest
        ((0, 0, 1), math.pi),  # z largest
        ((1, 1, 0), math.pi),
        ((1, -2, 3), 2.5),
        ((0.2, 0.1, -1), -1.9),
    ],
)
def test_known_rotations_give_their_quaternion(axis, angle):
    expected = axis_angle(axis, angle)
    expected = -expected if expected[3] < 0 else expected
    quaternion = quaternion_from_matrix(matrix_from_quaternion(expected))
    assert quaternion == pytest.approx(expected, abs=1e-12)
    assert quaternion[3] >= 0


def test_random_rotations_round_trip():
    rng = np.random.default_rng(7)
    for q in rng.normal(size=(500, 4)):
        rotation = matrix_from_quaternion(q)
        assert rotation @ rotation.T == pytest.approx(np.eye(3), abs=1e-12)
        back = quaternion_from_matrix(rotation)
        assert np.linalg.norm(back) == pytest.approx(1.0)
        assert matrix_from_quaternion(back) == pytest.approx(rotation, abs=1e-12)
        assert abs(np.dot(back, q / np.linalg.norm(q))) == pytest.approx(1.0)  # q or -q


def test_an_overhead_cameras_optical_frame_is_half_a_turn_about_x():
    camera = PinholeCamera(eye=(1.0, 1.5, 3.0), target=(1.0, 1.5, 0.0), fov_deg=60, width=160, height=120)
    rotation, _ = optical_pose_of(camera)
    assert quaternion_from_matrix(rotation) == pytest.approx((1.0, 0.0, 0.0, 0.0), abs=1e-12)


@pytest.mark.parametrize(
    'matrix, message',
    [
        (np.eye(2), 'rotation: expected a finite 3x3 matrix, got shape (2, 2)'),
        (np.full((3, 3), np.nan), 'rotation: expected a finite 3x3 matrix, got shape (3, 3)'),
        (2 * np.eye(3), 'rotation: not a rotation matrix (R R^T = I and det R = 1 required)'),
        (np.diag([1.0, 1.0, -1.0]), 'rotation: not a rotation matrix (R R^T = I and det R = 1 required)'),
    ],
)
def test_a_matrix_that_is_no_rotation_is_refused(matrix, message):
    with pytest.raises(ValueError) as error:
        quaternion_from_matrix(matrix)
    assert str(error.value) == message


@pytest.mark.parametrize('quaternion', [(0, 0, 0, 0), (1, 0, 0), (math.inf, 0, 0, 1)])
def test_a_quaternion_of_no_length_is_refused(quaternion):
    with pytest.raises(ValueError) as error:
        matrix_from_quaternion(quaternion)
    assert str(error.value) == (
        f'quaternion: expected 4 finite numbers (x, y, z, w) not all 0, got {quaternion!r}'
    )
