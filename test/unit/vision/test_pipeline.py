"""Outlines on the floor from rendered views, checked against the world's ground truth."""

import threading
from pathlib import Path

import numpy as np
import pytest
import yaml
from shapely.geometry import Polygon, box

from drvs.algorithms import PixelObject, parse_algorithm
from drvs.sim.scene import TINY_RENDERER_SAMPLE, Scene
from drvs.sim.world_file import load_world
from drvs.vision.camera import PinholeCamera
from drvs.vision.frame import Frame
from drvs.vision.pipeline import FrameCache, draw_detections, in_region, locate_objects, project_objects

ACCURACY_WORLD = 'test/worlds/accuracy.yaml'
WHOLE_FLOOR = (0.0, 0.0, 6.0, 4.0)


@pytest.fixture(scope='module')
def accuracy():
    """The accuracy world and one 800x600 frame from each of its cameras (rendered once)."""
    world = load_world(ACCURACY_WORLD)
    with Scene(world) as scene:
        frames = {c.name: scene.render(PinholeCamera.from_config(c)) for c in world.vision_systems}
    return world, frames


def match(outlines, truth):
    """The outline overlapping ``truth`` most."""
    return max((Polygon(o) for o in outlines), key=lambda p: p.intersection(truth).area)


def iou(a, b):
    return a.intersection(b).area / a.union(b).area


def test_the_renderer_samples_where_the_scene_module_says(tmp_path):
    """A flat plate covers exactly the pixels whose sample points fall inside its projection."""
    data = yaml.safe_load(Path(ACCURACY_WORLD).read_text())
    data['objects'] = [
        {'name': 'plate', 'position': [2.613, 2.087], 'size': [0.537, 0.311, 0.001], 'colour': [60, 60, 60]}
    ]
    data['vision_systems'] = [
        {'name': 'vs1', 'position': [2.6, 2.0, 3.0], 'fov_deg': 60, 'resolution': [160, 120]}
    ]
    path = tmp_path / 'plate.yaml'
    path.write_text(yaml.safe_dump(data))
    world = load_world(path)
    camera = PinholeCamera.from_config(world.vision_systems[0])
    with Scene(world) as scene:
        frame = scene.render(camera)
    mask = parse_algorithm(world.colour_models['obstacle']).params.mask(frame.rgb) > 0
    corners = camera.project_3d_to_pixel([(x, y, 0.001) for x, y in world.objects[0].footprint()])
    (u_min, v_min), (u_max, v_max) = corners.min(axis=0), corners.max(axis=0)
    rows, cols = np.mgrid[0 : camera.height, 0 : camera.width]
    u = cols + 0.5 + TINY_RENDERER_SAMPLE[0]
    v = rows + 0.5 + TINY_RENDERER_SAMPLE[1]
    expected = (u >= u_min) & (u <= u_max) & (v >= v_min) & (v <= v_max)
    assert np.array_equal(mask, expected)


@pytest.mark.parametrize('name', ['tall', 'rotated', 'edge'])
def test_outlines_match_the_true_footprints_at_800x600(accuracy, name):
    world, frames = accuracy
    body = next(o for o in world.objects if o.name == name)
    truth = Polygon(body.footprint())
    outlines = locate_objects(frames['vs1'], parse_algorithm(world.colour_models['obstacle']), WHOLE_FLOOR)
    assert len(outlines) == 3
    found = match(outlines, truth)
    assert found.exterior.is_ccw
    assert found.centroid.distance(truth.centroid) <= 0.02
    assert iou(found, truth) >= 0.9


def test_an_object_partly_out_of_view_is_reported_as_the_part_seen(accuracy):
    world, frames = accuracy
    edge = Polygon(next(o for o in world.objects if o.name == 'edge').footprint())
    outlines = locate_objects(frames['vs2'], parse_algorithm(world.colour_models['obstacle']), WHOLE_FLOOR)
    seen = match(outlines, edge)
    assert 0.1 < seen.area / edge.area < 0.5  # vs2's image ends across the box
    assert edge.buffer(0.01).contains(seen)


def test_the_depth_buffer_puts_a_tall_box_where_it_stands(accuracy):
    """Without depth (every outline vertex on the floor plane) the 0.5 m box would be misplaced."""
    world, frames = accuracy
    frame = frames['vs1']
    tall = Polygon(next(o for o in world.objects if o.name == 'tall').footprint())
    model = parse_algorithm(world.colour_models['obstacle'])
    pixel_object = max(model.detect(frame), key=lambda o: o.area)
    flat = Polygon(frame.camera.pixel_to_floor(frame.to_camera(pixel_object.outline))[:, :2])
    assert flat.centroid.distance(tall.centroid) > 0.05
    assert iou(flat, tall) < 0.8
    assert match(locate_objects(frame, model, WHOLE_FLOOR), tall).centroid.distance(tall.centroid) <= 0.02


@pytest.mark.parametrize('name', ['tall', 'rotated'])
def test_two_cameras_that_see_an_object_agree(accuracy, name):
    world, frames = accuracy
    truth = Polygon(next(o for o in world.objects if o.name == name).footprint())
    model = parse_algorithm(world.colour_models['obstacle'])
    one, two = (match(locate_objects(frames[c], model, WHOLE_FLOOR), truth) for c in ('vs1', 'vs2'))
    assert one.centroid.distance(two.centroid) <= 0.02
    assert iou(one, two) >= 0.9


def test_only_objects_in_the_region_of_interest_are_reported_clipped_to_it(accuracy):
    world, frames = accuracy
    model = parse_algorithm(world.colour_models['obstacle'])
    region = (2.3, 0.0, 6.0, 4.0)  # half of `tall`, all of `rotated`, none of `edge`
    outlines = [Polygon(o) for o in locate_objects(frames['vs1'], model, region)]
    assert len(outlines) == 2
    for outline in outlines:
        assert box(*region).buffer(1e-9).contains(outline)
    half = box(2.3, 2.1, 2.5, 2.7)
    assert iou(match([list(o.exterior.coords) for o in outlines], half), half) >= 0.9
    assert locate_objects(frames['vs1'], model, (5.0, 3.0, 6.0, 4.0)) == []


def test_nothing_of_another_colour_is_reported(accuracy):
    world, frames = accuracy
    human = parse_algorithm(world.colour_models['human'])
    assert locate_objects(frames['vs1'], human, WHOLE_FLOOR) == []
    robot = locate_objects(frames['vs1'], parse_algorithm(world.colour_models['self']), WHOLE_FLOOR)
    assert len(robot) == 1
    assert Polygon(robot[0]).centroid.distance(Polygon(world.robot.footprint()).centroid) <= 0.02


def test_detections_are_drawn_where_they_are_seen(accuracy):
    world, frames = accuracy
    frame = frames['vs1']
    outline = [(2.1, 2.1), (2.5, 2.1), (2.5, 2.7), (2.1, 2.7)]
    image = draw_detections(frame, [outline])
    u, v = frame.camera.project_3d_to_pixel((2.1, 2.1, 0.0)) - np.asarray(TINY_RENDERER_SAMPLE)
    assert tuple(image[int(v), int(u)]) == (255, 0, 255)
    assert image.shape == frame.rgb.shape and not np.array_equal(image, frame.rgb)


def make_cache(max_age=0.1, render_time=0.0):
    clock = {'now': 100.0}
    camera = PinholeCamera(eye=(0, 0, 1), target=(0, 0, 0), fov_deg=60, width=16, height=12)
    gate = threading.Event()

    def capture(stamp):
        gate.wait(5.0)  # hold the first render until every request has arrived
        clock['now'] += render_time
        return Frame(np.zeros((12, 16, 3), np.uint8), np.ones((12, 16), np.float32), camera, stamp)

    return FrameCache(capture, max_age, clock=lambda: clock['now']), clock, gate


def test_ten_simultaneous_requests_cost_one_render():
    cache, clock, gate = make_cache()
    results = []
    threads = [threading.Thread(target=lambda: results.append(cache.get(clock['now']))) for _ in range(10)]
    for thread in threads:
        thread.start()
    gate.set()
    for thread in threads:
        thread.join(5.0)
    assert len(results) == 10 and len({id(frame) for frame, _ in results}) == 1
    assert (cache.renders, cache.hits) == (1, 9)


@pytest.mark.parametrize('later, renders', [(0.05, 1), (0.1, 1), (0.15, 2)])
@pytest.mark.parametrize('render_time', [0.0, 0.3])
def test_a_frame_is_reused_within_max_frame_age_of_its_capture(later, renders, render_time):
    """Age counts from the end of the capture: a request seen only after a slow render reuses it."""
    cache, clock, gate = make_cache(max_age=0.1, render_time=render_time)
    gate.set()
    first, reused = cache.get(clock['now'])
    assert not reused and first.stamp == 100.0  # stamped with the capture's start
    clock['now'] += later
    second, _ = cache.get(clock['now'])
    assert cache.renders == renders
    assert second.stamp == pytest.approx(100.0 if renders == 1 else 100.0 + render_time + later)


def test_the_algorithms_confidence_reaches_every_object_a_request_gets_clipped_or_not():
    camera = PinholeCamera(eye=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0), fov_deg=60, width=400, height=300)
    frame = Frame(rgb=np.zeros((300, 400, 3), np.uint8), depth=None, camera=camera, stamp=0.0)
    square = np.array([(150.0, 100.0), (250.0, 100.0), (250.0, 200.0), (150.0, 200.0)])
    pixel_objects = [
        PixelObject(square, 1e4, confidence=0.6),
        PixelObject(square + 10, 1e4, label='tag36h11:1', height=0.0, keep_order=True, confidence=0.9),
        PixelObject(square - 10, 1e4),  # an algorithm that does not say
    ]
    objects = project_objects(frame, pixel_objects)
    assert [o.confidence for o in objects] == [0.6, 0.9, 0.0]
    whole = in_region(objects, (-5.0, -5.0, 5.0, 5.0))
    assert [(o.label, o.confidence) for o in whole] == [('', 0.6), ('tag36h11:1', 0.9), ('', 0.0)]
    min_x, min_y, max_x, max_y = objects[0].bounds
    clipped = in_region(objects, (-5.0, -5.0, (min_x + max_x) / 2, 5.0))  # half of each
    assert [(o.label, o.confidence) for o in clipped] == [('', 0.6), ('tag36h11:1', 0.9), ('', 0.0)]
    assert Polygon(clipped[0].outline).area == pytest.approx(objects[0].shape.area / 2)
