"""drvs_calibrate: a camera's pose in map from AprilTags (or pixel/map pairs) on the floor.

The views are rendered with PyBullet (drvs.testing.tags: textured quads on a floor),
so the true pose is the PinholeCamera's and the image's K is
``intrinsics_of(camera, TINY_RENDERER_SAMPLE)``.
"""

import contextlib
import doctest
import io
import json
import os
import re
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest
import yaml

from drvs.sim.scene import TINY_RENDERER_SAMPLE
from drvs.sim.world_file import load_world
from drvs.testing import free_port
from drvs.testing.harness import REPO
from drvs.testing.tags import (
    ANGLE_TOLERANCE,
    CAMERAS,
    POSITION_TOLERANCE,
    TAGS,
    FloorTag,
    pose_errors,
    render_floor_tags,
    tag_args,
    write_camera_info,
)
from drvs.tools.calibrate import calibrate, parse_args, sibling_camera_info
from drvs.vision import calibration
from drvs.vision.calibration import CalibrationError, FloorPoint, Intrinsics
from drvs.vision.camera import PinholeCamera
from drvs.vision.optics import OPENCV_OFFSET, intrinsics_of, optical_pose_of

COMMAND = [sys.executable, str(REPO / 'nodes/drvs_calibrate')]


def pixels_of(camera, points) -> np.ndarray:
    """OpenCV pixel coordinates, in the rendered array, of map points."""
    return camera.project_3d_to_pixel(points) - np.asarray(TINY_RENDERER_SAMPLE) - OPENCV_OFFSET


def intrinsics_args(K) -> list[str]:
    return ['--fx', repr(K[0, 0]), '--fy', repr(K[1, 1]), '--cx', repr(K[0, 2]), '--cy', repr(K[1, 2])]


def run_command(*args, env=None, timeout=60) -> subprocess.CompletedProcess:
    """nodes/drvs_calibrate ``args``, run as a user runs it."""
    return subprocess.run(
        [*COMMAND, *map(str, args)], cwd=REPO, capture_output=True, text=True, timeout=timeout, env=env
    )


def run(*args) -> subprocess.CompletedProcess:
    """drvs_calibrate ``args`` in this process, from the repository (what nodes/drvs_calibrate does
    but for starting Python: its exit code, stdout and stderr), for the many image-file cases;
    :func:`run_command` runs the command itself."""
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.chdir(REPO), contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        try:
            code = calibrate(parse_args(list(map(str, args))))
        except SystemExit as exit_:  # argparse's refusals
            code = exit_.code
    return subprocess.CompletedProcess(['drvs_calibrate', *args], code, stdout.getvalue(), stderr.getvalue())


@pytest.fixture(scope='module')
def views(tmp_path_factory):
    """Each camera's rendered view, saved as PNG (BGR on disk, as cv2.imwrite writes)."""
    folder = tmp_path_factory.mktemp('views')
    paths = {}
    for name, camera in CAMERAS.items():
        rgb = render_floor_tags(camera, TAGS, folder / 'textures')
        paths[name] = folder / f'{name}.png'
        cv2.imwrite(str(paths[name]), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return paths


# -- the rendering the other tests rely on ---------------------------------------------------------
def test_rendered_tags_decode_where_the_camera_model_projects_them(views):
    camera = CAMERAS['from_the_south']
    image = cv2.imread(str(views['from_the_south']))
    intrinsics = Intrinsics(intrinsics_of(camera, TINY_RENDERER_SAMPLE))
    seen = calibration.detect_tags(image, intrinsics)
    assert sorted(seen) == [tag.id for tag in TAGS]
    for tag in TAGS:
        (sighting,) = seen[tag.id]
        # Corner 0 is the printed top-left: the texture lies upright and unmirrored.
        assert np.abs(sighting.corners - pixels_of(camera, tag.corners())).max() < 0.6, tag
        centre = pixels_of(camera, [*tag.position, 0.0])
        assert np.linalg.norm(sighting.centre - centre) < 0.2, tag


# -- the pose ----------------------------------------------------------------------------------------
@pytest.mark.parametrize('name', CAMERAS)
def test_tags_on_the_floor_give_the_pose_within_1_cm_and_half_a_degree(views, name):
    camera = CAMERAS[name]
    intrinsics = Intrinsics(intrinsics_of(camera, TINY_RENDERER_SAMPLE))
    seen = calibration.detect_tags(cv2.imread(str(views[name])), intrinsics)
    tags = [calibration.TagSpec(tag.id, tag.position) for tag in TAGS]
    result = calibration.solve(calibration.tag_points(tags, seen), intrinsics, 800, 600)
    position_error, angle_error = pose_errors(camera, result.rotation, result.translation)
    assert position_error <= POSITION_TOLERANCE and angle_error <= ANGLE_TOLERANCE, (
        position_error,
        angle_error,
    )
    assert result.rms_error < 0.3


def test_four_tags_are_enough(views):
    camera = CAMERAS['from_the_south']
    intrinsics = Intrinsics(intrinsics_of(camera, TINY_RENDERER_SAMPLE))
    seen = calibration.detect_tags(cv2.imread(str(views['from_the_south'])), intrinsics)
    tags = [calibration.TagSpec(tag.id, tag.position) for tag in TAGS[:4]]
    result = calibration.solve(calibration.tag_points(tags, seen), intrinsics, 800, 600)
    position_error, angle_error = pose_errors(camera, result.rotation, result.translation)
    assert position_error <= POSITION_TOLERANCE and angle_error <= ANGLE_TOLERANCE, (
        position_error,
        angle_error,
    )


def test_exact_point_pairs_give_the_exact_pose():
    camera = CAMERAS['from_the_north_east']
    K = intrinsics_of(camera, TINY_RENDERER_SAMPLE)
    floor = [(1.0, 1.0), (3.0, 1.2), (2.8, 2.9), (0.9, 2.5), (2.0, 2.0)]
    pixels = pixels_of(camera, [(x, y, 0.0) for x, y in floor])
    points = [
        FloorPoint(f'point {i}', tuple(p), f) for i, (p, f) in enumerate(zip(pixels, floor, strict=True))
    ]
    result = calibration.solve(points, Intrinsics(K), 800, 600)
    position_error, angle_error = pose_errors(camera, result.rotation, result.translation)
    assert position_error < 1e-6 and angle_error < 1e-5
    assert result.max_error < 1e-6
    assert result.target == pytest.approx(camera.target, abs=1e-6)
    assert result.fov_deg == pytest.approx(60.0)


def test_a_distorted_camera_is_recovered_from_points_on_the_command_line(tmp_path):
    camera = CAMERAS['from_the_west_turned']
    K = intrinsics_of(camera, TINY_RENDERER_SAMPLE)
    distortion = [-0.25, 0.08, 0.001, -0.0005, -0.01]
    rotation, eye = optical_pose_of(camera)
    corners = [(60, 60), (740, 60), (740, 540), (60, 540), (400, 300), (250, 400)]  # out to the image's edges
    floor = [tuple(np.round(camera.pixel_to_floor(pixel)[:2], 2)) for pixel in corners]
    rvec = cv2.Rodrigues(rotation.T)[0]
    tvec = -rotation.T @ eye
    pixels, _ = cv2.projectPoints(
        np.array([(x, y, 0.0) for x, y in floor]), rvec, tvec, K, np.array(distortion)
    )
    ideal = pixels_of(camera, [(x, y, 0.0) for x, y in floor])
    assert np.abs(pixels.reshape(-1, 2) - ideal).max() > 20.0  # the lens matters
    points = [f'{u!r},{v!r}:{x},{y}' for (u, v), (x, y) in zip(pixels.reshape(-1, 2), floor, strict=True)]
    output = tmp_path / 'pose.json'
    result = run_command(
        '--image',
        blank_image(tmp_path),
        *intrinsics_args(K),
        '--distortion',
        ','.join(map(str, distortion)),
        *[arg for point in points for arg in ('--point', point)],
        '--json',
        output,
    )
    assert result.returncode == 0, result.stderr
    pose = json.loads(output.read_text())
    position_error, angle_error = pose_errors(camera, pose['rotation'], pose['position'])
    assert position_error < 1e-6 and angle_error < 1e-5
    assert pose['world_entry']['distortion'] == distortion
    assert f', distortion: [{", ".join(map(str, distortion))}]}}' in result.stdout


def test_a_tag_centre_is_exact_under_distortion():
    camera = CAMERAS['from_the_south']
    K = intrinsics_of(camera, TINY_RENDERER_SAMPLE)
    distortion = (-0.3, 0.1, 0.002, 0.001, 0.0)
    rotation, eye = optical_pose_of(camera)
    rvec, tvec = cv2.Rodrigues(rotation.T)[0], -rotation.T @ eye
    tag = FloorTag(7, (2.7, 2.9), yaw=0.7, size=0.5)
    square = np.vstack([tag.corners(), [[*tag.position, 0.0]]])
    pixels, _ = cv2.projectPoints(square, rvec, tvec, K, np.array(distortion))
    corners, centre = pixels.reshape(-1, 2)[:4], pixels.reshape(-1, 2)[4]
    naive = calibration.tag_centre(corners, Intrinsics(K))
    assert np.linalg.norm(naive - centre) > 0.05  # the diagonals cross elsewhere in the distorted image
    exact = calibration.tag_centre(corners, Intrinsics(K, distortion))
    assert exact == pytest.approx(centre, abs=1e-6)


# -- the command ------------------------------------------------------------------------------------
def blank_image(folder, size=(800, 600)):
    path = folder / 'blank.png'
    cv2.imwrite(str(path), np.full((size[1], size[0], 3), 128, np.uint8))
    return path


def test_the_command_prints_a_static_transform_and_a_world_entry_that_loads(views, tmp_path):
    camera = CAMERAS['from_the_south']
    K = intrinsics_of(camera, TINY_RENDERER_SAMPLE)
    result = run('--image', views['from_the_south'], *intrinsics_args(K), *tag_args(TAGS), '--name', 'cam7')
    assert result.returncode == 0, result.stderr
    assert result.stderr == ''
    lines = result.stdout.splitlines()
    assert lines[0] == '6 floor points (pixels: OpenCV coordinates; map: metres):'
    assert [line.split()[:2] for line in lines[1:7]] == [['tag', str(tag.id)] for tag in TAGS]
    assert re.fullmatch(r'reprojection error: rms 0\.\d{3} px, max 0\.\d{3} px \(tag \d\)', lines[7])
    assert lines[8].startswith('camera in map: position ')

    number = r'-?\d+\.\d{6}'
    assert re.fullmatch(
        rf'static transform \(x y z qx qy qz qw parent child\): ({number} ){{7}}map cam7_optical_frame',
        lines[9],
    )
    command = lines[10].split()
    assert command[0] == '/usr/lib/tf2_ros/static_transform_publisher'
    assert ' '.join(command[1:]) == lines[9].split(': ', 1)[1]
    x, y, z, qx, qy, qz, qw = map(float, command[1:8])
    assert command[8:] == ['map', 'cam7_optical_frame']  # --name cam7: no frame_id in an image file
    rotation = quaternion_matrix(qx, qy, qz, qw)
    position_error, angle_error = pose_errors(camera, rotation, (x, y, z))
    assert position_error <= POSITION_TOLERANCE and angle_error <= ANGLE_TOLERANCE

    assert lines[11] == 'world file entry (under vision_systems:):'
    entry = lines[12]
    assert re.fullmatch(
        r'  - \{name: cam7, position: \[.*\], target: \[.*, 0\.0\], up: \[.*\], fov_deg: 60\.0, '
        r'resolution: \[800, 600\]\}',
        entry,
    )
    assert len(lines) == 13
    world = yaml.safe_load((REPO / 'test/worlds/small.yaml').read_text())
    del world['vision_systems']
    path = tmp_path / 'calibrated.yaml'
    path.write_text(yaml.safe_dump(world) + 'vision_systems:\n' + entry + '\n')
    (loaded,) = load_world(path).vision_systems
    model = PinholeCamera.from_config(loaded)
    right, up, forward = model.axes()
    rebuilt = np.column_stack([right, -up, forward])
    position_error, angle_error = pose_errors(camera, rebuilt, model.eye)
    assert position_error <= POSITION_TOLERANCE and angle_error <= ANGLE_TOLERANCE
    assert (loaded.name, loaded.resolution, loaded.distortion) == ('cam7', (800, 600), ())


def quaternion_matrix(x, y, z, w) -> np.ndarray:
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def test_the_json_has_what_the_text_has(views, tmp_path):
    K = intrinsics_of(CAMERAS['from_the_south'], TINY_RENDERER_SAMPLE)
    output = tmp_path / 'pose.json'
    args = ['--image', views['from_the_south'], *intrinsics_args(K), *tag_args(TAGS[:4])]
    result = run(*args, '--frame', 'cam1_optical', '--json', output)
    assert result.returncode == 0, result.stderr
    pose = json.loads(output.read_text())
    assert pose['command'] in result.stdout.splitlines()
    assert pose['command'].endswith(' map cam1_optical')
    assert f'  - {pose["world_entry_yaml"]}' in result.stdout.splitlines()
    assert [p['label'] for p in pose['points']] == ['tag 0', 'tag 1', 'tag 2', 'tag 3']
    assert max(p['error_px'] for p in pose['points']) == pytest.approx(pose['max_error_px'])
    assert np.asarray(pose['rotation']) == pytest.approx(
        quaternion_matrix(*pose['quaternion_xyzw']), abs=1e-9
    )


@pytest.mark.parametrize(
    ('name_args', 'frame'), [([], 'cam1_optical_frame'), (['--name', 'door'], 'door_optical_frame')]
)
def test_the_tf_lines_name_the_optical_frame_of_the_named_camera(views, tmp_path, name_args, frame):
    """An image file carries no frame_id: the tf lines are for NAME_optical_frame (--name, default cam1)."""
    K = intrinsics_of(CAMERAS['from_the_south'], TINY_RENDERER_SAMPLE)
    output = tmp_path / 'pose.json'
    result = run(
        '--image',
        views['from_the_south'],
        *intrinsics_args(K),
        *tag_args(TAGS[:4]),
        *name_args,
        '--json',
        output,
    )
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    (transform,) = [line for line in lines if line.startswith('static transform ')]
    (command,) = [line for line in lines if line.startswith('/usr/lib/tf2_ros/static_transform_publisher ')]
    assert transform.endswith(f' map {frame}') and command.endswith(f' map {frame}')
    assert json.loads(output.read_text())['frame'] == frame


def test_intrinsics_from_a_camera_info_yaml_file(views, tmp_path):
    camera = CAMERAS['from_the_south']
    path = write_camera_info(tmp_path / 'cam1.yaml', intrinsics_of(camera, TINY_RENDERER_SAMPLE))
    output = tmp_path / 'pose.json'
    result = run('--image', views['from_the_south'], '--camera-info', path, *tag_args(TAGS), '--json', output)
    assert result.returncode == 0, result.stderr
    pose = json.loads(output.read_text())
    position_error, angle_error = pose_errors(camera, pose['rotation'], pose['position'])
    assert position_error <= POSITION_TOLERANCE and angle_error <= ANGLE_TOLERANCE


# -- refusals ---------------------------------------------------------------------------------------
INTRINSICS = ['--fx', '519.6', '--fy', '519.6', '--cx', '400', '--cy', '299']


@pytest.mark.parametrize(
    'args, message',
    [
        (
            ['--tag', '0:1,1', '--tag', '1:2.5,1.2', '--tag', '2:1.2,2.6'],
            'drvs_calibrate: error: need at least 4 floor points, got 3: '
            'add --tag ID:X,Y or --point U,V:X,Y entries',
        ),
        (
            ['--tag', '0:1,1', '--tag', '1:2,1.5', '--tag', '4:3,2', '--tag', '5:0.5,0.75'],
            'drvs_calibrate: error: the 4 floor points lie on one line, which leaves the camera free to turn '
            'about it: add points off that line',
        ),
        (
            ['--tag', '0:1,1', '--tag', '1:2.5,1.2', '--tag', '2:1.2,2.6', '--tag', '9:3,3'],
            'drvs_calibrate: error: tag 9 is not seen in the image (tags seen: 0, 1, 2, 3, 4, 5); '
            'check the --tag ids, and that each tag is whole, flat and in focus, with a white border '
            '(quiet zone) around its black square at least two of its cells wide (200 px around an '
            '800 px tag)',
        ),
        (
            ['--tag', '0:1,1', '--tag', '1:2.5,1.2', '--tag', '2:1.2,2.6', '--tag', '0:3,3'],
            'drvs_calibrate: error: tag 0 is given twice: give each --tag id once',
        ),
        (
            ['--tag', '0:1,1', '--tag', '1:2.5,1.2', '--tag', '2:1.2,2.6', '--tag', '3:1,1'],
            'drvs_calibrate: error: tag 0 and tag 3 are both at map (1, 1): '
            'each point needs its own map position',
        ),
        (
            ['--tag', '0:1;1'],
            "drvs_calibrate: error: argument --tag: '0:1;1': expected ID:X,Y (a tag36h11 id and the map "
            'position of its centre, metres), e.g. 3:1.5,2.0 (see --help)',
        ),
        (
            ['--tag', '600:1,1'],
            "drvs_calibrate: error: argument --tag: '600:1,1': tag36h11 ids are 0 to 586 (see --help)",
        ),
        (
            ['--point', '12,x:1,1'],
            "drvs_calibrate: error: argument --point: '12,x:1,1': expected U,V:X,Y (OpenCV pixel, then map "
            'position in metres), e.g. 412.5,300:1.0,2.0 (see --help)',
        ),
        (
            ['--point', '812,5:1,1', '--point', '1,1:2,1', '--point', '1,2:2,2', '--point', '3,4:1,2'],
            'drvs_calibrate: error: point 1: pixel (812, 5) is outside the 800x600 image '
            '(OpenCV pixel coordinates: the top-left pixel is centred at 0,0)',
        ),
        (
            ['--distortion', '0.1,0.2'],
            "drvs_calibrate: error: argument --distortion: '0.1,0.2': expected 5 comma-separated numbers "
            'k1,k2,p1,p2,k3, e.g. -0.2,0.05,0,0,0 (see --help)',
        ),
    ],
    ids=[
        '3_points',
        'collinear',
        'tag_not_seen',
        'tag_twice',
        'same_spot',
        'bad_tag',
        'tag_id_range',
        'bad_point',
        'outside_the_image',
        'bad_distortion',
    ],
)
def test_bad_input_is_refused_in_one_line(views, args, message):
    result = run('--image', views['from_the_south'], *INTRINSICS, *args)
    assert (result.returncode, result.stderr, result.stdout) == (2, message + '\n', '')


@pytest.mark.parametrize(
    'args, message',
    [
        (
            ['--image', 'nowhere.png', *INTRINSICS],
            'drvs_calibrate: error: --image nowhere.png: no such file',
        ),
        (
            ['--image', 'README.md', *INTRINSICS],
            'drvs_calibrate: error: --image README.md: '
            'cannot read it as an image (not a format OpenCV reads?)',
        ),
        (
            ['--image', 'README.md', '--fx', '500'],
            'drvs_calibrate: error: intrinsics: --fy, --cx, --cy missing: give all of --fx --fy --cx --cy, '
            'or --camera-info (see --help)',
        ),
        (
            ['--image', 'README.md'],
            'drvs_calibrate: error: no intrinsics: give --camera-info FILE|TOPIC, or --fx --fy --cx --cy '
            '(see --help)',
        ),
        (
            ['--image', 'README.md', '--camera-info', 'nowhere.yaml'],
            'drvs_calibrate: error: --camera-info nowhere.yaml: cannot read it: No such file or directory',
        ),
        (
            ['--image', 'README.md', '--camera-info', 'test/worlds/small.yaml'],
            'drvs_calibrate: error: --camera-info test/worlds/small.yaml: '
            'camera_matrix.data: expected 9 numbers '
            '(a camera_calibration_parsers YAML file, as camera drivers save it)',
        ),
        (
            ['--image', 'README.md', '--distortion', '0,0,0,0,0'],
            'drvs_calibrate: error: --distortion goes with --fx --fy --cx --cy '
            '(a camera info carries its own) (see --help)',
        ),
    ],
    ids=[
        'missing_image',
        'not_an_image',
        'partial_intrinsics',
        'no_intrinsics',
        'missing_yaml',
        'not_camera_info',
        'distortion_alone',
    ],
)
def test_bad_files_and_intrinsics_are_refused_in_one_line(args, message):
    result = run(*args, '--tag', '0:1,1')
    assert (result.returncode, result.stderr, result.stdout) == (2, message + '\n', '')


def test_mirrored_map_points_put_the_camera_under_the_floor():
    camera = CAMERAS['from_the_north_east']
    floor = [(1.0, 1.0), (3.0, 1.2), (2.8, 2.9), (0.9, 2.5)]
    pixels = pixels_of(camera, [(x, y, 0.0) for x, y in floor])
    mirrored = [
        FloorPoint(f'point {i}', tuple(p), (x, -y))
        for i, (p, (x, y)) in enumerate(zip(pixels, floor, strict=True))
    ]
    with pytest.raises(CalibrationError) as raised:
        calibration.solve(mirrored, Intrinsics(intrinsics_of(camera, TINY_RENDERER_SAMPLE)), 800, 600)
    assert re.fullmatch(
        r'the best pose puts the camera under the floor \(z = -\d\.\d{3} m\): '
        r'are the map x and y swapped or mirrored\?',
        str(raised.value),
    )


def test_a_pose_with_a_point_behind_the_camera_is_refused():
    camera = CAMERAS['from_the_north_east']
    K = intrinsics_of(camera, TINY_RENDERER_SAMPLE)
    floor = [(1.0, 1.0), (3.0, 1.2), (2.8, 2.9), (8.0, 6.0)]  # (8, 6) is behind this camera
    points = [FloorPoint(f'point {i + 1}', (400.0, 300.0), f) for i, f in enumerate(floor)]
    rotation, eye = optical_pose_of(camera)
    pose = calibration.Calibration(tuple(points), np.zeros((4, 2)), rotation, eye, Intrinsics(K), 800, 600)
    with pytest.raises(CalibrationError) as raised:
        calibration.check_pose(pose)
    assert re.fullmatch(
        r'the best pose puts point 4 behind the camera \(depth -\d\.\d{3} m\): '
        'check that each pixel matches its map point',
        str(raised.value),
    )


def test_a_solvepnp_failure_is_reported(monkeypatch):
    def fail(*args, **kwargs):
        raise cv2.error('no solution')

    monkeypatch.setattr(calibration.cv2, 'solvePnPGeneric', fail)
    pixels = [(100.0, 100.0), (700.0, 100.0), (700.0, 500.0), (100.0, 500.0)]
    floor = [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)]
    points = [FloorPoint(f'point {i}', p, f) for i, (p, f) in enumerate(zip(pixels, floor, strict=True), 1)]
    with pytest.raises(CalibrationError) as raised:
        calibration.solve(points, Intrinsics.from_values(500, 500, 400, 300), 800, 600)
    assert str(raised.value) == (
        'cv2.solvePnP found no pose for these 4 points: '
        'check that each pixel matches its map point and the intrinsics'
    )


def test_doctests():
    assert doctest.testmod(calibration).failed == 0


def test_sibling_camera_info():
    assert sibling_camera_info('/cam1/image_raw') == '/cam1/camera_info'
    assert sibling_camera_info('/a/b/image_rect_color') == '/a/b/camera_info'
    assert sibling_camera_info('image_raw') == 'camera_info'


def test_without_a_master_the_topic_mode_fails_at_once(tmp_path):
    env = {**os.environ, 'ROS_HOME': str(tmp_path), 'ROS_MASTER_URI': f'http://127.0.0.1:{free_port()}'}
    start = time.monotonic()
    result = run_command(
        '--topic', '/cam1/image_raw', '--tag', '0:1,1', '--timeout', '5', env=env, timeout=30
    )
    assert time.monotonic() - start < 5
    assert (result.returncode, result.stdout) == (2, '')
    assert re.fullmatch(
        r'drvs_calibrate: error: no ROS master at http://127\.0\.0\.1:\d+ '
        r'\(\[Errno 111\] Connection refused\): start roscore and the camera driver, '
        r'set ROS_MASTER_URI \(source scripts/env\.sh\), or use --image FILE\n',
        result.stderr,
    )


def test_the_reference_of_the_empty_floor_is_written_for_foreground(tmp_path):
    """``--reference FILE`` without floor points only writes the image (no intrinsics needed); the
    foreground algorithm reads it back as it was."""
    from drvs.algorithms.foreground import read_reference

    image = blank_image(tmp_path, (160, 120))
    reference = tmp_path / 'cam1_floor.png'
    result = run('--image', image, '--reference', reference)
    assert (result.returncode, result.stdout) == (0, '')
    assert (
        result.stderr == f'drvs_calibrate: wrote the reference of the empty floor, 160x120, to {reference}\n'
    )
    assert read_reference(str(reference)).shape == (120, 160, 3)
    result = run('--image', image, '--reference', tmp_path / 'no' / 'such.png')
    assert result.returncode == 2
    assert result.stderr.startswith(
        f'drvs_calibrate: error: --reference {tmp_path}/no/such.png: cannot write it'
    )
