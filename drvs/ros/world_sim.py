"""The world_sim node: the simulated world, the only holder of ground truth.

It builds a world file in PyBullet (DIRECT), walks every ``human`` object around
its waypoint loop at its speed, drives the robot's body from ``/robot/cmd_vel``
(x, y velocity in ``map``, capped at the robot's speed, stopping at obstacles and
the floor's edge, counting contacts; see :mod:`drvs.simulation`) and publishes
every body's pose.

Parameters: the fields of :class:`WorldSimSettings`, each declared with its default,
meaning and range; README.md's world_sim table is generated from them.

Topics:

``/robot/cmd_vel`` (geometry_msgs/Twist, subscribed)
    ``linear.x``, ``linear.y``: the robot's velocity in ``map``, m/s.
``~poses`` = ``/world_sim/poses`` (drvs/BodyPoses, every step)
    ``header.stamp`` (the state's time), ``names`` and ``poses`` (x, y, theta = yaw) of
    every body (``robot``, ``station`` and each object). For the vision systems and
    sim_camera, which render the world from it; robots never read it.
``/tf``: ``map`` -> ``<body name>`` of the robot and each human (every step); ``/tf_static``
    of the bodies that never move (once, latched)
    The same poses for RViz, one frame per body on the floor at its centre, x along its
    heading (:func:`drvs.ros.tf_frames.body_transform`), stamped as ``~poses``.
``~ground_truth`` = ``/world_sim/ground_truth`` (std_msgs/String, JSON, every step)
    ``{"stamp", "time" (simulated seconds), "robot": {"position": [x, y], "yaw",
    "command": [vx, vy]}, "contacts" (count of new touches so far), "touching"
    (names, ``floor_edge`` for the edge), "blocked", "travelled" (m), "objects"}``.
    For tests and the scenario recorder only: a robot must never subscribe to it. It
    stays JSON on purpose: it is an observer's view of the simulation, not part of the
    DRVS interface, and its shape follows :meth:`drvs.simulation.Simulation.ground_truth`.

The simulation loop is guarded (:class:`drvs.guard.LoopGuard`): a step that raises
is logged with its traceback and the loop restarts; one that keeps failing shuts
the node down with exit code 1.
"""

from __future__ import annotations

import json
import math
import threading
import time
from dataclasses import dataclass

import rospy
import tf2_ros
from geometry_msgs.msg import Twist
from std_msgs.msg import String

from drvs.guard import RESTART, LoopGuard
from drvs.msg import BodyPoses
from drvs.ros.messages import body_poses_to_msg, to_time
from drvs.ros.tf_frames import body_transform
from drvs.settings import POSITIVE, REQUIRED, Settings, param
from drvs.simulation import Simulation
from drvs.world import load_world

MAX_STEP = 0.2
"""Seconds; a longer gap between timer ticks (a stalled machine) is simulated as this."""


@dataclass(frozen=True)
class WorldSimSettings(Settings):
    world: str = param(REQUIRED, 'the world file')
    rate: float = param(30.0, 'simulation steps and publications per second', unit='Hz', check=POSITIVE)
    cmd_timeout: float = param(
        0.5, 'the robot stops after this long without a `/robot/cmd_vel` message', unit='s', check=POSITIVE
    )


class WorldSimNode:
    """Simulation + topics; :meth:`start` builds the world and starts the timer."""

    def __init__(self, settings: WorldSimSettings):
        self.world = load_world(settings.world)
        self.rate = settings.rate
        self.cmd_timeout = settings.cmd_timeout
        self.simulation: Simulation | None = None
        self._lock = threading.Lock()  # guards the simulation and the command time
        self._last_command = None
        self._last_tick = None
        self._stopping = threading.Event()
        self.guard = LoopGuard(on_fatal=lambda reason: rospy.signal_shutdown(reason), stop=self._stopping)

    def start(self) -> None:
        self.simulation = Simulation(self.world)
        self.poses_pub = rospy.Publisher('~poses', BodyPoses, queue_size=2)
        self.truth_pub = rospy.Publisher('~ground_truth', String, queue_size=2)
        self.tf_broadcaster = tf2_ros.TransformBroadcaster()
        # Only the robot and the humans move: the rest go on /tf_static once, not 30 times a second.
        self.moving = {self.simulation.robot_name, *self.simulation.loops}
        self.static_tf_broadcaster = tf2_ros.StaticTransformBroadcaster()
        stamp = to_time(rospy.get_time())
        self.static_tf_broadcaster.sendTransform(
            [body_transform(name, pose, stamp) for name, pose in self.simulation.poses().items()
             if name not in self.moving]
        )  # fmt: skip
        rospy.Subscriber('/robot/cmd_vel', Twist, self._on_cmd_vel, queue_size=2)
        self._last_tick = rospy.get_time()
        self.guard.spawn(self._loop, 'simulation', RESTART)
        rospy.on_shutdown(self.stop)
        rospy.loginfo(
            '%s: world %s with %d object(s), %d moving; %.0f Hz',
            rospy.get_name(),
            self.world.path,
            len(self.world.objects),
            len(self.simulation.loops),
            self.rate,
        )

    def _on_cmd_vel(self, message: Twist) -> None:
        vx, vy = message.linear.x, message.linear.y
        if not (math.isfinite(vx) and math.isfinite(vy)):
            rospy.logwarn_throttle(
                5.0, '%s: /robot/cmd_vel not finite (%r, %r): stopping', rospy.get_name(), vx, vy
            )
        with self._lock:
            if self.simulation is None:
                return
            self.simulation.set_command(vx, vy)
            self._last_command = rospy.get_time()

    def _loop(self) -> None:
        period = 1.0 / self.rate
        next_tick = time.monotonic()
        while not self._stopping.is_set():
            self._tick()
            next_tick += period
            delay = next_tick - time.monotonic()
            if delay < 0:  # fell behind: do not try to catch up (MAX_STEP bounds the step)
                next_tick, delay = time.monotonic(), 0.0
            self._stopping.wait(delay)

    def _tick(self) -> None:
        now = rospy.get_time()
        with self._lock:
            if self.simulation is None:  # stopped
                return
            dt = min(max(now - self._last_tick, 0.0), MAX_STEP)
            self._last_tick = now
            if self._last_command is not None and now - self._last_command > self.cmd_timeout:
                self.simulation.set_command(0.0, 0.0)
                self._last_command = None
            self.simulation.step(dt)
            poses = self.simulation.poses()
            truth = self.simulation.ground_truth()
        self.poses_pub.publish(body_poses_to_msg(poses, now))
        stamp = to_time(now)  # the stamp of ~poses: the state's time
        self.tf_broadcaster.sendTransform([body_transform(name, poses[name], stamp) for name in self.moving])
        self.truth_pub.publish(String(json.dumps({'stamp': now, **truth})))

    def stop(self) -> None:
        self._stopping.set()
        for thread in self.guard.threads:
            thread.join(2.0)
        with self._lock:
            if self.simulation is not None:
                self.simulation.scene.close()
                self.simulation = None
