"""The typed topic messages: conversions round-trip through serialize/deserialize, the constants
match the controller's states, every field is documented and ``rosmsg show`` prints them."""

import dataclasses
import math
import subprocess

import genpy
import numpy as np
import pytest
from shapely.geometry import Polygon

from drvs.msg import (
    BodyPoses,
    NodeCpu,
    RecorderSample,
    Registry,
    RobotStatus,
    VisionSystemEntry,
    VisionSystemStats,
)
from drvs.robot import controller
from drvs.robot.robot_status import RobotStatus as Status
from drvs.ros.messages import (
    ROBOT_STATES,
    STATS_COUNTERS,
    body_poses_from_msg,
    body_poses_to_msg,
    occupancy_to_msg,
    path_to_msg,
    pose_to_msg,
    registry_to_dict,
    registry_to_msg,
    robot_status_to_dict,
    robot_status_to_msg,
    stats_to_dict,
    stats_to_msg,
)
from drvs.server.registry import Registration
from drvs.testing.harness import REPO
from drvs.testing.messages import round_trip as serialize_deserialize

MESSAGES = {
    'VisionSystemEntry': VisionSystemEntry,
    'Registry': Registry,
    'VisionSystemStats': VisionSystemStats,
    'RobotStatus': RobotStatus,
    'BodyPoses': BodyPoses,
    'NodeCpu': NodeCpu,
    'RecorderSample': RecorderSample,
}


def entry(name, points, expires_at, algorithms=('colour',)):
    return Registration(
        service_name=name,
        field_of_view=tuple(points),
        polygon=Polygon(points),
        expires_at=expires_at,
        provider='/' + name.split('/')[1],
        algorithms=frozenset(algorithms),
    )


def test_the_registry_round_trips_with_each_lease_expiry_in_ros_time():
    square = ((0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0))
    entries = [
        entry('/vs1/detect_object_boundary', square, expires_at=108.0, algorithms=('motion', 'apriltag')),
        entry('/vs2/detect_object_boundary', ((2.5, 1.0), (3.5, 1.0), (3.5, 3.0)), expires_at=101.5),
    ]
    msg = serialize_deserialize(registry_to_msg(entries, stamp=1000.25, clock_now=100.0))
    assert msg.header.frame_id == 'map'
    assert registry_to_dict(msg) == {
        'stamp': 1000.25,
        'vision_systems': [
            {
                'service_name': '/vs1/detect_object_boundary',
                'provider': '/vs1',
                'field_of_view': [list(p) for p in square],
                'algorithms': ['apriltag', 'motion'],
                'lease_expiry': pytest.approx(1008.25, abs=1e-6),
            },
            {
                'service_name': '/vs2/detect_object_boundary',
                'provider': '/vs2',
                'field_of_view': [[2.5, 1.0], [3.5, 1.0], [3.5, 3.0]],
                'algorithms': ['colour'],
                'lease_expiry': pytest.approx(1001.75, abs=1e-6),
            },
        ],
    }
    empty = serialize_deserialize(registry_to_msg([], stamp=5.0, clock_now=0.0))
    assert registry_to_dict(empty) == {'stamp': 5.0, 'vision_systems': []}


def test_stats_round_trip_with_requests_by_algorithm_as_parallel_arrays():
    counts = {key: index for index, key in enumerate(STATS_COUNTERS)}
    counts['callback_bytes'] = 5 << 32  # more than a uint32
    by_algorithm = {'motion': 2, 'colour:0,0,150,80,80,255': 7, 'other': 1}
    msg = serialize_deserialize(stats_to_msg(counts, by_algorithm, stamp=12.5))
    assert msg.algorithms == ['colour:0,0,150,80,80,255', 'motion', 'other']
    assert list(msg.algorithm_requests) == [7, 2, 1]
    assert stats_to_dict(msg) == {'stamp': 12.5, **counts, 'requests_by_algorithm': by_algorithm}


ROBOT_COUNTS = {
    'replans': 2,
    'path_length': 14,
    'requests': 300,
    'watch_calls': 12,
    'watches': 4,
    'failed_requests': 3,
    'callbacks': 290,
    'callback_bytes': 5_000_000_000,
    'refused_callbacks': 1,
    'superseded': 9,
    'obstacles': 4,
}


def observed(status):
    """``status`` as :func:`robot_status_to_dict` gives it back: lists for points, the tag's fields
    only when seen."""
    fields = dataclasses.asdict(status)
    for key in ('position', 'goal', 'tag_pose'):
        if fields[key] is not None:
            fields[key] = list(fields[key])
    if status.tag_pose is None:
        del fields['tag_pose'], fields['tag_stamp']
    return fields


def test_a_robot_status_with_a_tag_fix_round_trips():
    status = Status(
        state=controller.MOVING,
        stamp=42.5,
        distance_to_goal=2.5,
        position=(1.0, 2.0),
        goal=(3.5, 2.0),
        **ROBOT_COUNTS,
        refused={'BUSY': 3, 'RATE_LIMITED': 1},
        vision_systems={'self': 2, 'station': 1, 'obstacle': 0},
        tag_pose=(1.01, 1.99, 0.5),
        tag_stamp=42.25,
    )
    msg = serialize_deserialize(robot_status_to_msg(status))
    assert (msg.state, msg.state_name) == (RobotStatus.MOVING, 'moving')
    assert (msg.has_position, msg.has_goal) == (True, True)
    assert (msg.position.x, msg.position.y, msg.position.theta) == (1.0, 2.0, 0.5)  # heading as seen
    assert (msg.refused_statuses, list(msg.refused_counts)) == (['BUSY', 'RATE_LIMITED'], [3, 1])
    assert (msg.roles, list(msg.role_vision_systems)) == (['obstacle', 'self', 'station'], [0, 2, 1])
    assert robot_status_to_dict(msg) == {**observed(status), 'heading': 0.5}


def test_a_robot_status_says_unknown_with_nan_and_flags():
    status = Status(state=controller.LOCALISING, stamp=3.0, **ROBOT_COUNTS)
    msg = serialize_deserialize(robot_status_to_msg(status))
    assert (msg.state, msg.has_position, msg.has_goal) == (RobotStatus.LOCALISING, False, False)
    unknown = (msg.distance_to_goal, msg.position.x, msg.position.theta, msg.goal.x, msg.tag_pose.x)
    assert all(math.isnan(value) for value in unknown)
    assert msg.tag_stamp == genpy.Time()
    assert robot_status_to_dict(msg) == {**observed(status), 'heading': None}


def test_the_robot_status_has_the_messages_fields():
    """Each field of the message comes from one field of the status, and each field of the status
    goes into the message."""
    derived = {
        'header': 'stamp',
        'state_name': 'state',
        'has_position': 'position',
        'has_goal': 'goal',
        'refused_statuses': 'refused',
        'refused_counts': 'refused',
        'roles': 'vision_systems',
        'role_vision_systems': 'vision_systems',
    }
    from_message = {derived.get(slot, slot) for slot in RobotStatus.__slots__}
    assert from_message == {field.name for field in dataclasses.fields(Status)}


def test_a_robot_status_with_an_unknown_state_is_refused():
    with pytest.raises(ValueError) as raised:
        robot_status_to_msg(Status(state='lost'))
    assert str(raised.value) == (
        "state: expected one of localising, moving, blocked, arriving, arrived, failed, got 'lost'"
    )


def test_the_state_constants_cover_every_controller_state():
    assert set(ROBOT_STATES) == {
        controller.LOCALISING,
        controller.MOVING,
        controller.BLOCKED,
        controller.ARRIVING,
        controller.ARRIVED,
        controller.FAILED,
    }
    for state, code in ROBOT_STATES.items():
        assert getattr(RobotStatus, state.upper()) == code
    assert sorted(ROBOT_STATES.values()) == list(range(len(ROBOT_STATES)))


def test_the_robots_pose_path_and_map_round_trip_in_map():
    pose = serialize_deserialize(pose_to_msg((1.5, 2.0), math.pi / 2, stamp=7.5))
    assert (pose.header.frame_id, pose.header.stamp.to_sec()) == ('map', 7.5)
    assert (pose.pose.position.x, pose.pose.position.y) == (1.5, 2.0)
    assert (pose.pose.orientation.z, pose.pose.orientation.w) == pytest.approx((0.5**0.5, 0.5**0.5))
    assert serialize_deserialize(pose_to_msg((1.5, 2.0), None, 7.5)).pose.orientation.w == 1.0  # +x
    path = serialize_deserialize(path_to_msg([(0.5, 0.5), (1.0, 0.75)], stamp=7.5))
    assert [(p.pose.position.x, p.pose.position.y) for p in path.poses] == [(0.5, 0.5), (1.0, 0.75)]
    assert {(p.header.frame_id, p.pose.orientation.w) for p in path.poses} == {('map', 1.0)}
    values = np.zeros((2, 3), np.int8)
    values[1, 2], values[0, 1] = 100, 99
    grid = serialize_deserialize(occupancy_to_msg(values, 0.05, stamp=7.5))
    assert (grid.info.width, grid.info.height, grid.info.resolution) == (3, 2, pytest.approx(0.05))  # float32
    assert (grid.info.origin.position.x, grid.info.origin.orientation.w) == (0.0, 1.0)
    assert list(grid.data) == [0, 99, 0, 0, 0, 100]  # row-major, row 0 at y = 0


def test_body_poses_round_trip_with_the_stamp_of_the_state():
    poses = {'robot': (0.5, 1.25, 0.1), 'station': (3.5, 2.0, 0.0), 'walker': (-1.0, 2.0, -3.0)}
    msg = serialize_deserialize(body_poses_to_msg(poses, stamp=1700000000.125))
    assert msg.header.frame_id == 'map' and msg.names == ['robot', 'station', 'walker']
    stamp, received = body_poses_from_msg(msg)
    assert stamp == pytest.approx(1700000000.125, abs=1e-6)
    assert received == poses


def test_body_poses_with_a_name_missing_are_refused():
    msg = body_poses_to_msg({'robot': (0.0, 0.0, 0.0), 'station': (1.0, 1.0, 0.0)}, stamp=1.0)
    msg.names.pop()
    with pytest.raises(ValueError) as raised:
        body_poses_from_msg(msg)
    assert str(raised.value) == 'names: 1 name(s) for 2 pose(s)'


def test_a_field_of_the_wrong_type_does_not_serialize():
    with pytest.raises(genpy.SerializationError):
        serialize_deserialize(VisionSystemStats(requests='many'))


def definition(name):
    """(field and constant lines without comments, lines without a comment) of msg/NAME.msg."""
    fields, undocumented = [], []
    for line in (REPO / 'msg' / f'{name}.msg').read_text().splitlines():
        code = line.split('#', 1)[0].strip()
        if code:
            fields.append(' '.join(code.split()))
            if '#' not in line:
                undocumented.append(code)
    return fields, undocumented


@pytest.mark.parametrize('name', MESSAGES)
def test_every_field_is_documented_and_rosmsg_show_lists_it(name):
    fields, undocumented = definition(name)
    assert undocumented == []
    assert [f.split()[-1].split('=')[0] for f in fields if '=' not in f] == MESSAGES[name].__slots__
    result = subprocess.run(
        ['bash', '-c', f'source {REPO}/scripts/env.sh && rosmsg show drvs/{name}'],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    shown = [line.strip() for line in result.stdout.splitlines() if line.strip() and not line.startswith(' ')]
    assert shown == fields
