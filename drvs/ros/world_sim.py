"""The world_sim node: the simulated world in PyBullet, the only holder of ground truth.

It moves the humans and the robots (from their ``cmd_vel``), publishes every body's pose and, on
simulated time, ``/clock``. Simulation glue (it imports pybullet). Parameters, topics and the
clock are in docs/nodes/world_sim.md.
"""

from __future__ import annotations

import json
import math
import threading
import time

import rospy
import tf2_ros
from geometry_msgs.msg import Twist
from rosgraph_msgs.msg import Clock
from std_msgs.msg import String

from drvs.msg import BodyPoses
from drvs.ros.messages import body_poses_to_msg, to_time
from drvs.ros.node import NodeScaffold
from drvs.ros.tf_frames import body_transform
from drvs.sim.params import WorldSimSettings
from drvs.sim.simulation import Simulation, StepClock
from drvs.sim.world_file import load_world


class WorldSimNode:
    """Simulation + topics; :meth:`start` builds the world and starts the timer."""

    def __init__(self, settings: WorldSimSettings):
        self.world = load_world(settings.world)
        self.rate = settings.rate
        self.cmd_timeout = settings.cmd_timeout
        given = settings.real_time_factor is not None
        self.real_time_factor = settings.real_time_factor if given else self.world.real_time_factor
        self.sim_time = bool(rospy.get_param('/use_sim_time', False))
        if self.real_time_factor != 1 and not self.sim_time:
            source = '~real_time_factor' if given else f'the world file {self.world.path}'
            raise ValueError(
                f'real_time_factor {self.real_time_factor:g} (from {source}) runs the world on simulated '
                'time: set /use_sim_time true before starting the nodes (`rosparam set /use_sim_time true`), '
                'or run at real_time_factor 1'
            )
        self.simulation: Simulation | None = None
        self.clock: StepClock | None = None
        self._lock = threading.Lock()  # guards the simulation, the clock and the command times
        self._last_command: dict[str, float] = {}  # robot -> when its last command came
        self.node = NodeScaffold(None)  # no /diagnostics: the simulated world is not part of DRVS

    def start(self) -> None:
        self.simulation = Simulation(self.world)
        # Its own pacing and stamps, from the wall clock: rospy's time would follow the /clock this
        # node publishes, and a wait on it would deadlock.
        self.clock = StepClock(time.time, self.real_time_factor, simulated=self.sim_time)
        self.clock_pub = rospy.Publisher('/clock', Clock, queue_size=10) if self.sim_time else None
        self.poses_pub = rospy.Publisher('~poses', BodyPoses, queue_size=2)
        self.truth_pub = rospy.Publisher('~ground_truth', String, queue_size=2)
        self.tf_broadcaster = tf2_ros.TransformBroadcaster()
        # Only the robots and the humans move: the rest go on /tf_static once, not 30 times a second.
        self.moving = {*self.simulation.robots, *self.simulation.loops}
        self.static_tf_broadcaster = tf2_ros.StaticTransformBroadcaster()
        stamp = to_time(self.clock.now())
        self.static_tf_broadcaster.sendTransform(
            [body_transform(name, pose, stamp) for name, pose in self.simulation.poses().items()
             if name not in self.moving]
        )  # fmt: skip
        for name in self.simulation.robots:
            rospy.Subscriber(f'/{name}/cmd_vel', Twist, self._on_cmd_vel, callback_args=name, queue_size=2)
        self.node.spawn(self._loop, 'simulation')
        rospy.on_shutdown(self.stop)
        rospy.loginfo(
            '%s: world %s with %d robot(s), %d object(s), %d moving; %.0f Hz, %s',
            rospy.get_name(),
            self.world.path,
            len(self.simulation.robots),
            len(self.world.objects),
            len(self.simulation.loops),
            self.rate,
            f'simulated time on /clock at {self.real_time_factor:g}x' if self.sim_time else 'real time',
        )

    def _on_cmd_vel(self, message: Twist, robot: str) -> None:
        vx, vy = message.linear.x, message.linear.y
        if not (math.isfinite(vx) and math.isfinite(vy)):
            rospy.logwarn_throttle(
                5.0, '%s: /%s/cmd_vel not finite (%r, %r): stopping', rospy.get_name(), robot, vx, vy
            )
        with self._lock:
            if self.simulation is None:
                return
            self.simulation.set_command(vx, vy, robot)
            self._last_command[robot] = self.clock.now()

    def _loop(self) -> None:
        period = 1.0 / self.rate
        next_tick = time.monotonic()
        while not self.node.stopped:
            self._tick()
            next_tick += period
            delay = next_tick - time.monotonic()
            if delay < 0:  # fell behind: do not try to catch up (MAX_STEP bounds the step)
                next_tick, delay = time.monotonic(), 0.0
            self.node.wait(delay)

    def _tick(self) -> None:
        with self._lock:
            if self.simulation is None:  # stopped
                return
            now, dt = self.clock.tick()
            for robot, last in list(self._last_command.items()):
                if now - last > self.cmd_timeout:
                    self.simulation.set_command(0.0, 0.0, robot)
                    del self._last_command[robot]
            self.simulation.step(dt)
            poses = self.simulation.poses()
            truth = self.simulation.ground_truth()
        stamp = to_time(now)  # the state's time: /clock, and the stamp of everything published with it
        if self.clock_pub is not None:
            self.clock_pub.publish(Clock(clock=stamp))
        self.poses_pub.publish(body_poses_to_msg(poses, now))
        self.tf_broadcaster.sendTransform([body_transform(name, poses[name], stamp) for name in self.moving])
        self.truth_pub.publish(String(json.dumps({'stamp': now, **truth})))

    def stop(self) -> None:
        self.node.stop(join=2.0)
        with self._lock:
            if self.simulation is not None:
                self.simulation.scene.close()
                self.simulation = None
