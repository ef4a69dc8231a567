"""The CameraInfo camera model: agrees with the ideal camera, round trips through a lens, its footprints."""

import doctest
import math

import cv2
import numpy as np
import pytest
from shapely.geometry import Point, Polygon

import drvs.vision.optics
from drvs.sim.scene import TINY_RENDERER_SAMPLE
from drvs.vision.camera import PinholeCamera
from drvs.vision.optics import UNDISTORT_TOLERANCE, CameraModel, intrinsics_of, optical_pose_of

CAMERAS = {
    'overhead': PinholeCamera(eye=(2.0, 1.5, 3.0), target=(2.0, 1.5, 0.0), fov_deg=60, width=800, height=600),
    'tilted': PinholeCamera(eye=(0.5, 0.5, 2.5), target=(2.0, 2.0, 0.0), fov_deg=45, width=640, height=480),
    'rotated_up': PinholeCamera(
        eye=(1.0, 1.0, 4.0), target=(1.2, 0.9, 0.0), fov_deg=70, width=320, height=240, up=(1.0, 1.0, 0.0)
    ),
}
POINTS = np.array([(2.0, 1.5, 0.0), (2.4, 1.1, 0.5), (1.3, 2.2, 0.0), (1.9, 1.7, 1.2), (0.8, 1.9, 0.1)])
PLUMB_BOB = (-0.25, 0.08, 0.001, -0.001, 0.0)
BARREL = (-0.25, 0.08, 0.0, 0.0, 0.0)
DISTORTIONS = {
    'four': (-0.2, 0.05, 0.002, -0.001),
    'plumb_bob': PLUMB_BOB,
    'rational_polynomial': (-0.1, 0.02, 0.001, 0.002, 0.0, 0.2, 0.01, 0.0),
    'thin_prism': (-0.2, 0.05, 0.001, -0.002, 0.0, 0.0, 0.0, 0.0, 0.003, -0.001, 0.002, 0.001),
}


def pixel_grid(camera, n=9):
    """An n x n grid of positions over the whole image, its border and corners included."""
    u, v = np.meshgrid(np.linspace(0.0, camera.width, n), np.linspace(0.0, camera.height, n))
    return np.c_[u.ravel(), v.ravel()]


def depth_of(model, points):
    return (np.atleast_2d(points) - model.translation) @ model.rotation[:, 2]


def test_doctests():
    assert doctest.testmod(drvs.vision.optics).failed == 0


@pytest.mark.parametrize('name', CAMERAS)
def test_without_distortion_the_model_agrees_with_the_pinhole_camera(name):
    camera = CAMERAS[name]
    model = CameraModel.from_pinhole(camera, (0.0, 0.0))
    pixels = pixel_grid(camera, 11)
    assert model.project_3d_to_pixel(POINTS) == pytest.approx(camera.project_3d_to_pixel(POINTS), abs=1e-9)
    assert model.project_pixel_to_3d_ray(pixels) == pytest.approx(
        camera.project_pixel_to_3d_ray(pixels), abs=1e-9
    )
    floor = camera.pixel_to_floor(pixels, z=0.3)
    assert model.pixel_to_floor(pixels, z=0.3) == pytest.approx(floor, abs=1e-9, nan_ok=True)
    assert model.pixel_to_point(pixels, 2.5) == pytest.approx(camera.pixel_to_point(pixels, 2.5), abs=1e-9)
    # single positions keep their shape
    assert model.project_3d_to_pixel(POINTS[1]).shape == (2,)
    assert model.pixel_to_floor(pixels[3]) == pytest.approx(camera.pixel_to_floor(pixels[3]), abs=1e-9)
    assert model.eye == pytest.approx(camera.eye)


def test_the_footprint_without_distortion_is_the_pinhole_cameras():
    camera = CAMERAS['overhead']
    model = CameraModel.from_pinhole(camera)
    footprint = model.floor_footprint(max_range=100.0)
    assert Polygon(footprint).exterior.is_ccw
    assert Polygon(footprint).symmetric_difference(Polygon(camera.floor_footprint())).area == pytest.approx(
        0.0, abs=1e-9
    )
    clipped = Polygon(model.floor_footprint(max_range=100.0, floor_size=(5.0, 5.0)))
    expected = Polygon(camera.floor_footprint(floor_size=(5.0, 5.0)))
    assert clipped.symmetric_difference(expected).area == pytest.approx(0.0, abs=1e-9)


def test_a_model_of_rendered_frames_takes_the_renderers_sample_offset():
    """Array positions of a TinyRenderer frame + the sample offset are the ideal camera's (u, v)."""
    camera = CAMERAS['tilted']
    model = CameraModel.from_pinhole(camera, TINY_RENDERER_SAMPLE)
    expected = camera.project_3d_to_pixel(POINTS) - np.asarray(TINY_RENDERER_SAMPLE)
    assert model.project_3d_to_pixel(POINTS) == pytest.approx(expected, abs=1e-9)
    assert np.array_equal(model.K, intrinsics_of(camera, TINY_RENDERER_SAMPLE))
    rotation, translation = optical_pose_of(camera)
    assert np.array_equal(model.rotation, rotation) and np.array_equal(model.translation, translation)


@pytest.mark.parametrize('name', DISTORTIONS)
def test_projection_through_the_lens_is_opencvs(name):
    camera = CAMERAS['tilted']
    model = CameraModel.from_pinhole(camera, (0.0, 0.0), DISTORTIONS[name])
    rvec, _ = cv2.Rodrigues(model.rotation.T)
    tvec = -model.rotation.T @ model.translation
    expected, _ = cv2.projectPoints(POINTS, rvec, tvec, model.K, np.asarray(model.D))
    assert model.project_3d_to_pixel(POINTS) == pytest.approx(expected.reshape(-1, 2) + 0.5, abs=1e-9)


@pytest.mark.parametrize('name', DISTORTIONS)
@pytest.mark.parametrize('camera_name', ['tilted', 'rotated_up'])
def test_pixel_to_floor_and_back_through_the_lens(name, camera_name):
    camera = CAMERAS[camera_name]
    model = CameraModel.from_pinhole(camera, TINY_RENDERER_SAMPLE, DISTORTIONS[name])
    pixels = pixel_grid(camera, 15)
    floor = model.pixel_to_floor(pixels, z=0.2)
    seen = np.isfinite(floor).all(axis=1)
    assert seen.sum() > 100
    assert floor[seen, 2] == pytest.approx(0.2)
    assert model.project_3d_to_pixel(floor[seen]) == pytest.approx(pixels[seen], abs=1e-6)
    # and from the floor: points in view -> pixels -> the same points
    inner = pixels[seen] * 0.9 + (0.05 * camera.width, 0.05 * camera.height)
    points = model.pixel_to_floor(inner, z=0.0)
    back = model.pixel_to_floor(model.project_3d_to_pixel(points), z=0.0)
    assert back == pytest.approx(points, abs=1e-6)


def test_rays_and_depths_through_the_lens():
    model = CameraModel.from_pinhole(CAMERAS['overhead'], TINY_RENDERER_SAMPLE, PLUMB_BOB)
    pixels = model.project_3d_to_pixel(POINTS)
    assert model.pixel_to_point(pixels, depth_of(model, POINTS)) == pytest.approx(POINTS, abs=1e-6)
    assert model.pixel_to_point(pixels[2], depth_of(model, POINTS[2])[0]) == pytest.approx(
        POINTS[2], abs=1e-6
    )
    rays = model.project_pixel_to_3d_ray(pixels)
    towards = (POINTS - model.translation) / np.linalg.norm(POINTS - model.translation, axis=1)[:, None]
    assert rays == pytest.approx(towards, abs=1e-9)


def test_points_behind_the_camera_and_rays_into_the_sky_have_no_image():
    camera = PinholeCamera(
        eye=(0.0, 0.0, 1.0), target=(5.0, 0.0, 1.0), fov_deg=60, width=64, height=48, up=(0.0, 0.0, 1.0)
    )
    model = CameraModel.from_pinhole(camera, (0.0, 0.0), PLUMB_BOB)
    assert np.isnan(model.project_3d_to_pixel((-1.0, 0.0, 1.0))).all()
    assert np.isnan(model.project_3d_to_pixel([(1.0, 0.0, 0.0), (-1.0, 0.0, 0.0)])[1]).all()
    assert np.isnan(model.pixel_to_floor((32.0, 2.0))).all()  # above the horizon
    assert np.isfinite(model.pixel_to_floor((32.0, 46.0))).all()


def test_undistortion_converges_at_the_corners_where_opencvs_default_does_not():
    """cv2.undistortPoints' 5 fixed-point iterations leave a 90 degree barrel lens's corners far off."""
    camera = PinholeCamera(eye=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0), fov_deg=90, width=800, height=600)
    model = CameraModel.from_pinhole(camera, (0.0, 0.0), PLUMB_BOB)
    corners = np.array([(0.5, 0.5), (799.5, 0.5), (799.5, 599.5), (0.5, 599.5)])
    opencv = cv2.undistortPoints((corners - 0.5).reshape(-1, 1, 2), model.K, np.asarray(model.D)).reshape(
        -1, 2
    )
    at_origin = model.with_pose(np.eye(3), np.zeros(3))  # map = optical frame: (x, y, 1) projects
    opencv_error = np.abs(at_origin.project_3d_to_pixel(np.c_[opencv, np.ones(4)]) - corners).max()
    assert opencv_error > 10.0
    ours = model.undistort(corners)
    assert np.abs(at_origin.project_3d_to_pixel(np.c_[ours, np.ones(4)]) - corners).max() < 1e-8


def test_a_lens_that_folds_over_leaves_what_it_cannot_undo_undefined():
    """k1 = -0.9 alone: the distorted radius peaks at 0.385; pixels beyond have no ray."""
    camera = PinholeCamera(eye=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0), fov_deg=90, width=800, height=600)
    model = CameraModel.from_pinhole(camera, (0.0, 0.0), (-0.9, 0.0, 0.0, 0.0, 0.0))
    centre, corner = model.undistort([(400.0, 300.0), (10.5, 10.5)])
    assert centre == pytest.approx((0.0, 0.0))
    assert np.isnan(corner).all()
    assert UNDISTORT_TOLERANCE <= 1e-6


TILTED_TO_THE_HORIZON = PinholeCamera(
    eye=(0.0, 0.0, 1.5), target=(10.0, 0.0, 1.0), fov_deg=50, width=320, height=240, up=(0.0, 0.0, 1.0)
)


@pytest.mark.parametrize('distortion', [(), PLUMB_BOB], ids=['ideal', 'plumb_bob'])
def test_a_view_to_the_horizon_is_cut_at_max_range(distortion):
    model = CameraModel.from_pinhole(TILTED_TO_THE_HORIZON, TINY_RENDERER_SAMPLE, distortion)
    areas = []
    for max_range in (5.0, 10.0, 20.0):
        footprint = model.floor_footprint(max_range)
        assert len(footprint) >= 3 and np.all(np.isfinite(footprint))
        assert Polygon(footprint).exterior.is_ccw
        distances = [math.dist((x, y, 0.0), model.eye) for x, y in footprint]
        assert max(distances) <= max_range * (1 + 1e-9)
        areas.append(Polygon(footprint).area)
        # every floor point the image sees within (nearly) max_range is in it
        floor = model.pixel_to_floor(pixel_grid(model, 41))
        near = [p for p in floor if np.isfinite(p).all() and math.dist(p, model.eye) <= 0.99 * max_range]
        assert len(near) > 100
        shape = Polygon(footprint).buffer(0.01)
        assert all(shape.contains(Point(p[:2])) for p in near)
    assert areas[0] < areas[1] < areas[2]


def test_barrel_distortion_widens_the_footprint_of_a_camera_looking_down():
    camera = PinholeCamera(eye=(2.0, 1.5, 3.0), target=(2.0, 1.5, 0.0), fov_deg=70, width=320, height=240)
    ideal = Polygon(CameraModel.from_pinhole(camera).floor_footprint(max_range=50.0))
    model = CameraModel.from_pinhole(camera, TINY_RENDERER_SAMPLE, BARREL)
    footprint = Polygon(model.floor_footprint(max_range=50.0))
    assert footprint.exterior.is_ccw
    assert footprint.area > 1.1 * ideal.area
    floor = model.pixel_to_floor(pixel_grid(camera, 41))
    assert np.isfinite(floor).all()
    shape = footprint.buffer(0.01)
    assert all(shape.contains(Point(p[:2])) for p in floor)
    clipped = Polygon(model.floor_footprint(max_range=50.0, floor_size=(4.0, 3.0)))
    assert clipped.bounds == pytest.approx((0.0, 0.0, 4.0, 3.0))  # the view covers the whole floor


@pytest.mark.parametrize(
    'eye, target',
    [((0.0, 0.0, 0.0), (1.0, 0.0, -1.0)), ((0.0, 0.0, -1.0), (0.0, 0.0, -2.0)), ((0, 0, 1.0), (0, 0, 2.0))],
    ids=['on_the_floor', 'below_the_floor', 'looking_up'],
)
def test_a_camera_that_cannot_see_the_floor_has_an_empty_footprint(eye, target):
    camera = PinholeCamera(eye=eye, target=target, fov_deg=60, width=64, height=48)
    assert CameraModel.from_pinhole(camera, (0.0, 0.0), PLUMB_BOB).floor_footprint(10.0) == []


def test_max_range_below_the_camera_height_sees_nothing():
    model = CameraModel.from_pinhole(CAMERAS['overhead'])
    assert model.floor_footprint(max_range=3.0) == []
    assert model.floor_footprint(max_range=3.1) != []


def test_a_model_moved_to_another_pose_keeps_its_optics():
    model = CameraModel.from_pinhole(CAMERAS['overhead'], TINY_RENDERER_SAMPLE, PLUMB_BOB)
    moved = model.with_pose(*optical_pose_of(CAMERAS['tilted']))
    assert moved.eye == CAMERAS['tilted'].eye and model.eye == CAMERAS['overhead'].eye
    assert moved.D == model.D and np.array_equal(moved.K, model.K)
    assert moved.project_3d_to_pixel(POINTS[0]) != pytest.approx(model.project_3d_to_pixel(POINTS[0]))
    with pytest.raises(ValueError):
        model.K[0, 0] = 1.0  # the arrays are read-only: the model is immutable


@pytest.mark.parametrize(
    'change, message',
    [
        (
            {'D': (0.1, 0.2, 0.3)},
            'CameraModel: D: expected 0, 4, 5, 8, 12 finite coefficients (OpenCV order), '
            'got 3: [0.1, 0.2, 0.3]',
        ),
        ({'width': 0}, 'CameraModel: width: expected a positive integer, got 0'),
        ({'translation': (1.0, 2.0)}, 'CameraModel: translation: expected 3 finite numbers, got (1.0, 2.0)'),
    ],
    ids=['D', 'width', 'translation'],
)
def test_an_invalid_model_is_refused_naming_the_field(change, message):
    fields = {
        'K': intrinsics_of(CAMERAS['overhead']),
        'D': (),
        'width': 800,
        'height': 600,
        'rotation': np.eye(3),
        'translation': np.zeros(3),
    }
    with pytest.raises(ValueError) as error:
        CameraModel(**{**fields, **change})
    assert str(error.value) == message


def test_pixels_of_the_wrong_shape_are_refused():
    model = CameraModel.from_pinhole(CAMERAS['overhead'])
    with pytest.raises(ValueError) as error:
        model.pixel_to_floor([(1.0, 2.0, 3.0)])
    assert str(error.value) == 'CameraModel: pixels: expected shape (2,) or (N, 2), got (1, 3)'


@pytest.mark.parametrize('max_range', [0.0, -1.0, math.inf, math.nan])
def test_max_range_must_be_a_positive_distance(max_range):
    model = CameraModel.from_pinhole(CAMERAS['overhead'])
    with pytest.raises(ValueError) as error:
        model.floor_footprint(max_range)
    assert str(error.value) == (
        'CameraModel.floor_footprint: max_range: expected a positive finite number of metres, '
        f'got {max_range!r}'
    )
