"""The pinhole camera model: round trips world point -> pixel -> world, PyBullet's matrices, footprints."""

import math

import numpy as np
import pybullet
import pytest
from shapely.geometry import Polygon

from drvs.vision.camera import PinholeCamera

CAMERAS = {
    'overhead': PinholeCamera(eye=(2.0, 1.5, 3.0), target=(2.0, 1.5, 0.0), fov_deg=60, width=800, height=600),
    'tilted': PinholeCamera(eye=(0.5, 0.5, 2.5), target=(2.0, 2.0, 0.0), fov_deg=45, width=640, height=480),
    'rotated_up': PinholeCamera(
        eye=(1.0, 1.0, 4.0), target=(1.2, 0.9, 0.0), fov_deg=70, width=320, height=240, up=(1.0, 1.0, 0.0)
    ),
}
POINTS = [(2.0, 1.5, 0.0), (2.4, 1.1, 0.5), (1.3, 2.2, 0.0), (1.9, 1.7, 1.2)]


@pytest.mark.parametrize('name', CAMERAS)
def test_world_point_to_pixel_and_back(name):
    camera = CAMERAS[name]
    right, up, forward = camera.axes()
    for point in POINTS:
        pixel = camera.project_3d_to_pixel(point)
        depth = np.dot(np.subtract(point, camera.eye), forward)
        assert camera.pixel_to_point(pixel, depth) == pytest.approx(point, abs=1e-9)
        ray = camera.project_pixel_to_3d_ray(pixel)
        assert np.linalg.norm(ray) == pytest.approx(1.0)
        to_point = np.subtract(point, camera.eye)
        assert np.cross(ray, to_point) == pytest.approx((0, 0, 0), abs=1e-9)
        floor = camera.pixel_to_floor(pixel, z=point[2])
        assert floor == pytest.approx(point, abs=1e-9)


@pytest.mark.parametrize('name', CAMERAS)
def test_projection_matches_pybullets_view_and_projection_matrices(name):
    camera = CAMERAS[name]
    view = np.reshape(pybullet.computeViewMatrix(camera.eye, camera.target, camera.up), (4, 4)).T
    projection = np.reshape(
        pybullet.computeProjectionMatrixFOV(camera.fov_deg, camera.aspect, camera.near, camera.far), (4, 4)
    ).T
    for point in POINTS:
        clip = projection @ view @ np.array([*point, 1.0])
        ndc = clip[:3] / clip[3]
        expected = ((ndc[0] + 1) * camera.width / 2, (1 - ndc[1]) * camera.height / 2)
        assert camera.project_3d_to_pixel(point) == pytest.approx(expected, abs=1e-4)  # float32
        depth = np.dot(np.subtract(point, camera.eye), camera.axes()[2])
        buffer = (ndc[2] + 1) / 2  # OpenGL depth buffer value
        assert camera.metric_depth(buffer) == pytest.approx(depth, rel=1e-5)


def test_overhead_image_axes_follow_map_axes():
    camera = CAMERAS['overhead']
    assert camera.project_3d_to_pixel((2.0, 1.5, 0.0)) == pytest.approx((400, 300))
    u_right, v_right = camera.project_3d_to_pixel((2.5, 1.5, 0.0))
    u_up, v_up = camera.project_3d_to_pixel((2.0, 2.0, 0.0))
    assert u_right > 400 and v_right == pytest.approx(300)  # +x is to the right
    assert v_up < 300 and u_up == pytest.approx(400)  # +y is the top of the image
    assert camera.project_3d_to_pixel((2.0, 1.5, 3.5)) == pytest.approx((np.nan, np.nan), nan_ok=True)


def test_overhead_footprint_is_the_rectangle_under_the_camera():
    camera = CAMERAS['overhead']
    half_y = 3.0 * math.tan(math.radians(30))
    half_x = half_y * 800 / 600
    footprint = camera.floor_footprint()
    assert Polygon(footprint).exterior.is_ccw
    assert sorted(footprint) == pytest.approx(
        sorted(
            [
                (2 - half_x, 1.5 - half_y),
                (2 + half_x, 1.5 - half_y),
                (2 + half_x, 1.5 + half_y),
                (2 - half_x, 1.5 + half_y),
            ]
        )
    )
    clipped = Polygon(camera.floor_footprint(floor_size=(5.0, 5.0)))
    assert clipped.bounds == pytest.approx((0.0, 0.0, 2 + half_x, 1.5 + half_y))


def test_footprint_towards_the_horizon_ends_at_far():
    camera = PinholeCamera(
        eye=(0.0, 0.0, 1.0), target=(10.0, 0.0, 0.9), fov_deg=40, width=64, height=48, far=20
    )
    footprint = Polygon(camera.floor_footprint())
    assert footprint.area > 0
    forward = camera.axes()[2]
    depths = [np.dot(np.subtract((x, y, 0.0), camera.eye), forward) for x, y in footprint.exterior.coords]
    assert max(depths) == pytest.approx(20.0)  # cut where the depth reaches far
    assert min(x for x, _ in footprint.exterior.coords) > 0  # only ahead of the camera


@pytest.mark.parametrize(
    'camera',
    [
        PinholeCamera(eye=(0.0, 0.0, 1.0), target=(0.0, 0.0, 2.0), fov_deg=40, width=64, height=48),  # sky
        PinholeCamera(eye=(-5.0, -5.0, 1.0), target=(-5.0, -5.0, 0.0), fov_deg=40, width=64, height=48),
    ],
    ids=['looking_up', 'beside_the_floor'],
)
def test_a_camera_that_sees_no_floor_has_an_empty_footprint(camera):
    assert camera.floor_footprint(floor_size=(4.0, 3.0)) == []


def test_a_camera_moved_on_its_mount_keeps_its_view_direction():
    camera = CAMERAS['tilted'].moved_to(1.5, 0.0)
    assert camera.eye == (1.5, 0.0, 2.5)
    assert camera.target == (3.0, 1.5, 0.0)
