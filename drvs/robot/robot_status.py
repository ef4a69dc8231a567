"""The blind robot's status, as it publishes it on ``~status`` (drvs/RobotStatus) every tick.

The controller fills what it decides (:meth:`drvs.robot.controller.Controller.status`), the node
adds its requests, callbacks and map; :func:`drvs.ros.messages.robot_status_to_msg` makes the
message. The fields are the message's, documented in msg/RobotStatus.msg. No ROS here.
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ['COUNTERS', 'RobotStatus']

COUNTERS = (
    'replans',
    'path_length',
    'requests',
    'watch_calls',
    'watches',
    'failed_requests',
    'callbacks',
    'callback_bytes',
    'refused_callbacks',
    'superseded',
    'obstacles',
)
"""The status's counters, in the message's order."""


@dataclass
class RobotStatus:
    """The robot's status at ``stamp`` (ROS seconds); ``None`` where it does not know."""

    state: str  # a drvs.robot.controller state name: localising, moving, ..., failed
    stamp: float = 0.0
    reason: str = ''  # why it failed
    distance_to_goal: float | None = None
    position: tuple[float, float] | None = None  # where it believes it is (predicted between fixes)
    goal: tuple[float, float] | None = None  # the station's position
    replans: int = 0
    path_length: int = 0  # points in the current plan
    requests: int = 0  # calls sent to the server, watch calls included
    watch_calls: int = 0
    watches: int = 0  # standing now
    failed_requests: int = 0  # calls with no response
    refused: dict[str, int] = field(default_factory=dict)  # refusals per status name
    callbacks: int = 0
    callback_bytes: int = 0  # their serialized size
    refused_callbacks: int = 0
    superseded: int = 0
    obstacles: int = 0  # obstacle outlines in the current map
    vision_systems: dict[str, int] = field(default_factory=dict)  # role -> reached by its last call
    tag_pose: tuple[float, float, float] | None = None  # x, y, heading of its newest tag fix, as seen
    tag_stamp: float = 0.0  # when the frames of tag_pose were taken
