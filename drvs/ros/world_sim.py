"""The world_sim node: the simulated world, the only holder of ground truth.

It builds a world file in PyBullet (DIRECT), walks every ``human`` object around
its waypoint loop at its speed, drives each robot's body from ``/<name>/cmd_vel``
(x, y velocity in ``map``, capped at the robot's speed, stopping at obstacles, the
other robots and the floor's edge, counting contacts; see :mod:`drvs.sim.simulation`)
and publishes every body's pose.

Time: in real time (``/use_sim_time`` unset or false) everything is stamped with the
wall time, as by any node. With ``/use_sim_time`` true, world_sim is the world's clock:
every step it publishes ``/clock``, which starts at the wall time world_sim started at
and advances by the wall time elapsed × ``~real_time_factor`` (at most
:data:`drvs.sim.simulation.MAX_STEP` per step), and stamps everything with it; every other
node's ``rospy.get_time()`` follows it (their node_main waits for the first ``/clock``
before it builds them). world_sim keeps its own pacing and stamps on its own
:class:`drvs.sim.simulation.StepClock` from the wall clock, never on rospy's time, which in
this node too would follow the ``/clock`` it publishes and would deadlock a wait on it.
A ``real_time_factor`` below 1 without ``/use_sim_time`` is refused: the other nodes
would run in real time.

Parameters: the fields of :class:`WorldSimSettings`, each declared with its default,
meaning and range; README.md's world_sim table is generated from them.

Topics:

``/<name>/cmd_vel`` (geometry_msgs/Twist, subscribed), for each robot of the world
    ``linear.x``, ``linear.y``: the robot's velocity in ``map``, m/s. ``/robot/cmd_vel``
    in the single-robot worlds, whose robot is called ``robot``.
``/clock`` (rosgraph_msgs/Clock, every step, only with ``/use_sim_time`` true)
    The simulated time (above).
``~poses`` = ``/world_sim/poses`` (drvs/BodyPoses, every step)
    ``header.stamp`` (the state's time), ``names`` and ``poses`` (x, y, theta = yaw) of
    every body (each robot, each station and each object). For the vision systems and
    sim_camera, which render the world from it; robots never read it.
``/tf``: ``map`` -> ``<body name>`` of each robot and each human (every step); ``/tf_static``
    of the bodies that never move (once, latched)
    The same poses for RViz, one frame per body on the floor at its centre, x along its
    heading (:func:`drvs.ros.tf_frames.body_transform`), stamped as ``~poses``.
``~ground_truth`` = ``/world_sim/ground_truth`` (std_msgs/String, JSON, every step)
    ``{"stamp", "time" (simulated seconds since the start), "robot": {"position": [x, y],
    "yaw", "command": [vx, vy]}, "contacts" (count of new touches so far), "touching"
    (names, ``floor_edge`` for the edge), "blocked", "travelled" (m), "objects",
    "robots": {name: {"position", "yaw", "command", "contacts", "touching", "blocked",
    "travelled"}}}``: the top-level robot keys are the first robot's, ``robots`` has
    every robot's. For tests and the scenario recorder only: a robot must never
    subscribe to it. It stays JSON on purpose: it is an observer's view of the
    simulation, not part of the DRVS interface, and its shape follows
    :meth:`drvs.sim.simulation.Simulation.ground_truth`.

The simulation loop is guarded (:class:`drvs.common.guard.LoopGuard`): a step that raises
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
from rosgraph_msgs.msg import Clock
from std_msgs.msg import String

from drvs.common.guard import RESTART, LoopGuard
from drvs.common.settings import POSITIVE, REQUIRED, Range, Settings, param
from drvs.msg import BodyPoses
from drvs.ros.messages import body_poses_to_msg, to_time
from drvs.ros.tf_frames import body_transform
from drvs.sim.simulation import Simulation, StepClock
from drvs.sim.world_file import load_world

FACTOR = Range(lambda value: 0 < value <= 1, 'must be above 0 and at most 1', '0 < x ≤ 1')


@dataclass(frozen=True)
class WorldSimSettings(Settings):
    world: str = param(REQUIRED, 'the world file')
    rate: float = param(30.0, 'simulation steps and publications per second', unit='Hz', check=POSITIVE)
    cmd_timeout: float = param(
        0.5, 'a robot stops after this long without a message on its `cmd_vel`', unit='s', check=POSITIVE
    )
    real_time_factor: float | None = param(
        None,
        'simulated seconds per wall second; below 1 needs `/use_sim_time` true (world_sim then publishes '
        '`/clock`)',
        check=FACTOR,
        default_text="the world's `real_time_factor` (1)",
    )


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
        self._stopping = threading.Event()
        self.guard = LoopGuard(on_fatal=lambda reason: rospy.signal_shutdown(reason), stop=self._stopping)

    def start(self) -> None:
        self.simulation = Simulation(self.world)
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
        self.guard.spawn(self._loop, 'simulation', RESTART)
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
        while not self._stopping.is_set():
            self._tick()
            next_tick += period
            delay = next_tick - time.monotonic()
            if delay < 0:  # fell behind: do not try to catch up (MAX_STEP bounds the step)
                next_tick, delay = time.monotonic(), 0.0
            self._stopping.wait(delay)

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
        self._stopping.set()
        for thread in self.guard.threads:
            thread.join(2.0)
        with self._lock:
            if self.simulation is not None:
                self.simulation.scene.close()
                self.simulation = None
