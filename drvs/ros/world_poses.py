"""The newest state of the simulated world, as world_sim publishes it on ``/world_sim/poses``.

Shared by everything that renders the world: a vision system in render mode and sim_camera.
"""

from __future__ import annotations

import threading

import rospy

from drvs.msg import BodyPoses
from drvs.ros.messages import body_poses_from_msg


class LatestPoses:
    """Subscribes to a drvs/BodyPoses topic and keeps only its newest message, decoded."""

    def __init__(self, topic: str):
        self.topic = topic
        self._lock = threading.Lock()  # guards _stamp and _poses
        self._stamp: float | None = None
        self._poses: dict | None = None

    def start(self) -> None:
        rospy.Subscriber(self.topic, BodyPoses, self._on_poses, queue_size=1)

    def _on_poses(self, message: BodyPoses) -> None:
        try:
            stamp, poses = body_poses_from_msg(message)
        except ValueError as error:
            rospy.logwarn_throttle(10.0, '%s: unreadable poses message: %s', rospy.get_name(), error)
            return
        with self._lock:
            self._stamp, self._poses = stamp, poses

    def latest(self) -> tuple[float | None, dict | None]:
        """(stamp of the state, {name: (x, y, yaw)}); (None, None) until world_sim has published."""
        with self._lock:
            return self._stamp, self._poses
