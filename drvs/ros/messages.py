"""The typed topic messages <-> core types: the registry, a vision system's counters, the robot's
status, pose, plan and map, and the simulated world's poses.

Each ``*_to_msg`` builds the message a node publishes from what the node holds; each
``*_to_dict`` (or :func:`body_poses_from_msg`) turns a received message back into plain
Python values for the observers (the scenario recorder, test nodes): numbers, lists and
dicts, with ``None`` where the message says "unknown" (NaN or a ``has_*`` flag).

>>> msg = body_poses_to_msg({'robot': (1.0, 2.0, 0.5)}, stamp=12.25)
>>> body_poses_from_msg(msg)
(12.25, {'robot': (1.0, 2.0, 0.5)})
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence

import genpy
from geometry_msgs.msg import Point, Pose, Pose2D, PoseStamped
from nav_msgs.msg import OccupancyGrid, Path
from std_msgs.msg import Header

from drvs.msg import BodyPoses, Registry, RobotStatus, VisionSystemEntry, VisionSystemStats
from drvs.robot import controller, robot_status
from drvs.ros.conversions import points_to_polygon, polygon_to_points
from drvs.server.registry import Registration

FRAME = 'map'
NAN = float('nan')

STATS_COUNTERS = (
    'requests',
    'refused',
    'callbacks',
    'callback_failures',
    'callback_bytes',
    'renders',
    'no_frame',
    'cache_hits',
    'registrations',
    'objects',
    'watch_calls',
    'watches',
    'watch_evaluations',
)
"""The counters of drvs/VisionSystemStats, in the message's order (``watches`` is a gauge: standing now)."""

ROBOT_STATES = {
    controller.LOCALISING: RobotStatus.LOCALISING,
    controller.MOVING: RobotStatus.MOVING,
    controller.BLOCKED: RobotStatus.BLOCKED,
    controller.ARRIVING: RobotStatus.ARRIVING,
    controller.ARRIVED: RobotStatus.ARRIVED,
    controller.FAILED: RobotStatus.FAILED,
}
"""The controller's state names -> drvs/RobotStatus constants."""

ROBOT_COUNTERS = robot_status.COUNTERS
"""The counters of drvs/RobotStatus, in the message's order."""


def to_time(seconds: float) -> genpy.Time:
    """Seconds -> a ROS time (never negative)."""
    return genpy.Time.from_sec(max(float(seconds), 0.0))


def header(stamp: float) -> Header:
    """A std_msgs/Header in ``map`` stamped ``stamp`` (seconds)."""
    return Header(stamp=to_time(stamp), frame_id=FRAME)


def _known(value: float) -> float | None:
    return None if math.isnan(value) else value


# -- /drvs/registry ----------------------------------------------------------------------------------
def registry_to_msg(entries: Iterable[Registration], stamp: float, clock_now: float) -> Registry:
    """The registry's entries -> drvs/Registry stamped ``stamp`` (ROS seconds).

    A lease's expiry is on the registry's own clock; ``clock_now`` is that clock's reading
    at ``stamp``, so ``lease_expiry`` = ``stamp`` + the time left.
    """
    return Registry(
        header=header(stamp),
        vision_systems=[
            VisionSystemEntry(
                service_name=entry.service_name,
                provider=entry.provider,
                field_of_view=points_to_polygon(entry.field_of_view),
                algorithms=sorted(entry.algorithms),
                lease_expiry=to_time(stamp + entry.expires_at - clock_now),
            )
            for entry in entries
        ],
    )


def registry_to_dict(msg: Registry) -> dict:
    """drvs/Registry -> ``{'stamp', 'vision_systems': [{'service_name', 'provider',
    'field_of_view': [[x, y], ...], 'algorithms', 'lease_expiry'}, ...]}``."""
    return {
        'stamp': msg.header.stamp.to_sec(),
        'vision_systems': [
            {
                'service_name': entry.service_name,
                'provider': entry.provider,
                'field_of_view': [list(point) for point in polygon_to_points(entry.field_of_view)],
                'algorithms': list(entry.algorithms),
                'lease_expiry': entry.lease_expiry.to_sec(),
            }
            for entry in msg.vision_systems
        ],
    }


# -- /<vision system>/stats --------------------------------------------------------------------------
def stats_to_msg(
    counts: Mapping[str, int], by_algorithm: Mapping[str, int], stamp: float
) -> VisionSystemStats:
    """A vision system's counters (:data:`STATS_COUNTERS`) and its accepted requests per
    algorithm string -> drvs/VisionSystemStats (algorithms sorted)."""
    algorithms = sorted(by_algorithm)
    return VisionSystemStats(
        header=header(stamp),
        algorithms=algorithms,
        algorithm_requests=[int(by_algorithm[a]) for a in algorithms],
        **{key: int(counts.get(key, 0)) for key in STATS_COUNTERS},
    )


def stats_to_dict(msg: VisionSystemStats) -> dict:
    """drvs/VisionSystemStats -> ``{'stamp', COUNTER: n, ..., 'requests_by_algorithm': {algorithm: n}}``."""
    return {
        'stamp': msg.header.stamp.to_sec(),
        **{key: getattr(msg, key) for key in STATS_COUNTERS},
        'requests_by_algorithm': dict(zip(msg.algorithms, msg.algorithm_requests, strict=True)),
    }


# -- /robot/status -----------------------------------------------------------------------------------
def robot_status_to_msg(status: robot_status.RobotStatus) -> RobotStatus:
    """The robot's status (:class:`drvs.robot.robot_status.RobotStatus`) -> drvs/RobotStatus.

    ``position.theta`` is the heading of ``tag_pose`` (NaN without); what is unknown is NaN, with
    ``has_position`` and ``has_goal`` false.
    """
    state = status.state
    if state not in ROBOT_STATES:
        raise ValueError(f'state: expected one of {", ".join(ROBOT_STATES)}, got {state!r}')
    position, goal, tag_pose = status.position, status.goal, status.tag_pose
    distance = status.distance_to_goal
    refused, roles = status.refused, status.vision_systems
    return RobotStatus(
        header=header(status.stamp),
        state=ROBOT_STATES[state],
        state_name=state,
        reason=status.reason or '',
        distance_to_goal=NAN if distance is None else float(distance),
        has_position=position is not None,
        position=Pose2D(
            *(map(float, position[:2]) if position is not None else (NAN, NAN)),
            float(tag_pose[2]) if tag_pose is not None else NAN,
        ),
        has_goal=goal is not None,
        goal=Point(*(map(float, goal[:2]) if goal is not None else (NAN, NAN)), 0.0),
        refused_statuses=sorted(refused),
        refused_counts=[int(refused[s]) for s in sorted(refused)],
        roles=sorted(roles),
        role_vision_systems=[int(roles[r]) for r in sorted(roles)],
        tag_pose=Pose2D(*map(float, tag_pose)) if tag_pose is not None else Pose2D(NAN, NAN, NAN),
        tag_stamp=to_time(status.tag_stamp) if tag_pose is not None else genpy.Time(),
        **{key: int(getattr(status, key)) for key in ROBOT_COUNTERS},
    )


def robot_status_to_dict(msg: RobotStatus) -> dict:
    """drvs/RobotStatus -> the fields of :class:`drvs.robot.robot_status.RobotStatus` as plain
    values for the observers (``position`` and ``goal`` lists, ``None`` for what is unknown),
    with ``heading`` (``position.theta``); ``tag_pose`` and ``tag_stamp`` only when seen."""
    status = {
        'state': msg.state_name,
        'reason': msg.reason,
        'stamp': msg.header.stamp.to_sec(),
        'distance_to_goal': _known(msg.distance_to_goal),
        'position': [msg.position.x, msg.position.y] if msg.has_position else None,
        'heading': _known(msg.position.theta),
        'goal': [msg.goal.x, msg.goal.y] if msg.has_goal else None,
        **{key: getattr(msg, key) for key in ROBOT_COUNTERS},
        'refused': dict(zip(msg.refused_statuses, msg.refused_counts, strict=True)),
        'vision_systems': dict(zip(msg.roles, msg.role_vision_systems, strict=True)),
    }
    if not math.isnan(msg.tag_pose.x):
        status['tag_pose'] = [msg.tag_pose.x, msg.tag_pose.y, msg.tag_pose.theta]
        status['tag_stamp'] = msg.tag_stamp.to_sec()
    return status


# -- /robot/pose, /robot/path, /robot/map -----------------------------------------------------------
def pose_to_msg(position: Sequence[float], heading: float | None, stamp: float) -> PoseStamped:
    """Where the robot believes it is -> geometry_msgs/PoseStamped in ``map``; facing +x when no
    camera saw its heading."""
    msg = PoseStamped(header=header(stamp))
    msg.pose.position.x, msg.pose.position.y = position
    yaw = heading or 0.0
    msg.pose.orientation.z, msg.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    return msg


def path_to_msg(points: Iterable[Sequence[float]], stamp: float) -> Path:
    """The robot's plan (x, y points) -> nav_msgs/Path in ``map``."""
    msg = Path(header=header(stamp))
    for x, y in points:
        pose = PoseStamped(header=msg.header)
        pose.pose.position.x, pose.pose.position.y = x, y
        pose.pose.orientation.w = 1.0
        msg.poses.append(pose)
    return msg


def occupancy_to_msg(values, resolution: float, stamp: float) -> OccupancyGrid:
    """The robot's grid (rows x cols of OccupancyGrid values, row 0 at y = 0) -> nav_msgs/OccupancyGrid
    with its origin at (0, 0) of ``map``."""
    msg = OccupancyGrid(header=header(stamp))
    msg.info.resolution = resolution
    msg.info.height, msg.info.width = values.shape
    msg.info.origin = Pose()
    msg.info.origin.orientation.w = 1.0
    msg.data = values.ravel().tolist()
    return msg


# -- /world_sim/poses --------------------------------------------------------------------------------
def body_poses_to_msg(poses: Mapping[str, Sequence[float]], stamp: float) -> BodyPoses:
    """{name: (x, y, yaw)} of the state at ``stamp`` -> drvs/BodyPoses (names in the given order)."""
    return BodyPoses(
        header=header(stamp),
        names=list(poses),
        poses=[Pose2D(float(x), float(y), float(yaw)) for x, y, yaw in poses.values()],
    )


def body_poses_from_msg(msg: BodyPoses) -> tuple[float, dict[str, tuple[float, float, float]]]:
    """drvs/BodyPoses -> (stamp in seconds, {name: (x, y, yaw)}).

    :raises ValueError: when ``names`` and ``poses`` differ in length.
    """
    if len(msg.names) != len(msg.poses):
        raise ValueError(f'names: {len(msg.names)} name(s) for {len(msg.poses)} pose(s)')
    return msg.header.stamp.to_sec(), {
        name: (pose.x, pose.y, pose.theta) for name, pose in zip(msg.names, msg.poses, strict=True)
    }
