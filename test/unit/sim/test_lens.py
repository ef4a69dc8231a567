"""Rendering through a lens: the identity without distortion; distorted frames the lens model reads back."""

import math

import numpy as np
import pytest
import yaml
from shapely.geometry import Polygon

from drvs.algorithms import parse_algorithm
from drvs.sim.lens import MAX_CANVAS, Lens
from drvs.sim.scene import TINY_RENDERER_SAMPLE, Scene
from drvs.sim.world import box_footprint
from drvs.sim.world_file import load_world
from drvs.vision.camera import PinholeCamera
from drvs.vision.frame import Frame
from drvs.vision.optics import CameraModel, intrinsics_of
from drvs.vision.pipeline import locate_objects, vertex_depths

BARREL = (-0.2, 0.05, 0.001, -0.001, 0.0)
WHOLE_FLOOR = (0.0, 0.0, 6.0, 4.0)
PLATE = {'position': (3.0, 2.1), 'size': (0.3, 0.3, 0.002), 'yaw': 0.3}  # thin: no sides seen
CRATE = {'position': (1.2, 2.2), 'size': (0.35, 0.25, 0.3), 'yaw': 0.5}
WORLD = {
    'floor': {'size': [6.0, 4.0], 'colour': [255, 255, 255]},
    # robot and station far outside the view
    'robot': {'position': [5.5, 3.5], 'size': [0.3, 0.3, 0.2], 'colour': [0, 200, 0]},
    'station': {'position': [5.5, 0.5], 'size': [0.4, 0.3, 0.1], 'colour': [0, 0, 220]},
    'objects': [
        {
            'name': 'plate',
            'colour': [60, 60, 60],
            **{k: list(v) if k != 'yaw' else v for k, v in PLATE.items()},
        },
        {
            'name': 'crate',
            'colour': [0, 0, 220],
            'decoy': True,  # blue like a station: found by the station model, on purpose
            **{k: list(v) if k != 'yaw' else v for k, v in CRATE.items()},
        },
        # a long, thin, flat strip along x, well off the image's centre line
        {'name': 'strip', 'position': [2.0, 0.75], 'size': [2.4, 0.08, 0.02], 'colour': [220, 0, 0]},
    ],
    'vision_systems': [{'name': 'vs1', 'position': [2.0, 1.5, 2.0], 'fov_deg': 60, 'resolution': [320, 240]}],
    'colour_models': {
        'self': 'colour:0,150,0,80,255,80',
        'station': 'colour:0,0,150,80,80,255',
        'obstacle': 'colour:40,40,40,90,90,90',
        'human': 'colour:150,0,0,255,80,80',
    },
}
MODELS = {'plate': 'obstacle', 'crate': 'station', 'strip': 'human'}


@pytest.fixture(scope='module')
def views(tmp_path_factory):
    """The world, its camera, and for each lens (ideal, barrel) the lens and its output frame."""
    path = tmp_path_factory.mktemp('lens') / 'lens.yaml'
    path.write_text(yaml.safe_dump(WORLD))
    world = load_world(path)
    camera = PinholeCamera.from_config(world.vision_systems[0])
    lenses = {'ideal': Lens(camera, ()), 'barrel': Lens(camera, BARREL)}
    with Scene(world) as scene:
        frames = {name: lens.apply(scene.render(lens.canvas, 7.0)) for name, lens in lenses.items()}
    return world, camera, lenses, frames


def mask_of(world, frame, name):
    return parse_algorithm(world.colour_models[MODELS[name]]).params.mask(frame.rgb) > 0


def centroid(mask):
    rows, columns = np.nonzero(mask)
    return np.array([columns.mean() + 0.5, rows.mean() + 0.5])  # DRVS coordinates


def test_without_distortion_the_lens_is_the_identity(views):
    world, camera, lenses, frames = views
    for distortion in ((), (0.0,) * 5):
        lens = Lens(camera, distortion)
        assert lens.identity and lens.canvas is camera and lens.padding == (0, 0)
        assert np.array_equal(lens.model.K, intrinsics_of(camera, TINY_RENDERER_SAMPLE))
    with Scene(world) as scene:
        frame = scene.render(camera, 3.0)
    assert lenses['ideal'].apply(frame) is frame


def test_the_canvas_has_the_cameras_focal_length_and_pose(views):
    _, camera, lenses, frames = views
    lens = lenses['barrel']
    canvas = lens.canvas
    assert (canvas.eye, canvas.target, canvas.up) == (camera.eye, camera.target, camera.up)
    assert canvas.width == camera.width + 2 * lens.padding[0]
    assert canvas.height == camera.height + 2 * lens.padding[1]
    assert canvas.width > camera.width and canvas.height > camera.height  # barrel: it sees wider
    K, K_canvas = intrinsics_of(camera, TINY_RENDERER_SAMPLE), intrinsics_of(canvas, TINY_RENDERER_SAMPLE)
    assert K_canvas[0, 0] == pytest.approx(K[0, 0], rel=1e-12)
    assert K_canvas[:2, 2] == pytest.approx(K[:2, 2] + lens.padding, abs=1e-9)
    assert lens.model.D == BARREL and np.array_equal(lens.model.K, K)
    frame = frames['barrel']
    assert frame.rgb.shape == (camera.height, camera.width, 3) and frame.depth.shape == (
        camera.height,
        camera.width,
    )
    assert frame.depth.dtype == np.float32 and frame.stamp == 7.0
    assert isinstance(frame.camera, CameraModel) and frame.sample_offset == (0.0, 0.0)
    assert frame.camera.eye == camera.eye


def test_each_output_pixel_is_taken_from_where_its_ray_meets_the_canvas(views):
    """A canvas whose pixels hold their own (column, row): the output shows each pixel's source."""
    _, camera, lenses, _ = views
    lens = lenses['barrel']
    canvas = lens.canvas
    rows, columns = np.mgrid[0 : canvas.height, 0 : canvas.width].astype(np.float32)
    coordinates = np.dstack([columns, rows, np.zeros_like(rows)])
    frame = lens.apply(Frame(coordinates, rows.copy(), canvas, 0.0, TINY_RENDERER_SAMPLE))
    # Where the ray of each output pixel centre lands in the canvas render (array coordinates).
    out_rows, out_columns = np.mgrid[0 : camera.height, 0 : camera.width]
    centres = np.c_[out_columns.ravel(), out_rows.ravel()] + 0.5
    points = lens.model.pixel_to_point(centres, 1.0)
    expected = CameraModel.from_pinhole(canvas, TINY_RENDERER_SAMPLE).project_3d_to_pixel(points) - 0.5
    assert frame.rgb[..., :2].reshape(-1, 2) == pytest.approx(expected, abs=1 / 32)  # remap's bilinear steps
    assert np.abs(frame.depth.ravel() - expected[:, 1]).max() <= 0.5 + 0.01  # nearest
    assert expected.min() >= 1.0 and (expected.max(axis=0) <= (canvas.width - 2, canvas.height - 2)).all()


def test_a_plate_appears_where_the_lens_model_projects_it(views):
    world, camera, lenses, frames = views
    top_centre = (*PLATE['position'], PLATE['size'][2])
    seen = centroid(mask_of(world, frames['barrel'], 'plate'))
    assert seen == pytest.approx(lenses['barrel'].model.project_3d_to_pixel(top_centre), abs=1.5)
    ideal = camera.project_3d_to_pixel(top_centre) - np.asarray(TINY_RENDERER_SAMPLE)
    assert np.linalg.norm(seen - ideal) > 4.0  # the lens moved it noticeably
    assert centroid(mask_of(world, frames['ideal'], 'plate')) == pytest.approx(ideal, abs=1.5)


def bow(mask):
    """Largest distance (pixels) of a strip's centre line from the straight line fitted to it."""
    columns = np.flatnonzero(mask.any(axis=0))[3:-3]  # not its rounded ends
    rows = np.array([np.flatnonzero(mask[:, c]).mean() for c in columns])
    line = np.polyval(np.polyfit(columns, rows, 1), columns)
    return np.abs(rows - line).max()


def test_a_straight_strip_on_the_floor_appears_curved(views):
    world, _, _, frames = views
    assert bow(mask_of(world, frames['ideal'], 'strip')) < 0.6
    assert bow(mask_of(world, frames['barrel'], 'strip')) > 2.0


def test_depth_through_the_lens_is_along_the_optical_axis(views):
    world, camera, lenses, frames = views
    frame = frames['barrel']
    plate = mask_of(world, frame, 'plate')
    top = np.abs(frame.depth[plate] - (camera.eye[2] - PLATE['size'][2])) < 1e-3
    assert top.mean() > 0.9  # the rest: blended edge colours next to the floor's depth
    assert frame.depth[0, 0] == pytest.approx(camera.eye[2], abs=1e-3)  # the floor in a corner


@pytest.mark.parametrize('name, body', [('plate', PLATE), ('crate', CRATE)])
def test_outlines_through_the_lens_lie_on_the_true_footprint(views, name, body):
    world, _, lenses, frames = views
    frame = frames['barrel']
    truth = Polygon(box_footprint(body['position'], body['size'][:2], body['yaw']))
    algorithm = parse_algorithm(world.colour_models[MODELS[name]])
    outline = max(algorithm.detect(frame), key=lambda o: o.area).outline
    points = lenses['barrel'].model.pixel_to_point(outline, vertex_depths(frame, outline))
    found = Polygon(points[:, :2])
    for corner in truth.exterior.coords[:-1]:
        assert min(math.dist(corner, p) for p in found.exterior.coords) <= 0.02
    assert found.hausdorff_distance(truth) <= 0.02
    # The frame's camera is the lens model, so drvs.vision.pipeline reads distorted frames unchanged.
    located = [Polygon(o) for o in locate_objects(frame, algorithm, WHOLE_FLOOR)]
    assert len(located) == 1 and located[0].hausdorff_distance(truth) <= 0.02


def test_a_lens_applies_to_its_canvas_moved_on_the_mount(views):
    world, _, lenses, _ = views
    lens = lenses['barrel']
    with Scene(world) as scene:
        frame = lens.apply(scene.render(lens.canvas.moved_to(2.6, 1.8)))
    assert frame.camera.eye == (2.6, 1.8, 2.0)
    truth = Polygon(box_footprint(PLATE['position'], PLATE['size'][:2], PLATE['yaw']))
    located = locate_objects(frame, parse_algorithm(world.colour_models['obstacle']), WHOLE_FLOOR)
    assert len(located) == 1 and Polygon(located[0]).hausdorff_distance(truth) <= 0.02


def test_a_frame_not_rendered_with_the_canvas_is_refused(views):
    world, camera, lenses, _ = views
    with Scene(world) as scene:
        frame = scene.render(camera)
    with pytest.raises(ValueError) as error:
        lenses['barrel'].apply(frame)
    canvas = lenses['barrel'].canvas
    assert str(error.value) == (
        f'Lens.apply: expected a frame rendered with the lens canvas ({canvas.width}x{canvas.height}, '
        f'fov {canvas.fov_deg:.6g} deg), got 320x240 from {camera!r}'
    )


def test_a_lens_needing_too_large_a_canvas_is_refused():
    camera = PinholeCamera(eye=(0.0, 0.0, 2.0), target=(0.0, 0.0, 0.0), fov_deg=90, width=3600, height=2700)
    with pytest.raises(ValueError) as error:
        Lens(camera, (-0.25, 0.08, 0.001, -0.001, 0.0))
    assert str(error.value) == (
        'Lens: distortion [-0.25, 0.08, 0.001, -0.001, 0.0] needs a 4202x3378 canvas to render the 3600x2700 '
        f'image; the limit is {MAX_CANVAS} pixels per side (the distortion is too strong for this field of '
        'view and resolution)'
    )


def test_a_lens_that_folds_over_is_refused():
    camera = PinholeCamera(eye=(0.0, 0.0, 2.0), target=(0.0, 0.0, 0.0), fov_deg=90, width=160, height=120)
    with pytest.raises(ValueError) as error:
        Lens(camera, (-0.9, 0.0, 0.0, 0.0, 0.0))
    assert str(error.value) == (
        'Lens: distortion [-0.9, 0.0, 0.0, 0.0, 0.0] cannot be undone at 68 of 260 border points of the '
        '160x120 image (first at (52.5, 0.0)): the lens model folds over there'
    )
