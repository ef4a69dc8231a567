"""``foreground``: what differs from the empty floor, under a global change of light and a soft
shadow; its reference learnt or given; its footprint from the region's edge nearest the camera."""

from dataclasses import replace

import cv2
import numpy as np
import pytest
from shapely.geometry import Point, Polygon

from drvs.algorithms import AlgorithmError, FrameProblem, parse_algorithm
from drvs.algorithms.foreground import LEARN_FRAMES, Foreground, ForegroundParams, read_reference
from drvs.testing.depth import Box, depth_frame
from drvs.vision.camera import PinholeCamera
from drvs.vision.frame_problems import FrameProblems
from drvs.vision.pipeline import project_objects

CAMERA = PinholeCamera(eye=(2.0, 1.5, 3.0), target=(2.0, 1.5, 0.0), fov_deg=60, width=320, height=240)
PALLET = Box((1.0, 0.9), (0.6, 0.6, 0.05))
CRATE = Box((2.0, 1.5), (0.4, 0.6, 0.5))  # below the camera
TALL = Box((3.2, 2.3), (0.5, 0.3, 1.0))  # near the corner of the view
BOXES = (PALLET, CRATE, TALL)


def noisy(rgb, seed=0):
    """A camera's sensor noise (3 grey levels)."""
    noise = np.random.default_rng(seed).normal(0, 3, rgb.shape)
    return np.clip(rgb.astype(np.float32) + noise, 0, 255).astype(np.uint8)


def shaded(rgb, factor):
    return np.clip(rgb.astype(np.float32) * factor, 0, 255).astype(np.uint8)


def soft_shadow():
    """A shadow darkening to 65% in its middle, blurred over ~25 pixels (a diffuse light's)."""
    shade = np.ones((CAMERA.height, CAMERA.width), np.float32)
    shade[40:160, 20:140] = 0.65
    return cv2.GaussianBlur(shade, (0, 0), 12)[..., None]


@pytest.fixture(scope='module')
def scene():
    empty = depth_frame(CAMERA, [])
    return Foreground(noisy(empty.rgb, seed=1)), depth_frame(CAMERA, BOXES)


LIGHTS = {
    'as the reference': lambda rgb: rgb,
    'dimmed to 70%': lambda rgb: shaded(rgb, 0.7),
    'brightened by 25%': lambda rgb: shaded(rgb, 1.25),
    'a soft shadow': lambda rgb: shaded(rgb, soft_shadow()),
}


@pytest.mark.parametrize('light', list(LIGHTS))
def test_each_object_is_found_once_whatever_the_light(scene, light):
    foreground, frame = scene
    lit = replace(frame, rgb=noisy(LIGHTS[light](frame.rgb)))
    objects = project_objects(lit, foreground.detect(lit, ForegroundParams()))
    assert len(objects) == len(BOXES)
    for box in BOXES:
        truth = Polygon(box.footprint())
        assert sum(o.shape.intersects(truth) for o in objects) == 1
    assert all(o.confidence > 0.95 for o in objects)


def test_an_empty_floor_in_a_soft_shadow_and_dimmed_has_nothing_on_it(scene):
    foreground, _ = scene
    empty = depth_frame(CAMERA, [])
    dim = replace(empty, rgb=noisy(shaded(empty.rgb, 0.8 * soft_shadow()), seed=2))
    assert foreground.detect(dim, ForegroundParams()) == []


# box, least IoU of the estimated footprint with the true one; its near edge (towards the point
# below the camera) within 3 cm. A tall box's estimate grows with H / (H - h) (docs/design.md).
@pytest.mark.parametrize(
    'box, least_iou', [(PALLET, 0.9), (CRATE, 0.65), (TALL, 0.35)], ids=['pallet', 'crate', 'tall']
)
def test_the_footprint_is_estimated_from_the_edge_nearest_the_camera(scene, box, least_iou):
    foreground, frame = scene
    objects = project_objects(frame, foreground.detect(frame, ForegroundParams()))
    truth = Polygon(box.footprint())
    (found,) = [o for o in objects if o.shape.intersects(truth)]
    assert found.shape.intersection(truth).area / found.shape.union(truth).area >= least_iou
    assert found.shape.intersection(truth).area / truth.area >= 0.95  # conservative: the box is inside
    below = Point(CAMERA.eye[:2])  # the nearest point of each outline to the point below the camera
    if not truth.contains(below):  # a box below the camera shows no side: its top, enlarged, is all
        assert found.shape.distance(below) == pytest.approx(truth.distance(below), abs=0.03)


def test_without_a_reference_it_learns_the_first_frames_and_says_so_meanwhile():
    empty = depth_frame(CAMERA, [])
    foreground = Foreground()
    frames = [replace(empty, rgb=noisy(empty.rgb, seed=i)) for i in range(LEARN_FRAMES)]
    for i, frame in enumerate(frames[:-1]):
        foreground.observe(frame)
        with pytest.raises(FrameProblem) as error:
            foreground.detect(frame, ForegroundParams())
        assert str(error.value) == (
            f'foreground: learning the reference of the empty floor ({i + 1} of {LEARN_FRAMES} frames); '
            'give the vision system ~reference to start at once'
        )
    foreground.observe(frames[-1])
    boxes = depth_frame(CAMERA, [CRATE])
    assert len(foreground.detect(boxes, ForegroundParams())) == 1


def test_a_reference_of_another_size_is_refused_with_both_sizes():
    foreground = Foreground(np.zeros((120, 160, 3), np.uint8))
    frame = depth_frame(CAMERA, [])
    assert (
        foreground.frame_problem(frame) == 'foreground: the reference image is 160x120 but the frames 320x240'
    )


def test_a_reference_is_read_from_an_image_file(tmp_path):
    rgb = depth_frame(CAMERA, [CRATE]).rgb.copy()
    rgb[0, 0] = (255, 0, 0)
    path = tmp_path / 'floor.png'
    cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert np.array_equal(read_reference(str(path)), rgb)
    with pytest.raises(ValueError) as error:
        read_reference(str(tmp_path / 'none.png'))
    assert str(error.value) == (
        f'{tmp_path}/none.png: cannot read it as an image (no such file, or not a format OpenCV reads)'
    )


@pytest.mark.parametrize('text, message', [('0', "got '0'"), ('x', "got 'x'"), ('1,2', "got '1,2'")])
def test_bad_parameters_are_refused(text, message):
    with pytest.raises(AlgorithmError) as error:
        parse_algorithm(f'foreground:{text}')
    assert (
        str(error.value) == f'algorithm: foreground MIN_AREA must be a positive number of pixels, {message}'
    )


def test_frame_problems_are_held_for_a_while_and_cleared_by_a_frame_that_works():
    problems = FrameProblems(hold=10.0)
    problems.note('elevation', 'elevation: no depth', now=0.0)
    problems.note('foreground', 'foreground: learning', now=5.0)
    assert problems.messages(now=9.0) == ['elevation: no depth', 'foreground: learning']
    assert problems.messages(now=12.0) == ['foreground: learning']
    problems.clear('foreground')
    assert problems.current('foreground', now=12.0) is None
