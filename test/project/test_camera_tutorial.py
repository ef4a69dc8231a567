"""docs/tutorials/your-camera.md's tag recipe, followed as a new user would: print the tags as the
page says, lay them on a grey floor at the page's positions and a realistic size, photograph the floor
with a camera, and drvs_calibrate gives that camera's pose, printed as the page shows.

Tags of 30 and 40 cm are there because they show large in the image: with the recipe's
old white border of one cell (100 px), OpenCV 4.6 misses them on these floors.
The photograph is synthetic: each printed tag (the PNG the recipe writes) is warped onto the
camera's image of a plain grey floor through the homography its floor square gives, at four
times the resolution and then averaged down, as a lens and a sensor would.
"""

import json
import os
import re
import subprocess
import sys

import cv2
import numpy as np
import pytest

from drvs.testing.doc_examples import commands, output_pattern, shell_blocks
from drvs.testing.harness import REPO
from drvs.vision.camera import PinholeCamera
from drvs.vision.optics import OPENCV_OFFSET, intrinsics_of, optical_pose_of

PAGE = REPO / 'docs' / 'tutorials' / 'your-camera.md'
CAMERA = PinholeCamera(eye=(1.8, -0.6, 3.0), target=(1.9, 1.7, 0.0), fov_deg=60, width=800, height=600)
"""The camera of the page's example output: about 3 m up, south of the tags, looking at them."""
SUPERSAMPLE = 4
POSITION_TOLERANCE = 0.01  # metres
ANGLE_TOLERANCE = 0.5  # degrees


def recipe_blocks() -> tuple[str, str]:
    """The page's block that makes the printable tags, and the drvs_calibrate block."""
    blocks = shell_blocks(PAGE, indented=True)
    (make,) = [block for block in blocks if 'drawMarker' in block]
    (calibrate,) = [block for block in blocks if block.startswith('nodes/drvs_calibrate')]
    return make, calibrate


@pytest.fixture(scope='module')
def printed(tmp_path_factory):
    """The recipe run as written in a folder of its own (its .venv the project's): tag0.png ... tag3.png."""
    folder = tmp_path_factory.mktemp('print')
    (folder / '.venv').symlink_to(REPO / '.venv')
    make, _ = recipe_blocks()
    result = subprocess.run(['bash', '-c', make], cwd=folder, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    return {tag: cv2.imread(str(folder / f'tag{tag}.png'), cv2.IMREAD_GRAYSCALE) for tag in range(4)}


def test_each_printed_tag_has_a_white_border_two_cells_wide(printed):
    for image in printed.values():
        assert image.shape == (1200, 1200)
        ring = np.ones(image.shape, bool)
        ring[200:1000, 200:1000] = False
        assert (image[ring] == 255).all()
        assert (image[200:300, 200:1000] == 0).all()  # the tag's own black border, one cell of 100 px


def photograph(printed: dict, tags: dict, black_square: float, grey: int) -> np.ndarray:
    """CAMERA's BGR image of a floor of ``grey`` with each printed tag lying at its map position,
    its black square ``black_square`` metres wide, its printed top towards +y."""
    width, height = CAMERA.width * SUPERSAMPLE, CAMERA.height * SUPERSAMPLE
    image = np.full((height, width), grey, np.uint8)
    for tag, (x, y) in tags.items():
        sheet = printed[tag]
        half = sheet.shape[0] * black_square / 800 / 2.0  # the black square is 800 px of the sheet
        floor = [
            [x - half, y + half, 0.0],
            [x + half, y + half, 0.0],
            [x + half, y - half, 0.0],
            [x - half, y - half, 0.0],
        ]
        corners = np.float32([[0, 0], [1, 0], [1, 1], [0, 1]]) * sheet.shape[0] - OPENCV_OFFSET
        seen = CAMERA.project_3d_to_pixel(np.array(floor)) * SUPERSAMPLE - OPENCV_OFFSET
        homography = cv2.getPerspectiveTransform(corners, np.float32(seen))
        warped = cv2.warpPerspective(sheet, homography, (width, height), flags=cv2.INTER_AREA)
        inside = cv2.warpPerspective(
            np.full_like(sheet, 255), homography, (width, height), flags=cv2.INTER_NEAREST
        )
        image[inside > 0] = warped[inside > 0]
    small = cv2.resize(image, (CAMERA.width, CAMERA.height), interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(small, cv2.COLOR_GRAY2BGR)


FLOORS = [(60, 0.19), (150, 0.19), (60, 0.3), (120, 0.4), (180, 0.4)]
"""(grey level of the floor, the black square's side in metres): 19 cm is a tag printed across A3."""


@pytest.mark.parametrize(('grey', 'black_square'), FLOORS)
def test_drvs_calibrate_recovers_the_pose_from_the_printed_tags_on_a_grey_floor(
    printed, tmp_path, grey, black_square
):
    _, block = recipe_blocks()
    ((command, documented),) = commands(block)
    tags = {
        int(tag): tuple(map(float, floor.split(',')))
        for tag, floor in re.findall(r'--tag (\d+):(\S+)', command)
    }
    assert sorted(tags) == [0, 1, 2, 3]
    image = tmp_path / 'floor.png'
    cv2.imwrite(str(image), photograph(printed, tags, black_square, grey))

    # As on the page, but from the photograph, with the camera's intrinsics, instead of --topic.
    K = intrinsics_of(CAMERA)
    arguments = command.split()[1:]
    topic = arguments.index('--topic')
    arguments[topic : topic + 2] = ['--image', str(image)]
    arguments += ['--fx', repr(K[0, 0]), '--fy', repr(K[1, 1]), '--cx', repr(K[0, 2]), '--cy', repr(K[1, 2])]
    output = tmp_path / 'pose.json'
    result = subprocess.run(
        [sys.executable, str(REPO / 'nodes/drvs_calibrate'), *arguments, '--json', str(output)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, 'ROS_MASTER_URI': 'http://127.0.0.1:1'},  # no master needed
    )
    assert result.returncode == 0, result.stderr
    printed_lines = [line.strip() for line in result.stdout.splitlines()]
    for line in documented:
        pattern = output_pattern(line.strip())
        assert any(pattern.fullmatch(out) for out in printed_lines), f'{line!r} not in:\n{result.stdout}'

    pose = json.loads(output.read_text())
    assert pose['frame'] == 'cam1_optical_frame'
    true_rotation, true_translation = optical_pose_of(CAMERA)
    rotation = np.asarray(pose['rotation'])
    cosine = (np.trace(rotation.T @ true_rotation) - 1.0) / 2.0
    angle = np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))
    assert np.linalg.norm(np.asarray(pose['position']) - true_translation) <= POSITION_TOLERANCE
    assert angle <= ANGLE_TOLERANCE
