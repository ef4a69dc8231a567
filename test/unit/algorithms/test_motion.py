"""``motion[:MIN_AREA]``: parsing, background subtraction on drawn frames, and a walking human rendered."""

import doctest
import threading
from collections import namedtuple

import cv2
import numpy as np
import pytest
import yaml
from shapely.geometry import Point, Polygon, box

import drvs.algorithms.motion
from drvs.algorithms import AlgorithmError, AlgorithmSet, builtin_algorithms, parse_algorithm
from drvs.algorithms.motion import DEFAULT_MIN_AREA, WARM_UP, Motion, MotionParams
from drvs.sim.scene import Scene
from drvs.sim.simulation import loop_of, position_on_loop
from drvs.sim.world_file import load_world
from drvs.vision.camera import PinholeCamera
from drvs.vision.frame import Frame
from drvs.vision.pipeline import locate_objects

# -- parameters ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    'text, min_area',
    [
        ('motion', DEFAULT_MIN_AREA),
        ('motion:', DEFAULT_MIN_AREA),
        ('motion:250', 250.0),
        ('motion: 12.5 ', 12.5),
    ],
)
def test_min_area_is_optional_and_any_positive_number(text, min_area):
    parsed = parse_algorithm(text)
    assert parsed.name == 'motion'
    assert parsed.params == MotionParams(min_area)


@pytest.mark.parametrize(
    'text, message',
    [
        ('motion:x', "algorithm: motion MIN_AREA must be a positive number of pixels, got 'x'"),
        ('motion:0', "algorithm: motion MIN_AREA must be a positive number of pixels, got '0'"),
        ('motion:-5', "algorithm: motion MIN_AREA must be a positive number of pixels, got '-5'"),
        ('motion:nan', "algorithm: motion MIN_AREA must be a positive number of pixels, got 'nan'"),
        ('motion:inf', "algorithm: motion MIN_AREA must be a positive number of pixels, got 'inf'"),
        ('motion:100:3', "algorithm: motion takes one optional field MIN_AREA, got '100:3'"),
        ('motion:100,3', "algorithm: motion takes one optional field MIN_AREA, got '100,3'"),
    ],
)
def test_bad_parameters_are_refused_naming_the_problem(text, message):
    with pytest.raises(AlgorithmError) as raised:
        parse_algorithm(text)
    assert str(raised.value) == message


def test_doctests():
    result = doctest.testmod(drvs.algorithms.motion)
    assert result.failed == 0 and result.attempted > 0


def test_motion_is_a_streaming_builtin_with_the_outline_tolerance_given():
    motion = next(a for a in builtin_algorithms(epsilon=2.5) if a.name == 'motion')
    assert isinstance(motion, Motion)
    assert motion.streaming and motion.epsilon == 2.5
    assert motion.syntax == 'motion[:MIN_AREA]'
    assert MotionParams(250.0).format() == 'motion:250'


# -- drawn frames (400x300) --------------------------------------------------------------------------

WIDTH, HEIGHT = 400, 300
RECT = (40, 30)  # width, height of the moving rectangle, pixels
STEP = 8  # pixels per frame
Background = namedtuple('Background', 'name image noise')


def backgrounds():
    rng = np.random.default_rng(7)
    flat = np.full((HEIGHT, WIDTH, 3), (200, 200, 190), np.uint8)
    # Tiles of random colours 20 px wide: a floor with texture but no noise.
    tiles = rng.integers(40, 220, size=(HEIGHT // 20 + 1, WIDTH // 20 + 1, 3), dtype=np.uint8)
    textured = np.repeat(np.repeat(tiles, 20, axis=0), 20, axis=1)[:HEIGHT, :WIDTH].copy()
    return [
        Background('flat', flat, 0.0),
        Background('textured', textured, 0.0),
        Background('noisy', flat, 2.0),
    ]


BACKGROUNDS = backgrounds()


def drawn(background: Background, rects=(), stamp=0.0, seed=0, colour=(30, 60, 160)) -> Frame:
    """A frame of ``background`` with filled rectangles (u, v, width, height) drawn on it."""
    image = background.image.copy()
    for u, v, w, h in rects:
        cv2.rectangle(image, (u, v), (u + w - 1, v + h - 1), colour, thickness=-1)
    if background.noise:
        noise = np.random.default_rng(seed).normal(0.0, background.noise, image.shape)
        image = np.clip(image + noise, 0, 255).astype(np.uint8)
    return Frame(rgb=image, depth=None, camera=None, stamp=stamp)


def rect_at(i):
    return (60 + STEP * i, 120, *RECT)


def pixel_iou(outline, rect):
    u, v, w, h = rect
    found = Polygon(outline)
    truth = box(u, v, u + w, v + h)
    return found.intersection(truth).area / found.union(truth).area


def learnt(motion, background, frames=10):
    """``motion`` after ``frames`` frames of ``background`` alone; the next stamp."""
    for i in range(frames):
        motion.observe(drawn(background, stamp=i * 0.2, seed=i))
    return frames


@pytest.mark.parametrize('background', BACKGROUNDS, ids=lambda b: b.name)
def test_a_moving_rectangle_is_found_where_it_is_drawn(background):
    motion = Motion()
    start = learnt(motion, background)
    for i in range(12):
        frame = drawn(background, [rect_at(i)], stamp=(start + i) * 0.2, seed=start + i)
        motion.observe(frame)
        found = motion.detect(frame, MotionParams())
        assert len(found) == 1, f'frame {i}'
        assert pixel_iou(found[0].outline, rect_at(i)) >= 0.8, f'frame {i}'
        assert found[0].label == '' and found[0].height is None


@pytest.mark.parametrize('background', BACKGROUNDS, ids=lambda b: b.name)
def test_nothing_is_found_while_nothing_moves(background):
    motion = Motion()
    still = [(150, 100, 50, 40)]  # a rectangle that stands still from the first frame on
    for i in range(25):
        frame = drawn(background, still, stamp=i * 0.2, seed=i)
        motion.observe(frame)
        assert motion.detect(frame, MotionParams(20)) == [], f'frame {i}'


def test_nothing_is_reported_before_the_warm_up():
    """The first frames would be all 'moving' to an empty model: they report nothing."""
    motion = Motion()
    background = BACKGROUNDS[0]
    for i in range(WARM_UP):
        frame = drawn(background, [rect_at(5 * i)], stamp=i * 0.2)  # a rectangle's width a frame
        assert motion.detect(frame, MotionParams()) == []  # not observed: not learnt either
        assert motion.frames_observed == i
        motion.observe(frame)
        if i < WARM_UP - 1:
            assert motion.detect(frame, MotionParams()) == []
    found = motion.detect(frame, MotionParams())  # warmed up: where the rectangle is now
    assert len(found) == 1 and pixel_iou(found[0].outline, rect_at(5 * (WARM_UP - 1))) >= 0.8


def test_a_frame_observed_twice_is_learnt_once():
    background = BACKGROUNDS[2]
    once, twice = Motion(), Motion()
    for i in range(20):
        rects = [rect_at(i - 10)] if i >= 10 else []
        frame = drawn(background, rects, stamp=i * 0.2, seed=i)
        once.observe(frame)
        twice.observe(frame)
        twice.observe(frame)
        assert twice.frames_observed == once.frames_observed == i + 1
        for a, b in zip(once.detect(frame, MotionParams()), twice.detect(frame, MotionParams()), strict=True):
            assert np.array_equal(a.outline, b.outline)
    # The same stamp with another image is another frame.
    twice.observe(drawn(background, stamp=19 * 0.2, seed=99))
    assert twice.frames_observed == 21


def test_a_frame_never_observed_is_judged_without_learning_from_it():
    """A rectangle that stops stays 'moving' however often an unobserved frame of it is judged."""
    motion = Motion()
    background = BACKGROUNDS[0]
    start = learnt(motion, background)
    stopped = drawn(background, [rect_at(0)], stamp=start * 0.2)
    for _ in range(40):
        found = motion.detect(stopped, MotionParams())
        assert len(found) == 1 and pixel_iou(found[0].outline, rect_at(0)) >= 0.8
    assert motion.frames_observed == start


def test_min_area_leaves_out_smaller_moving_regions():
    motion = Motion()
    background = BACKGROUNDS[1]
    start = learnt(motion, background)
    frame = drawn(background, [(100, 100, 8, 8), (250, 150, 30, 30)], stamp=start * 0.2)
    motion.observe(frame)
    assert sorted(o.area for o in motion.detect(frame, MotionParams(50))) == [64.0, 900.0]
    assert [o.area for o in motion.detect(frame, MotionParams(100))] == [900.0]


def ghost_frames(background):
    """Frames after a rectangle that stood 10 frames left the view in which its old place is reported."""
    motion = Motion()
    old = (100, 100, 50, 40)
    for i in range(10):
        motion.observe(drawn(background, [old], stamp=i * 0.2, seed=i))
    haunted = []
    for i in range(10, 40):
        frame = drawn(background, stamp=i * 0.2, seed=i)
        motion.observe(frame)
        found = motion.detect(frame, MotionParams())
        assert all(pixel_iou(o.outline, old) >= 0.5 for o in found), f'frame {i}'  # only its ghost
        if found:
            haunted.append(i - 10)
    return haunted


@pytest.mark.parametrize('background', BACKGROUNDS, ids=lambda b: b.name)
def test_the_ghost_of_something_that_left_is_short(background):
    """On a plain floor the spot left is recognised as floor at once; on texture it fades in ~14 frames."""
    haunted = ghost_frames(background)
    if background.name == 'textured':
        assert haunted == list(range(len(haunted))) and 12 <= len(haunted) <= 15
    else:
        assert haunted == []


def test_a_new_image_size_starts_a_new_model():
    motion = Motion()
    learnt(motion, BACKGROUNDS[0])
    small = Frame(np.zeros((120, 160, 3), np.uint8), None, None, 5.0)
    assert motion.detect(small, MotionParams()) == []  # not the model's size: not judged
    motion.observe(small)
    assert motion.frames_observed == 1
    motion.reset()
    assert motion.frames_observed == 0


def test_observe_and_detect_from_two_threads():
    motion = Motion()
    background = BACKGROUNDS[2]
    frames = [drawn(background, [rect_at(i % 20)] if i > 10 else [], i * 0.2, i) for i in range(60)]
    errors = []

    def feed():
        for frame in frames:
            motion.observe(frame)

    def ask():
        try:
            for frame in frames[20:]:
                for pixel_object in motion.detect(frame, MotionParams()):
                    assert pixel_object.area >= DEFAULT_MIN_AREA
        except Exception as error:  # any failure in this thread, asserted in the main one
            errors.append(error)

    threads = [threading.Thread(target=feed), threading.Thread(target=ask)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30.0)
    assert errors == [] and motion.frames_observed == 60


# -- a walking human rendered at 800x600 -----------------------------------------------------------

RATE = 5.0  # frames per second of simulated time
STANDING = 10  # frames the human stands at the start of its loop before walking (requests start then)
FRAMES = 40
GHOST_LIMIT = 5  # frames after the human starts walking by which its ghost is gone
WORLD = {
    'floor': {'size': [4.0, 3.0], 'colour': [255, 255, 255]},
    'robot': {'position': [0.2, 1.5], 'size': [0.3, 0.3, 0.2], 'colour': [0, 200, 0], 'speed': 0.5},
    'station': {'position': [3.75, 1.5], 'size': [0.4, 0.3, 0.1], 'colour': [0, 0, 220]},
    'objects': [
        {
            'name': 'walker',
            'kind': 'human',
            'position': [1.5, 1.1],
            'size': [0.3, 0.3, 1.7],
            'colour': [220, 0, 0],
            # Its 1.7 m top stays in view all the way round from 3 m up.
            'waypoints': [[2.5, 1.1], [2.5, 1.9], [1.5, 1.9]],
            'speed': 0.5,
        }
    ],
    'vision_systems': [{'name': 'vs1', 'position': [2.0, 1.5, 3.0], 'fov_deg': 60, 'resolution': [800, 600]}],
    'colour_models': {
        'self': 'colour:0,150,0,80,255,80',
        'station': 'colour:0,0,150,80,80,255',
        'obstacle': 'colour:40,40,40,90,90,90',
        'human': 'colour:150,0,0,255,80,80',
    },
}
WHOLE_FLOOR = (0.0, 0.0, 4.0, 3.0)


@pytest.fixture(scope='module')
def walk(tmp_path_factory):
    """[(true footprint centre, outlines motion reports)] for each frame of the stream at 5 Hz.

    The human stands for the first STANDING frames (it becomes background), then walks
    its loop at 0.5 m/s; every frame is observed, then judged as a request would be.
    """
    path = tmp_path_factory.mktemp('motion') / 'walk.yaml'
    path.write_text(yaml.safe_dump(WORLD))
    world = load_world(path)
    human = world.objects[0]
    loop = loop_of(human.position, human.waypoints)
    camera = PinholeCamera.from_config(world.vision_systems[0])
    motion = parse_algorithm('motion', AlgorithmSet([Motion()]))  # one instance per camera
    results = []
    with Scene(world) as scene:
        for i in range(FRAMES):
            x, y = position_on_loop(loop, human.speed, max(i - STANDING, 0) / RATE)
            scene.set_pose(human.name, x, y, 0.0)
            frame = scene.render(camera, stamp=i / RATE)
            motion.algorithm.observe(frame)
            results.append(((x, y), [Polygon(o) for o in locate_objects(frame, motion, WHOLE_FLOOR)]))
    return results


def test_a_human_standing_since_the_stream_began_is_not_reported(walk):
    assert [len(found) for _, found in walk[: STANDING + 1]] == [0] * (STANDING + 1)


def test_the_ghost_of_where_the_human_stood_is_gone_within_a_second(walk):
    counts = [len(found) for _, found in walk[STANDING + 1 :]]
    assert max(counts[:GHOST_LIMIT]) >= 1  # it moves: something is reported at once
    assert counts[GHOST_LIMIT - 1 :] == [1] * (len(counts) - GHOST_LIMIT + 1)


def test_a_walking_human_is_reported_within_5cm_of_its_footprint_centre(walk):
    errors = []
    for truth, found in walk[STANDING + GHOST_LIMIT :]:
        nearest = min(found, key=lambda outline: outline.centroid.distance(Point(truth)))
        errors.append(nearest.centroid.distance(Point(truth)))
        assert nearest.area == pytest.approx(0.09, abs=0.01)  # its 0.3 x 0.3 m footprint
    assert max(errors) <= 0.05, errors


# -- confidence: the share of a region's pixels the model found changed ----------------------------


def test_a_solid_moving_rectangle_has_confidence_1_and_a_speckled_one_less():
    """Speckled: a tenth of the rectangle's pixels show the floor; the cleaning fills the holes."""
    background = BACKGROUNDS[1]
    solid, speckled = Motion(), Motion()
    start = learnt(solid, background)
    learnt(speckled, background)
    holes = np.random.default_rng(3).random(RECT[::-1]) < 0.1
    for i in range(4):
        frame = drawn(background, [rect_at(i)], stamp=(start + i) * 0.2)
        solid.observe(frame)
        (found,) = solid.detect(frame, MotionParams())
        assert found.confidence == 1.0, f'frame {i}'
        u, v, w, h = rect_at(i)
        rgb = frame.rgb.copy()
        rgb[v : v + h, u : u + w][holes] = background.image[v : v + h, u : u + w][holes]
        frame = Frame(rgb=rgb, depth=None, camera=None, stamp=frame.stamp)
        speckled.observe(frame)
        (found,) = speckled.detect(frame, MotionParams())
        assert 0.8 <= found.confidence <= 0.97, f'frame {i}'
