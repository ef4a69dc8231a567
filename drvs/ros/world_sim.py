"""The world_sim node: the simulated world, the only holder of ground truth.

It builds a world file in PyBullet (DIRECT), walks every ``human`` object around
its waypoint loop at its speed, drives the robot's body from ``/robot/cmd_vel``
(x, y velocity in ``map``, capped at the robot's speed, stopping at obstacles and
the floor's edge, counting contacts; see :mod:`drvs.simulation`) and publishes
every body's pose.

Parameters (private):

``~world`` (str, required)
    The world file.
``~rate`` (float, default 30)
    Steps and publications per second.
``~cmd_timeout`` (float, default 0.5)
    Seconds without a ``/robot/cmd_vel`` message after which the robot stops.

Topics:

``/robot/cmd_vel`` (geometry_msgs/Twist, subscribed)
    ``linear.x``, ``linear.y``: the robot's velocity in ``map``, m/s.
``~poses`` = ``/world_sim/poses`` (drvs/BodyPoses, every step)
    ``header.stamp`` (the state's time), ``names`` and ``poses`` (x, y, theta = yaw) of
    every body (``robot``, ``station`` and each object). For the vision systems and
    sim_camera, which render the world from it; robots never read it.
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

import rospy
from geometry_msgs.msg import Twist
from std_msgs.msg import String

from drvs.guard import RESTART, LoopGuard
from drvs.msg import BodyPoses
from drvs.ros.messages import body_poses_to_msg
from drvs.simulation import Simulation
from drvs.world import load_world

MAX_STEP = 0.2
"""Seconds; a longer gap between timer ticks (a stalled machine) is simulated as this."""


class WorldSimNode:
    """Simulation + topics; :meth:`start` builds the world and starts the timer."""

    def __init__(self, world_path: str, rate: float = 30.0, cmd_timeout: float = 0.5):
        if not rate > 0:
            raise ValueError(f'~rate: must be positive, got {rate}')
        self.world = load_world(world_path)
        self.rate = rate
        self.cmd_timeout = cmd_timeout
        self.simulation: Simulation | None = None
        self._lock = threading.Lock()  # guards the simulation and the command time
        self._last_command = None
        self._last_tick = None
        self._stopping = threading.Event()
        self.guard = LoopGuard(on_fatal=lambda reason: rospy.signal_shutdown(reason), stop=self._stopping)

    @classmethod
    def from_params(cls) -> WorldSimNode:
        return cls(
            rospy.get_param('~world'),
            rate=float(rospy.get_param('~rate', 30.0)),
            cmd_timeout=float(rospy.get_param('~cmd_timeout', 0.5)),
        )

    def start(self) -> None:
        self.simulation = Simulation(self.world)
        self.poses_pub = rospy.Publisher('~poses', BodyPoses, queue_size=2)
        self.truth_pub = rospy.Publisher('~ground_truth', String, queue_size=2)
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
        self.truth_pub.publish(String(json.dumps({'stamp': now, **truth})))

    def stop(self) -> None:
        self._stopping.set()
        for thread in self.guard.threads:
            thread.join(2.0)
        with self._lock:
            if self.simulation is not None:
                self.simulation.scene.close()
                self.simulation = None
