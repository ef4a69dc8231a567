"""``elevation``: boxes of known size and height on synthetic depth, straight down and from the side
of the view, with and without a depth sensor's noise; its parameters and its refusals."""

from dataclasses import replace

import numpy as np
import pytest
from shapely.geometry import Polygon

from drvs.algorithms import AlgorithmError, builtin_algorithms, parse_algorithm
from drvs.algorithms.elevation import DEFAULT_MIN_HEIGHT, DepthProblem, Elevation, ElevationParams
from drvs.sim.depth_noise import DepthNoise
from drvs.testing.depth import Box, depth_frame
from drvs.vision.camera import PinholeCamera
from drvs.vision.optics import CameraModel
from drvs.vision.pipeline import in_region, project_objects

CAMERA = PinholeCamera(eye=(2.0, 1.5, 3.0), target=(2.0, 1.5, 0.0), fov_deg=60, width=320, height=240)
CENTRE = Box((2.0, 1.5), (0.4, 0.6, 0.5))  # straight below the camera
SIDE = Box((3.2, 2.3), (0.5, 0.3, 1.0))  # near the corner of the view: its side faces show
PALLET = Box((1.0, 0.9), (0.6, 0.6, 0.05))
BOXES = (CENTRE, SIDE, PALLET)
NOISE = DepthNoise(error=0.0015)


# name, box, noisy, least IoU with the true footprint, largest height error (m)
Case = tuple[str, Box, bool, float, float]
# At 320x240 a pixel is 1.4 cm of floor: a clean footprint is within about a pixel all round; with
# noise the sensor's holes along depth edges (2 pixels) cost about another pixel.
CASES: list[Case] = [
    ('below, clean', CENTRE, False, 0.95, 0.005),
    ('side, clean', SIDE, False, 0.93, 0.005),
    ('pallet, clean', PALLET, False, 0.92, 0.005),
    ('below, noisy', CENTRE, True, 0.85, 0.02),
    ('side, noisy', SIDE, True, 0.90, 0.02),
    ('pallet, noisy', PALLET, True, 0.90, 0.02),
]


def noisy(frame, seed=1, noise=NOISE):
    return replace(frame, depth=noise.apply(frame.depth, frame.rgb, np.random.default_rng(seed)))


@pytest.fixture(scope='module')
def frames():
    clean = depth_frame(CAMERA, BOXES)
    return {False: clean, True: noisy(clean)}


def found_on_floor(frame, text='elevation'):
    parsed = parse_algorithm(text)
    return project_objects(frame, parsed.detect(frame))


def best_match(objects, box):
    truth = Polygon(box.footprint())
    return max(objects, key=lambda o: o.shape.intersection(truth).area), truth


@pytest.mark.parametrize('name, box, with_noise, least_iou, height_error', CASES, ids=[c[0] for c in CASES])
def test_a_box_is_reported_as_its_footprint_with_its_top_height(
    frames, name, box, with_noise, least_iou, height_error
):
    objects = found_on_floor(frames[with_noise])
    assert len(objects) == len(BOXES)
    found, truth = best_match(objects, box)
    iou = found.shape.intersection(truth).area / found.shape.union(truth).area
    assert iou >= least_iou, name
    assert found.height == pytest.approx(box.top, abs=height_error)
    assert (0.7 if with_noise else 0.9) <= found.confidence <= 1.0  # holes from the noise lower it


def test_a_tall_box_at_the_side_is_its_footprint_not_its_tops_perspective(frames):
    """The top of a 1 m box near the corner of the view shows ~50% farther out than its footprint:
    met with the floor, the top would be displaced; elevation reports where it stands."""
    pixels = CAMERA.project_3d_to_pixel([(x, y, SIDE.top) for x, y in SIDE.footprint()])
    perspective = Polygon(CAMERA.pixel_to_floor(pixels)[:, :2])
    found, truth = best_match(found_on_floor(frames[False]), SIDE)
    assert perspective.intersection(truth).area / perspective.union(truth).area < 0.3
    assert found.shape.centroid.distance(truth.centroid) < 0.02


def test_min_and_max_height_select_by_the_top():
    objects = found_on_floor(depth_frame(CAMERA, BOXES), 'elevation:0.1,0.8')
    assert [round(o.height, 2) for o in objects] == [0.5]  # the pallet is too low, the 1 m box too high


def test_a_shelf_above_the_floor_is_reported_at_its_footprint_with_its_top():
    shelf = Box((2.3, 1.2), (0.6, 0.4, 0.05), bottom=1.2)
    (found,) = found_on_floor(depth_frame(CAMERA, [shelf]))
    truth = Polygon(shelf.footprint())
    assert found.shape.intersection(truth).area / found.shape.union(truth).area > 0.9
    assert found.height == pytest.approx(1.25, abs=0.005)


# The room under a shelf: a camera that sees floor under it measures its underside from below: the
# clearance is never more than 1 cm too high, and here (the floor seen under it a strip some ten
# pixels deep) at most 3 cm too low on clean depth, 10 cm with a Kinect-class sensor's noise (three
# times its noise come off). One that sees only its top proves nothing (0).
HIGH_SHELF = Box((3.3, 2.2), (0.5, 0.4, 0.1), bottom=0.35)  # the side of the view: floor seen under it
SHELF_BELOW = replace(HIGH_SHELF, centre=(2.0, 1.5))  # straight below the camera: its top alone


@pytest.mark.parametrize('with_noise', [False, True], ids=['clean', 'noisy'])
def test_a_shelf_seen_from_the_side_of_the_view_has_its_clearance(with_noise):
    frame = depth_frame(CAMERA, [HIGH_SHELF, PALLET])
    found, truth = best_match(found_on_floor(noisy(frame) if with_noise else frame), HIGH_SHELF)
    assert found.shape.intersection(truth).area / found.shape.union(truth).area > 0.85
    assert found.height == pytest.approx(HIGH_SHELF.top, abs=0.02)
    assert HIGH_SHELF.bottom - (0.10 if with_noise else 0.03) <= found.clearance <= HIGH_SHELF.bottom + 0.01


@pytest.mark.parametrize('seed', [1, 2])
@pytest.mark.parametrize('centre', [(3.0, 1.5), (1.0, 2.2)])
def test_a_clearance_is_never_much_higher_than_the_underside(seed, centre):
    """Here and there (more places: the slow test below)."""
    shelf = replace(HIGH_SHELF, centre=centre)
    (found,) = found_on_floor(noisy(depth_frame(CAMERA, [shelf]), seed=seed))
    assert found.clearance <= shelf.bottom + 0.01


@pytest.mark.parametrize('with_noise', [False, True], ids=['clean', 'noisy'])
def test_what_is_seen_from_above_only_or_stands_on_the_floor_has_no_clearance(with_noise):
    """The shelf straight below the camera (its top alone), and boxes and a pallet on the floor
    straight down and from the side: 0 (unknown, or on the floor)."""
    frame = depth_frame(CAMERA, [SHELF_BELOW, SIDE, PALLET])
    objects = found_on_floor(noisy(frame) if with_noise else frame)
    assert len(objects) == 3
    assert [o.clearance for o in objects] == [0.0, 0.0, 0.0]
    assert [o.clearance for o in found_on_floor(depth_frame(CAMERA, [CENTRE]))] == [0.0]


def test_a_shelf_behind_a_box_on_the_floor_is_as_low_as_the_box():
    """One region (closer than the closing): the floor seen under the shelf above the box proves
    room, but the lowest side face, the box's, bounds its clearance."""
    box = Box((HIGH_SHELF.centre[0] - 0.28, HIGH_SHELF.centre[1]), (0.03, 0.4, 0.3))
    found, _ = best_match(found_on_floor(depth_frame(CAMERA, [HIGH_SHELF, box])), HIGH_SHELF)
    assert found.clearance == 0.0


def test_an_empty_floor_with_noise_has_nothing_on_it():
    assert found_on_floor(noisy(depth_frame(CAMERA, []), seed=7)) == []


def test_a_calibrated_camera_model_gives_the_same_footprints():
    """A topic camera's model (CameraModel, OpenCV conventions) and the ideal camera agree."""
    clean = depth_frame(CAMERA, BOXES)
    model = CameraModel.from_pinhole(CAMERA)
    objects = found_on_floor(replace(clean, camera=model))
    found, truth = best_match(objects, SIDE)
    assert found.shape.intersection(truth).area / found.shape.union(truth).area > 0.93


def test_objects_carry_their_height_to_the_request():
    objects = found_on_floor(depth_frame(CAMERA, [CENTRE]))
    (located,) = in_region(objects, (1.0, 1.0, 2.0, 2.0))  # clipped to the region's half of the box
    assert located.height == pytest.approx(0.5, abs=0.005)
    (shelf,) = in_region(found_on_floor(depth_frame(CAMERA, [HIGH_SHELF])), (3.0, 2.0, 4.0, 3.0))
    assert shelf.clearance == pytest.approx(HIGH_SHELF.bottom, abs=0.06)


@pytest.mark.parametrize(
    'text, params',
    [
        ('', ElevationParams(DEFAULT_MIN_HEIGHT, None)),
        ('0.05', ElevationParams(0.05, None)),
        (' 0.05 , 1.2 ', ElevationParams(0.05, 1.2)),
    ],
)
def test_parameters(text, params):
    assert Elevation().parse(text) == params


@pytest.mark.parametrize(
    'text, message',
    [
        ('x', "algorithm: elevation MIN_HEIGHT must be a number of metres >= 0, got 'x'"),
        ('-1', "algorithm: elevation MIN_HEIGHT must be a number of metres >= 0, got '-1'"),
        ('0.1,nan', "algorithm: elevation MAX_HEIGHT must be a number of metres >= 0, got 'nan'"),
        ('0.5,0.2', 'algorithm: elevation MAX_HEIGHT 0.2 is not above MIN_HEIGHT 0.5'),
        ('1,2,3', "algorithm: elevation takes MIN_HEIGHT[,MAX_HEIGHT] (metres), got 3 fields in '1,2,3'"),
    ],
)
def test_bad_parameters_are_refused_naming_the_field(text, message):
    with pytest.raises(AlgorithmError) as error:
        Elevation().parse(text)
    assert str(error.value) == message


def test_a_camera_without_depth_does_not_run_elevation():
    assert 'elevation' in [a.name for a in builtin_algorithms()]
    assert 'elevation' not in [a.name for a in builtin_algorithms(depth=False)]


@pytest.mark.parametrize(
    'change, message',
    [
        (
            {'depth': None},
            'elevation: the frame has no depth image (a camera without depth cannot run elevation)',
        ),
        (
            {'depth': np.ones((120, 160), np.float32)},
            'elevation: the depth image is 160x120 but the colour image 320x240: '
            'depth must be registered to the colour image',
        ),
        (
            {'depth': np.zeros((240, 320), np.float32)},
            'elevation: the depth image has no valid pixel (every one 0, NaN or infinite)',
        ),
        (
            {'depth': np.zeros((240, 320, 3), np.float32)},
            'elevation: the depth image is not one channel of numbers (shape (240, 320, 3), float32)',
        ),
    ],
    ids=['none', 'size', 'all invalid', 'channels'],
)
def test_unusable_depth_is_refused_with_what_is_wrong(change, message):
    frame = replace(depth_frame(CAMERA, [CENTRE]), **change)
    with pytest.raises(DepthProblem) as error:
        Elevation().detect(frame, ElevationParams())
    assert str(error.value) == message


@pytest.mark.parametrize('seed', [1, 2, 3])
def test_with_a_noisier_sensor_each_box_is_still_one_object(seed):
    """Twice the error and wider holes: even the 5 cm pallet (below 2 sigma at 3 m per pixel) is
    one object."""
    noise = DepthNoise(error=0.003, edge_width=3)
    objects = found_on_floor(noisy(depth_frame(CAMERA, BOXES), seed=seed, noise=noise))
    assert len(objects) == len(BOXES)
    for box in BOXES:
        found, truth = best_match(objects, box)
        assert found.shape.intersection(truth).area / found.shape.union(truth).area >= 0.7, box
        assert found.height == pytest.approx(box.top, abs=0.03)


def test_a_ragged_edge_moved_in_keeps_the_body_not_nothing():
    """Moving a region's outline in by half a cell cuts a one-cell spur off its ragged edge: the body
    is what stays (it used to be dropped whole, losing a noisy pallet)."""
    from drvs.algorithms.elevation import _inset

    neck = [(5.5, 10), (5.5, 10.6), (7, 10.6), (7, 13.6), (4, 13.6), (4, 10.6), (5, 10.6), (5, 10)]
    body = [(0, 0), (10, 0), (10, 10), *neck, (0, 10)]  # a 3 x 3 blob on a half-cell neck
    inset = Polygon(_inset(np.asarray(body, float), 1.0))
    assert inset.area == pytest.approx(81.0)  # the 10 x 10 body, 0.5 in all round, not the blob


def test_the_rays_kept_per_lens_follow_the_camera_as_it_moves():
    """Undistorting every pixel is done once per lens; each pose only turns the result."""
    lens = CameraModel.from_pinhole(CAMERA, distortion=(-0.2, 0.05, 0.001, -0.001, 0.0))
    frame = depth_frame(CAMERA, [])
    elevation = Elevation()
    for turned, offset in ((CAMERA, (0.0, 0.0)), (replace(CAMERA, target=(2.3, 1.8, 0.0)), (-0.5, 0.5))):
        for camera in (turned, CameraModel.from_pinhole(turned, distortion=lens.D)):
            shown = replace(frame, camera=camera, sample_offset=offset)
            rays = elevation._rays_of(shown)
            pixels = shown.to_camera([(0.5, 0.5), (200.5, 100.5), (319.5, 239.5)])
            expected = camera.pixel_to_point(pixels, np.ones(3)) - np.asarray(camera.eye)
            assert rays[[0, 100, 239], [0, 200, 319]] == pytest.approx(expected, abs=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize('with_noise, lowest', [(False, -0.07), (True, -0.17)], ids=['clean', 'noisy'])
def test_over_the_view_a_clearance_is_from_below_and_boxes_have_none(with_noise, lowest):
    """docs/design.md's figures: a 35 cm shelf, a 40 cm box and a 1 m box at 18 places over the
    view, two noise seeds: the shelf's clearance 0 or within (lowest, +1 cm) of its underside, and
    measured at 29 of the 36 at least; the boxes' always 0."""
    errors, found_under = [], 0
    for x in np.linspace(1.0, 3.4, 6):
        for y in (0.7, 1.5, 2.3):
            shelf = replace(HIGH_SHELF, centre=(x, y))
            for box in (shelf, Box((x, y), (0.5, 0.3, 0.4)), Box((x, y), (0.4, 0.5, 1.0))):
                for seed in (0, 1):
                    frame = depth_frame(CAMERA, [box])
                    (found,) = found_on_floor(noisy(frame, seed=seed) if with_noise else frame)
                    if box is not shelf:
                        assert found.clearance == 0.0, box
                    elif found.clearance > 0:
                        found_under += 1
                        errors.append(found.clearance - shelf.bottom)
    assert found_under >= 29
    assert lowest <= min(errors) and max(errors) <= 0.01
