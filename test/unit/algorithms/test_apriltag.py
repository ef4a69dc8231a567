"""The apriltag algorithm: parsing, detection on drawn and rendered frames, and tags in world files."""

import doctest
import math
import threading

import cv2
import numpy as np
import pytest
import yaml

import drvs.algorithms.apriltag
import drvs.algorithms.tag_images
from drvs.algorithms import AlgorithmError, AlgorithmSet, parse_algorithm
from drvs.algorithms.apriltag import AprilTag, TagQuery, decision_margin, tag_pose
from drvs.algorithms.tag_images import FAMILIES, cells, dictionary, tag_image
from drvs.sim.scene import Scene
from drvs.sim.world import Tag, WorldError
from drvs.sim.world_file import load_world
from drvs.vision.camera import PinholeCamera
from drvs.vision.frame import Frame
from drvs.vision.optics import CameraModel
from drvs.vision.pipeline import locate_labelled

ALGORITHMS = AlgorithmSet([AprilTag()])


def parse(text):
    return parse_algorithm(text, ALGORITHMS)


# -- parsing -----------------------------------------------------------------------------------
@pytest.mark.parametrize(
    'text, query',
    [
        ('apriltag:tag36h11', TagQuery('tag36h11')),
        ('apriltag:tag16h5:0,29', TagQuery('tag16h5', (0, 29))),
        ('apriltag:tag25h9:34', TagQuery('tag25h9', (34,))),
        ('apriltag:tag36h10:2319,7:h=0.25', TagQuery('tag36h10', (2319, 7), 0.25)),
        ('apriltag:tag36h11:h=0', TagQuery('tag36h11', (), 0.0)),
        ('apriltag:tag36h11:h=1e-1', TagQuery('tag36h11', (), 0.1)),
        ('apriltag: tag36h11 : 3 , 4 : h = 0.2', TagQuery('tag36h11', (3, 4), 0.2)),
    ],
)
def test_valid_requests_parse(text, query):
    parsed = parse(text)
    assert parsed.name == 'apriltag'
    assert parsed.params == query
    assert parse(parsed.params.format()).params == query


def test_the_query_formats_as_its_algorithm_string():
    assert parse('apriltag:tag36h11:3,7:h=0.2').params.format() == 'apriltag:tag36h11:3,7:h=0.2'
    assert str(parse('apriltag:tag16h5').params) == 'apriltag:tag16h5'


NEEDS_FAMILY = (
    'algorithm: apriltag needs a FAMILY: apriltag:FAMILY[:ID,ID,...][:h=HEIGHT], e.g. apriltag:tag36h11'
)
ORDER = 'algorithm: apriltag PARAMS must be FAMILY[:ID,ID,...][:h=HEIGHT] in that order, got {!r}'


@pytest.mark.parametrize(
    'text, message',
    [
        ('apriltag', NEEDS_FAMILY),
        ('apriltag:', NEEDS_FAMILY),
        ('apriltag: ', NEEDS_FAMILY),
        (
            'apriltag:tag99',
            "algorithm: apriltag FAMILY must be one of tag16h5, tag25h9, tag36h10, tag36h11, got 'tag99'",
        ),
        (
            'apriltag:36h11:3',
            "algorithm: apriltag FAMILY must be one of tag16h5, tag25h9, tag36h10, tag36h11, got '36h11'",
        ),
        (
            'apriltag:tag36h11:587',
            "algorithm: apriltag ID must be an integer 0-586 (an id of tag36h11), got '587'",
        ),
        (
            'apriltag:tag16h5:30',
            "algorithm: apriltag ID must be an integer 0-29 (an id of tag16h5), got '30'",
        ),
        (
            'apriltag:tag36h11:x',
            "algorithm: apriltag ID must be an integer 0-586 (an id of tag36h11), got 'x'",
        ),
        (
            'apriltag:tag36h11:-1',
            "algorithm: apriltag ID must be an integer 0-586 (an id of tag36h11), got '-1'",
        ),
        (
            'apriltag:tag36h11:1_0',
            "algorithm: apriltag ID must be an integer 0-586 (an id of tag36h11), got '1_0'",
        ),
        (
            'apriltag:tag36h11:3,',
            "algorithm: apriltag ID must be an integer 0-586 (an id of tag36h11), got ''",
        ),
        ('apriltag:tag36h11:', "algorithm: apriltag ID must be an integer 0-586 (an id of tag36h11), got ''"),
        ('apriltag:tag36h11:3,4,3', 'algorithm: apriltag ID 3 is given twice'),
        ('apriltag:tag36h11:h=-1', "algorithm: apriltag h must be a finite number >= 0 (metres), got '-1'"),
        ('apriltag:tag36h11:h=nan', "algorithm: apriltag h must be a finite number >= 0 (metres), got 'nan'"),
        ('apriltag:tag36h11:h=inf', "algorithm: apriltag h must be a finite number >= 0 (metres), got 'inf'"),
        ('apriltag:tag36h11:h=', "algorithm: apriltag h must be a finite number >= 0 (metres), got ''"),
        (
            'apriltag:tag36h11:3:h=abc',
            "algorithm: apriltag h must be a finite number >= 0 (metres), got 'abc'",
        ),
        ('apriltag:tag36h11:h=1_0', "algorithm: apriltag h must be a finite number >= 0 (metres), got '1_0'"),
        ('apriltag:tag36h11:h=0.2:3', ORDER.format('tag36h11:h=0.2:3')),
        ('apriltag:tag36h11:3:4', ORDER.format('tag36h11:3:4')),
        ('apriltag:tag36h11:h=1:h=2', ORDER.format('tag36h11:h=1:h=2')),
        (
            'apriltag:tag36h11:3:h=0:x',
            'algorithm: apriltag takes at most 3 fields FAMILY:ID,ID,...:h=HEIGHT, '
            "got 4 in 'tag36h11:3:h=0:x'",
        ),
    ],
)
def test_bad_requests_are_refused_naming_the_part(text, message):
    with pytest.raises(AlgorithmError) as error:
        parse(text)
    assert str(error.value) == message


@pytest.mark.parametrize(
    'kwargs, message',
    [
        (
            {'default_height': -0.1},
            'AprilTag: default_height: expected a finite number of metres >= 0, got -0.1',
        ),
        (
            {'default_height': True},
            'AprilTag: default_height: expected a finite number of metres >= 0, got True',
        ),
        (
            {'heights': {'tag36h11:3': math.nan}},
            "AprilTag: heights['tag36h11:3']: expected a finite number of metres >= 0, got nan",
        ),
    ],
)
def test_bad_heights_are_refused(kwargs, message):
    with pytest.raises(ValueError) as error:
        AprilTag(**kwargs)
    assert str(error.value) == message


@pytest.mark.parametrize('module', [drvs.algorithms.apriltag, drvs.algorithms.tag_images])
def test_doctests(module):
    result = doctest.testmod(module)
    assert result.attempted > 0 and result.failed == 0


def test_the_family_table_matches_opencv():
    for name, family in FAMILIES.items():
        aruco = dictionary(name)
        assert (aruco.markerSize, aruco.bytesList.shape[0]) == (family.bits, family.ids)


# -- drawn frames ------------------------------------------------------------------------------
WIDTH, HEIGHT = 400, 300
SUPERSAMPLE = 4


def square(centre, half, angle, stretch=0.0) -> np.ndarray:
    """The black square's corners in the image (DRVS coordinates, v down), in the outline's order
    (printed top-left, bottom-left, bottom-right, top-right), the tag turned ``angle`` radians
    anticlockwise on screen; ``stretch`` pulls the right side apart (a perspective view)."""
    right = np.array([math.cos(angle), -math.sin(angle)])
    up = np.array([-math.sin(angle), -math.cos(angle)])
    c = np.asarray(centre, float)
    return np.array(
        [
            c - half * right + half * up,
            c - half * right - half * up,
            c + half * right - half * up * (1 + stretch),
            c + half * right + half * up * (1 + stretch),
        ]
    )


def drawn_frame(tags, camera=None) -> Frame:
    """A white frame with each (family, id, corners) warped so its black square's corners are
    ``corners`` (outline order, DRVS coordinates); drawn large and averaged down, as a camera would."""
    big = np.full((HEIGHT * SUPERSAMPLE, WIDTH * SUPERSAMPLE), 255, np.uint8)
    for family, tag_id, corners in tags:
        image = tag_image(family, tag_id, cell_pixels=16)
        n, cell = image.shape[0], 16
        source = np.array([[cell, cell], [cell, n - cell], [n - cell, n - cell], [n - cell, cell]], float)
        target = np.asarray(corners, float) * SUPERSAMPLE
        # OpenCV maps pixel centres: its coordinates are the corner coordinates - 0.5.
        homography = cv2.getPerspectiveTransform(
            (source - 0.5).astype(np.float32), (target - 0.5).astype(np.float32)
        )
        warped = cv2.warpPerspective(
            image, homography, big.shape[::-1], flags=cv2.INTER_LINEAR, borderValue=255
        )
        big = np.minimum(big, warped)
    grey = cv2.resize(big, (WIDTH, HEIGHT), interpolation=cv2.INTER_AREA)
    if camera is None:
        camera = PinholeCamera(
            eye=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0), fov_deg=60, width=WIDTH, height=HEIGHT
        )
    return Frame(rgb=np.dstack([grey] * 3), depth=None, camera=camera, stamp=0.0)


TAG_3 = square((110, 120), 40, math.radians(30), stretch=0.08)
TAG_7 = square((300, 90), 35, math.radians(-100))
TAG_25H9_2 = square((280, 220), 35, math.radians(10))
CORNER_TOLERANCE = 0.1  # pixels


@pytest.fixture(scope='module')
def drawn():
    return drawn_frame([('tag36h11', 3, TAG_3), ('tag36h11', 7, TAG_7), ('tag25h9', 2, TAG_25H9_2)])


def by_label(found):
    return {obj.label: obj for obj in found}


def test_tags_are_found_with_their_corners_in_the_documented_order(drawn):
    found = by_label(parse('apriltag:tag36h11').detect(drawn))
    assert sorted(found) == ['tag36h11:3', 'tag36h11:7']
    for label, corners in (('tag36h11:3', TAG_3), ('tag36h11:7', TAG_7)):
        tag = found[label]
        assert tag.keep_order
        assert tag.height == 0.0
        assert tag.outline.shape == (4, 2)
        assert np.max(np.abs(tag.outline - corners)) <= CORNER_TOLERANCE, (label, tag.outline - corners)
        x, y = corners[:, 0], corners[:, 1]
        area = abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) / 2
        assert tag.area == pytest.approx(area, rel=0.01)


def test_an_ids_list_keeps_only_those_tags(drawn):
    assert [obj.label for obj in parse('apriltag:tag36h11:7').detect(drawn)] == ['tag36h11:7']
    assert sorted(obj.label for obj in parse('apriltag:tag36h11:7,3,100').detect(drawn)) == [
        'tag36h11:3',
        'tag36h11:7',
    ]
    assert parse('apriltag:tag36h11:100').detect(drawn) == []


def test_another_family_is_not_reported(drawn):
    found = parse('apriltag:tag25h9').detect(drawn)
    assert [obj.label for obj in found] == ['tag25h9:2']
    assert np.max(np.abs(found[0].outline - TAG_25H9_2)) <= CORNER_TOLERANCE
    assert parse('apriltag:tag36h10').detect(drawn) == []


def test_a_frame_without_tags_gives_nothing():
    frame = drawn_frame([])
    rgb = frame.rgb.copy()
    cv2.rectangle(rgb, (50, 50), (150, 150), (0, 0, 0), -1)  # a black square is no tag
    cv2.rectangle(rgb, (200, 60), (300, 160), (0, 0, 0), 3)
    blank = Frame(rgb=rgb, depth=None, camera=frame.camera, stamp=0.0)
    for family in FAMILIES:
        assert parse(f'apriltag:{family}').detect(blank) == []


def test_heights_come_from_the_request_then_the_instance_then_the_default(drawn):
    algorithms = AlgorithmSet([AprilTag(default_height=0.05, heights={'tag36h11:3': 0.2})])
    found = by_label(parse_algorithm('apriltag:tag36h11', algorithms).detect(drawn))
    assert (found['tag36h11:3'].height, found['tag36h11:7'].height) == (0.2, 0.05)
    found = by_label(parse_algorithm('apriltag:tag36h11:h=0.3', algorithms).detect(drawn))
    assert (found['tag36h11:3'].height, found['tag36h11:7'].height) == (0.3, 0.3)


def test_a_camera_model_frame_gives_the_same_corners(drawn):
    model = CameraModel.from_pinhole(drawn.camera)
    frame = Frame(rgb=drawn.rgb, depth=None, camera=model, stamp=0.0)
    expected = by_label(parse('apriltag:tag36h11').detect(drawn))
    found = by_label(parse('apriltag:tag36h11').detect(frame))
    assert sorted(found) == sorted(expected)
    for label, tag in found.items():
        assert np.allclose(tag.outline, expected[label].outline, atol=1e-6)


def test_two_threads_may_detect_at_once(drawn):
    parsed = parse('apriltag:tag36h11')
    expected = by_label(parsed.detect(drawn))
    results, errors = [], []

    def work():
        try:
            for _ in range(5):
                results.append(by_label(parsed.detect(drawn)))
        except Exception as error:  # reported below, on the test's thread
            errors.append(error)

    threads = [threading.Thread(target=work) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == []
    assert len(results) == 10
    for result in results:
        assert sorted(result) == sorted(expected)
        for label, tag in result.items():
            assert np.array_equal(tag.outline, expected[label].outline)


@pytest.mark.parametrize('yaw', [0.0, 0.5, -2.0, math.pi])
def test_tag_pose_gives_the_centre_and_the_printed_right(yaw):
    c, s = math.cos(yaw), math.sin(yaw)
    local = [(-0.1, 0.1), (-0.1, -0.1), (0.1, -0.1), (0.1, 0.1)]  # TL, BL, BR, TR at yaw 0
    corners = [(1.5 + c * x - s * y, 2.0 + s * x + c * y, 0.2) for x, y in local]
    x, y, found = tag_pose(corners)
    assert (x, y) == pytest.approx((1.5, 2.0), abs=1e-12)
    assert math.remainder(found - yaw, 2 * math.pi) == pytest.approx(0.0, abs=1e-12)


def test_tag_pose_uses_the_diagonals_not_the_mean():
    # A perspective-like quad: the diagonals cross at (1, 1); the corners' mean is elsewhere.
    x, y, yaw = tag_pose([(0.0, 2.0), (0.0, 0.0), (2.0, 0.0), (4.0, 4.0)])
    assert (x, y) == pytest.approx((1.0, 1.0))
    with pytest.raises(ValueError, match=r'tag_pose: expected 4 corners \(x, y\), got shape \(3, 2\)'):
        tag_pose([(0, 0), (1, 0), (1, 1)])


def test_the_tag_image_has_a_one_cell_quiet_zone():
    image = tag_image('tag36h11', 0, cell_pixels=4)
    assert image.shape == ((cells('tag36h11') + 2) * 4,) * 2
    assert (image[:4] == 255).all() and (image[:, :4] == 255).all()
    assert (image[4:8, 4:-4] == 0).all()  # the black border


# -- rendered world ----------------------------------------------------------------------------
ROBOT = {'position': [1.7, 1.3], 'size': [0.3, 0.3, 0.2], 'yaw': 0.5, 'colour': [0, 200, 0], 'speed': 0.5}
STATION = {'position': [2.6, 1.9], 'size': [0.4, 0.3, 0.1], 'yaw': -0.3, 'colour': [0, 0, 220]}


def world_data(**changes):
    data = {
        'floor': {'size': [4.0, 3.0], 'colour': [255, 255, 255]},
        'robot': {**ROBOT, 'tag': {'family': 'tag36h11', 'id': 3, 'size': 0.2}},
        'station': {**STATION, 'tag': {'family': 'tag36h11', 'id': 5, 'size': 0.2}},
        'objects': [
            {'name': 'crate', 'position': [0.6, 0.6], 'size': [0.4, 0.4, 0.5], 'colour': [60, 60, 60]}
        ],
        'vision_systems': [{'name': 'vs1', 'position': [2.0, 1.5, 3.0], 'fov_deg': 60}],
        'colour_models': {
            'self': 'colour:0,150,0,80,255,80',
            'station': 'colour:0,0,150,80,80,255',
            'obstacle': 'colour:40,40,40,90,90,90',
            'human': 'colour:150,0,0,255,80,80',
        },
    }
    for key, value in changes.items():
        where, _, name = key.rpartition('.')
        target = data
        for part in where.split('.') if where else []:
            target = target[int(part)] if part.isdigit() else target[part]
        if value is None:
            del target[name]
        else:
            target[name] = value
    return data


def write_world(folder, data):
    path = folder / 'world.yaml'
    path.write_text(yaml.safe_dump(data))
    return path


REGION = (0.0, 0.0, 4.0, 3.0)
TILT = math.radians(20)
VIEWS = {
    # camera 3 m up; the robot where the world puts it, then moved (the tag moves with it)
    'straight down': (PinholeCamera((2.0, 1.5, 3.0), (2.0, 1.5, 0.0), 60, 800, 600), (1.7, 1.3, 0.5)),
    'tilted 20 degrees': (
        PinholeCamera((2.0, 1.5 - 3.0 * math.tan(TILT), 3.0), (2.0, 1.5, 0.0), 60, 800, 600),
        (1.45, 1.1, 0.5),
    ),
}


@pytest.fixture(scope='module')
def rendered(tmp_path_factory):
    """The world, and per view: (frame, the robot's true pose)."""
    world = load_world(write_world(tmp_path_factory.mktemp('apriltag'), world_data()))
    frames = {}
    scene = Scene(world)
    try:
        folder = scene.texture_folder
        assert folder is not None and folder.is_dir()
        for name, (camera, pose) in VIEWS.items():
            scene.set_pose('robot', *pose)
            frames[name] = (scene.render(camera), pose)
    finally:
        scene.close()
    assert not folder.exists()
    return world, frames


def pose_errors(found, label, truth):
    (outline,) = [item.outline for item in found if item.label == label]
    assert len(outline) == 4
    x, y, yaw = tag_pose(outline)
    return math.hypot(x - truth[0], y - truth[1]), abs(
        math.degrees(math.remainder(yaw - truth[2], 2 * math.pi))
    )


@pytest.mark.parametrize('view', list(VIEWS))
def test_a_rendered_tag_gives_the_robot_pose_within_1_cm_and_2_degrees(rendered, view):
    world, frames = rendered
    frame, truth = frames[view]
    heights = {world.robot.tag.label: world.robot.size[2], world.station.tag.label: world.station.size[2]}
    algorithms = AlgorithmSet([AprilTag(heights=heights)])
    found = locate_labelled(frame, parse_algorithm('apriltag:tag36h11:3', algorithms), REGION)
    assert [item.label for item in found] == ['tag36h11:3']
    distance, heading = pose_errors(found, 'tag36h11:3', truth)
    assert distance <= 0.01 and heading <= 2.0, (distance, heading)
    # The station's tag too, at its own height and yaw.
    found = locate_labelled(frame, parse_algorithm('apriltag:tag36h11', algorithms), REGION)
    assert sorted(item.label for item in found) == ['tag36h11:3', 'tag36h11:5']
    assert all(0.95 <= item.confidence <= 1.0 for item in found)  # sharp renders: clear cells
    distance, heading = pose_errors(found, 'tag36h11:5', (*STATION['position'], STATION['yaw']))
    assert distance <= 0.01 and heading <= 2.0, (distance, heading)


@pytest.mark.parametrize('view', list(VIEWS))
def test_without_the_tag_height_the_position_is_off(rendered, view):
    frame, truth = rendered[1][view]
    found = locate_labelled(frame, parse('apriltag:tag36h11:3:h=0'), REGION)
    distance, _ = pose_errors(found, 'tag36h11:3', truth)
    assert distance > 0.02


def test_a_scene_without_tags_makes_no_texture_folder(tmp_path):
    data = world_data(**{'robot.tag': None, 'station.tag': None})
    with Scene(load_world(write_world(tmp_path, data))) as scene:
        assert scene.tags == {}
        assert scene.texture_folder is None


# -- world files -------------------------------------------------------------------------------
def test_the_tag_key_parses(tmp_path):
    data = world_data(**{'station.tag': {'family': 'tag16h5', 'id': 29, 'size': 0.3}})
    world = load_world(write_world(tmp_path, data))
    assert world.robot.tag == Tag('tag36h11', 3, 0.2)
    assert world.robot.tag.label == 'tag36h11:3'
    assert world.station.tag == Tag('tag16h5', 29, 0.3)
    assert world.objects[0].tag is None
    assert world.robot.speed == 0.5  # the robot's rebuilt Body keeps its tag and speed


def test_the_same_id_in_another_family_is_another_tag(tmp_path):
    data = world_data(**{'station.tag': {'family': 'tag25h9', 'id': 3, 'size': 0.2}})
    assert load_world(write_world(tmp_path, data)).station.tag == Tag('tag25h9', 3, 0.2)


@pytest.mark.parametrize(
    'changes, message',
    [
        ({'robot.tag': 3}, 'robot.tag: expected a mapping, got 3'),
        (
            {'robot.tag.family': 'tag99'},
            "robot.tag.family: expected one of tag16h5, tag25h9, tag36h10, tag36h11, got 'tag99'",
        ),
        ({'robot.tag.id': 587}, 'robot.tag.id: expected an integer 0-586 (an id of tag36h11), got 587'),
        ({'robot.tag.id': -1}, 'robot.tag.id: expected an integer 0-586 (an id of tag36h11), got -1'),
        ({'robot.tag.id': '3'}, "robot.tag.id: expected an integer 0-586 (an id of tag36h11), got '3'"),
        ({'robot.tag.id': True}, 'robot.tag.id: expected an integer 0-586 (an id of tag36h11), got True'),
        (
            {'station.tag': {'family': 'tag25h9', 'id': 35, 'size': 0.2}},
            'station.tag.id: expected an integer 0-34 (an id of tag25h9), got 35',
        ),
        ({'robot.tag.size': 0}, 'robot.tag.size: expected a positive number, got 0'),
        ({'robot.tag.size': 'big'}, "robot.tag.size: expected a finite number, got 'big'"),
        (
            {'robot.tag.size': 0.31},
            "robot.tag.size: expected at most the body's smaller side, 0.3 m, got 0.31",
        ),
        ({'robot.tag.size': None}, 'robot.tag.size: missing'),
        (
            {'robot.tag.colour': [0, 0, 0]},
            'robot.tag.colour: does not apply to a tag (keys of a tag: family, id, size)',
        ),
        (
            {'station.tag.id': 3},
            'station.tag: tag36h11:3 is also robot.tag; each tag (family and id) may be on one body only',
        ),
        (
            {'objects.0.tag': {'family': 'tag36h11', 'id': 9, 'size': 0.2}},
            "object 'crate'.tag: only the robot and the station carry a tag "
            '(keys of a static object: name, kind, position, size, yaw, colour, decoy, shiny, bottom)',
        ),
    ],
)
def test_bad_tags_are_refused(tmp_path, changes, message):
    path = write_world(tmp_path, world_data(**changes))
    with pytest.raises(WorldError) as error:
        load_world(path)
    assert str(error.value) == f'{path}: {message}'


# -- confidence: how clearly the weakest cell reads ----------------------------------------------


def degraded(frame, blur=0.0):
    rgb = cv2.GaussianBlur(frame.rgb, (0, 0), blur) if blur else frame.rgb
    return Frame(rgb=rgb, depth=None, camera=frame.camera, stamp=0.0)


def confidences(frame, algorithm='apriltag:tag36h11'):
    return {obj.label: obj.confidence for obj in parse(algorithm).detect(frame)}


def test_a_sharp_tag_has_confidence_1(drawn):
    assert confidences(drawn) == {'tag36h11:3': 1.0, 'tag36h11:7': 1.0}
    assert confidences(drawn, 'apriltag:tag25h9') == {'tag25h9:2': 1.0}


def test_blur_and_fewer_pixels_lower_the_confidence(drawn):
    sharp, blurred, more = (confidences(degraded(drawn, blur))['tag36h11:3'] for blur in (0.0, 2.0, 3.0))
    assert 0.5 < more < blurred < sharp == 1.0
    large, small = (
        confidences(drawn_frame([('tag36h11', 3, square((150, 150), half, 0.3))]))['tag36h11:3']
        for half in (20, 7)
    )
    assert 0.5 < small < large == 1.0


def flipped_tag(cell=None):
    """A grey image of tag36h11:3 upright, 12 pixels a cell, with data cell (row, column) ``cell``
    painted the other colour; and its black square's corners in OpenCV coordinates (aruco order)."""
    image = tag_image('tag36h11', 3, cell_pixels=12)  # a quiet zone one cell wide, then the border
    if cell is not None:
        top, left = (cell[0] + 2) * 12, (cell[1] + 2) * 12
        image[top : top + 12, left : left + 12] = 255 - image[top : top + 12, left : left + 12]
    grey = np.full((300, 400), 255, np.uint8)
    grey[100 : 100 + image.shape[0], 150 : 150 + image.shape[1]] = image
    u0, v0, side = 162 - 0.5, 112 - 0.5, 8 * 12
    return grey, np.array([(u0, v0), (u0 + side, v0), (u0 + side, v0 + side), (u0, v0 + side)])


def test_a_cell_read_wrong_takes_the_confidence_below_one_half():
    grey, corners = flipped_tag()
    assert decision_margin(grey, corners, 'tag36h11', 3) == 1.0
    grey, corners = flipped_tag(cell=(3, 3))
    assert decision_margin(grey, corners, 'tag36h11', 3) < 0.5
    assert decision_margin(grey, corners, 'tag36h11', 4) == 0.0  # another tag's code: many cells wrong
    # aruco corrects no bit of the AprilTag families: it does not report such a tag at all.
    frame = Frame(rgb=np.dstack([grey] * 3), depth=None, camera=drawn_frame([]).camera, stamp=0.0)
    assert confidences(frame) == {}


def test_a_tag_without_contrast_has_confidence_0():
    grey, corners = flipped_tag()
    assert decision_margin(np.full_like(grey, 128), corners, 'tag36h11', 3) == 0.0
