"""world_sim's core: humans walking their waypoint loops, the robot driven by velocity commands.

The robot moves kinematically: its velocity command (x, y in ``map``) is capped at
its speed, and a step that would push it into an obstacle (any object, static or
human) or over the floor's edge is shortened to the last free position, so it
stops at obstacles instead of passing through them. Each new touch of an
obstacle counts one contact. A human walking into the robot does not stop (humans
follow their loop regardless); it counts as a contact too, and the robot may then
move in any direction that does not push it deeper.

Contacts are PyBullet's closest-point queries between the boxes of a :class:`Scene`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

from drvs.scene import Scene
from drvs.world import World

log = logging.getLogger('rosout.' + __name__)

TOUCH = 0.002
"""Bodies closer than this (metres) touch."""
FLOOR_EDGE = 'floor_edge'


def loop_of(start, waypoints) -> list[tuple[float, float]]:
    """The closed loop a moving body follows: its start, then each waypoint, then back to the start.

    Consecutive repeats are dropped, so a start equal to the first waypoint is not doubled.

    >>> loop_of((0, 0), [(0, 0), (2, 0)])
    [(0.0, 0.0), (2.0, 0.0)]
    """
    loop: list[tuple[float, float]] = []
    for point in [start, *waypoints]:
        point = (float(point[0]), float(point[1]))
        if not loop or point != loop[-1]:
            loop.append(point)
    if len(loop) > 1 and loop[-1] == loop[0]:
        loop.pop()
    return loop


def position_on_loop(loop, speed: float, elapsed: float, closed: bool = True) -> tuple[float, float]:
    """Where a body that started at ``loop[0]`` is after ``elapsed`` seconds at ``speed`` m/s.

    With ``closed`` false the body walks the points once and stays at the last.

    >>> position_on_loop([(0, 0), (2, 0)], 1.0, 3.0)  # out 2 m, back 1 m
    (1.0, 0.0)
    >>> position_on_loop([(0, 0), (2, 0)], 1.0, 3.0, closed=False)  # out 2 m, then stands
    (2.0, 0.0)
    """
    if len(loop) < 2 or speed <= 0:
        return loop[0]
    legs = [(loop[i], loop[(i + 1) % len(loop)]) for i in range(len(loop) if closed else len(loop) - 1)]
    lengths = [math.dist(a, b) for a, b in legs]
    total = sum(lengths)
    if not closed:
        distance = min(speed * max(elapsed, 0.0), total)
        if distance >= total:
            return (float(loop[-1][0]), float(loop[-1][1]))
    else:
        distance = (speed * max(elapsed, 0.0)) % total
    for (a, b), length in zip(legs, lengths, strict=True):
        if distance <= length:
            t = distance / length if length else 0.0
            return (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]))
        distance -= length
    return loop[0]


def mount_position(camera, elapsed: float) -> tuple[float, float]:
    """Where a camera on a moving mount (world file ``waypoints`` + ``speed``) is after ``elapsed`` s."""
    start = camera.position[:2]
    if not camera.moving:
        return (float(start[0]), float(start[1]))
    return position_on_loop(loop_of(start, camera.waypoints), camera.speed, elapsed)


@dataclass
class RobotState:
    x: float
    y: float
    yaw: float
    command: tuple[float, float] = (0.0, 0.0)
    contacts: int = 0
    touching: set[str] = field(default_factory=set)
    blocked: bool = False
    travelled: float = 0.0


class Simulation:
    """The moving parts of a world: call :meth:`step` with the time since the last step."""

    def __init__(self, world: World, scene: Scene | None = None):
        self.world = world
        self.scene = scene if scene is not None else Scene(world)
        self.time = 0.0
        robot = world.robot
        self.robot_name = robot.name
        self.robot = RobotState(robot.position[0], robot.position[1], robot.yaw)
        self.obstacles = [body.name for body in world.objects]
        self.walkers = [body for body in world.objects if body.moving]
        self.loops = {body.name: loop_of(body.position, body.waypoints) for body in self.walkers}
        self.robot_moved_at: float | None = None  # simulated time of the first non-zero command
        self.robot.touching = self._touching()

    # -- commands ------------------------------------------------------------------------------
    def set_command(self, vx: float, vy: float) -> None:
        """The robot's velocity in ``map`` (m/s); capped at the robot's speed, NaN means stop."""
        if not (math.isfinite(vx) and math.isfinite(vy)):
            vx = vy = 0.0
        norm = math.hypot(vx, vy)
        if norm > self.world.robot.speed:
            vx, vy = vx * self.world.robot.speed / norm, vy * self.world.robot.speed / norm
        if norm > 0 and self.robot_moved_at is None:
            self.robot_moved_at = self.time
        self.robot.command = (vx, vy)

    # -- stepping ------------------------------------------------------------------------------
    def step(self, dt: float) -> None:
        """Advance ``dt`` seconds: humans first, then the robot."""
        if dt <= 0:
            return
        self.time += dt
        for body in self.walkers:
            if body.wait_for_robot:
                elapsed = 0.0 if self.robot_moved_at is None else self.time - self.robot_moved_at
            else:
                elapsed = self.time
            x, y = position_on_loop(self.loops[body.name], body.speed, elapsed, body.loop)
            self.scene.set_pose(body.name, x, y, self.scene.pose(body.name)[2])
        self._move_robot(dt)

    def _penetration(self, x: float, y: float) -> dict[str, float]:
        """Depth by which the robot at (x, y) would overlap each obstacle or the floor edge (> 0)."""
        self.scene.set_pose(self.robot_name, x, y, self.robot.yaw)
        depth = {
            name: -d
            for name, d in self.scene.distances(self.robot_name, self.obstacles, 0.0).items()
            if d < 0
        }
        edge = self._beyond_edge(x, y)
        if edge > 0:
            depth[FLOOR_EDGE] = edge
        return depth

    def _beyond_edge(self, x: float, y: float) -> float:
        """How far the robot's footprint at (x, y) reaches over the floor's edge (<= 0: not)."""
        size, yaw = self.world.robot.size, self.robot.yaw
        c, s = abs(math.cos(yaw)), abs(math.sin(yaw))
        hx = (c * size[0] + s * size[1]) / 2
        hy = (s * size[0] + c * size[1]) / 2
        width, height = self.world.floor_size
        return max(hx - x, x + hx - width, hy - y, y + hy - height)

    def _allowed(self, x: float, y: float, current: dict[str, float]) -> bool:
        return all(d <= current.get(name, 0.0) + 1e-9 for name, d in self._penetration(x, y).items())

    def _move_robot(self, dt: float) -> None:
        state = self.robot
        start = (state.x, state.y)
        current = self._penetration(*start)
        vx, vy = state.command
        goal = (start[0] + vx * dt, start[1] + vy * dt)
        state.blocked = False
        if goal != start and not self._allowed(*goal, current):
            state.blocked = True
            low, high = 0.0, 1.0  # largest free fraction of the step, by bisection
            for _ in range(12):
                middle = (low + high) / 2
                if self._allowed(start[0] + middle * vx * dt, start[1] + middle * vy * dt, current):
                    low = middle
                else:
                    high = middle
            goal = (start[0] + low * vx * dt, start[1] + low * vy * dt)
        state.travelled += math.dist(start, goal)
        state.x, state.y = goal
        self.scene.set_pose(self.robot_name, state.x, state.y, state.yaw)
        touching = self._touching()
        if state.blocked:
            touching |= set(self._penetration(goal[0] + vx * dt, goal[1] + vy * dt))
            self.scene.set_pose(self.robot_name, state.x, state.y, state.yaw)
        new = touching - state.touching
        if new:
            state.contacts += len(new)
            log.info('robot contact with %s at (%.3f, %.3f)', ', '.join(sorted(new)), state.x, state.y)
        state.touching = touching

    def _touching(self) -> set[str]:
        touching = set(self.scene.distances(self.robot_name, self.obstacles, TOUCH))
        if self._beyond_edge(self.robot.x, self.robot.y) > -TOUCH:
            touching.add(FLOOR_EDGE)
        return touching

    # -- state ---------------------------------------------------------------------------------
    def poses(self) -> dict[str, tuple[float, float, float]]:
        """Every body's pose {name: (x, y, yaw)}: robot, station and objects."""
        return self.scene.poses()

    def ground_truth(self) -> dict:
        """The robot's true state and every pose, for tests and the scenario recorder only."""
        state = self.robot
        return {
            'time': self.time,
            'robot': {'position': [state.x, state.y], 'yaw': state.yaw, 'command': list(state.command)},
            'contacts': state.contacts,
            'touching': sorted(state.touching),
            'blocked': state.blocked,
            'travelled': state.travelled,
            'objects': {name: list(pose) for name, pose in self.poses().items()},
        }
