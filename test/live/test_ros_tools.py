"""Debian's stock ROS tools understand drvs types once scripts/env.sh is sourced."""

import pytest

from drvs.testing import RosHarness

pytestmark = pytest.mark.shared_master  # see test/conftest.py

STATUS_CONSTANTS = [
    'uint8 ACCEPTED=0',
    'uint8 INVALID=1',
    'uint8 BUSY=2',
    'uint8 RATE_LIMITED=3',
    'uint8 UNAVAILABLE=4',
    'uint8 UNSUPPORTED=5',
]
"""Both services' responses list the same status constants."""


def test_rossrv_show_prints_the_contract(ros: RosHarness):
    result = ros.run('rossrv show drvs/DetectObjectBoundary')
    assert result.returncode == 0, result.stderr
    lines = [line.strip() for line in result.stdout.splitlines() if line.strip()]
    assert lines == [
        'string algorithm',
        'drvs/BoundingBox region_of_interest',
        'float64 min_x',
        'float64 min_y',
        'float64 max_x',
        'float64 max_y',
        'string callback_service',
        'string request_id',
        'bool fused',
        'string callback_uri',
        '---',
        *STATUS_CONSTANTS,
        'bool accepted',
        'uint8 status',
        'string message',
        'uint32 vision_systems',
        'float32 retry_after',
    ]


def test_rossrv_show_lists_the_registration_lease_and_status(ros: RosHarness):
    result = ros.run('rossrv show drvs/RegisterVisionService')
    assert result.returncode == 0, result.stderr
    lines = [line.strip() for line in result.stdout.splitlines() if line.strip()]
    assert 'string[] algorithms' in lines[: lines.index('---')]
    assert lines[lines.index('---') + 1 :] == [
        *STATUS_CONSTANTS,
        'bool accepted',
        'uint8 status',
        'string message',
        'float32 lease',
        'float32 retry_after',
    ]


@pytest.mark.parametrize(
    'message, first_field',
    [
        ('drvs/DetectedObject', 'geometry_msgs/Polygon boundary'),
        ('drvs/BoundingBox', 'float64 min_x'),
    ],
)
def test_rosmsg_show_prints_the_contract(ros: RosHarness, message, first_field):
    result = ros.run(f'rosmsg show {message}')
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[0] == first_field
    if message == 'drvs/DetectedObject':
        assert 'string label' in result.stdout.splitlines()


def test_rosservice_call_typed_in_a_shell_reaches_a_node(ros: RosHarness):
    node = ros.start_node('test/nodes/echo_detect_boundary.py', name='echo')
    ros.wait_for_service('/echo/detect_object_boundary', node=node)
    assert (
        ros.run('rosservice type /echo/detect_object_boundary').stdout.strip() == 'drvs/DetectObjectBoundary'
    )
    result = ros.run(
        'rosservice call /echo/detect_object_boundary '
        "\"{algorithm: 'colour:0,0,150,80,80,255', region_of_interest: {min_x: 0.5, min_y: 1.0, max_x: 7.0,"
        ' max_y: 5.5}, callback_service: /robot/callback_coordinates, request_id: r1}"'
    )
    assert result.returncode == 0, result.stderr + ros.describe()
    assert 'accepted: True' in result.stdout
    assert 'message: "colour:0,0,150,80,80,255|r1|0.5,1.0,7.0,5.5"' in result.stdout
    assert f'vision_systems: {len("/robot/callback_coordinates")}' in result.stdout


def test_env_sh_defaults(tmp_path):
    import subprocess

    from drvs.testing.harness import REPO

    script = (
        f'unset ROS_MASTER_URI ROS_HOSTNAME ROS_IP; source {REPO}/scripts/env.sh; '
        'echo "$ROS_MASTER_URI|$ROS_HOSTNAME|$(command -v python)"; '
        f'ROS_IP=10.0.0.5; unset ROS_HOSTNAME; ROS_MASTER_URI=http://h:1/; source {REPO}/scripts/env.sh; '
        'echo "$ROS_MASTER_URI|${ROS_HOSTNAME:-unset}"'
    )
    out = subprocess.run(
        ['bash', '-c', script], capture_output=True, text=True, check=True
    ).stdout.splitlines()
    assert out[0] == f'http://127.0.0.1:11311|127.0.0.1|{REPO}/.venv/bin/python'
    assert out[1] == 'http://h:1/|unset'
