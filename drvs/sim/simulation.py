"""world_sim's core: humans walking their waypoint loops, the robots driven by velocity commands.

Robots move kinematically and stop at obstacles, other robots and the floor's edge,
counting contacts (PyBullet closest-point queries between a :class:`Scene`'s boxes); the
step clock paces the world. The rules: docs/nodes/world_sim.md ("Motion", "Time").
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from drvs.sim.scene import Scene
from drvs.sim.world import Body, Camera, World

log = logging.getLogger('rosout.' + __name__)

TOUCH = 0.002
"""Bodies closer than this (metres) touch."""
FLOOR_EDGE = 'floor_edge'
MAX_STEP = 0.2
"""Simulated seconds; a longer step (a stalled machine) is simulated as this."""


def loop_of(start: Sequence[float], waypoints: Sequence[Sequence[float]]) -> list[tuple[float, float]]:
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


def position_on_loop(
    loop: Sequence[tuple[float, float]], speed: float, elapsed: float, closed: bool = True
) -> tuple[float, float]:
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


def mount_position(camera: Camera, elapsed: float) -> tuple[float, float]:
    """Where a camera on a moving mount (world file ``waypoints`` + ``speed``) is after ``elapsed`` s."""
    start = camera.position[:2]
    if not camera.moving:
        return (float(start[0]), float(start[1]))
    return position_on_loop(loop_of(start, camera.waypoints), camera.speed, elapsed)


class StepClock:
    """The time world_sim steps and stamps by, read from a wall clock (``wall``, seconds since the epoch).

    In real time it is the wall time itself. ``simulated`` (ROS simulated time, published on
    ``/clock``) it starts at the wall time of its creation and each :meth:`tick` advances it by the
    wall time elapsed since the last tick × ``real_time_factor``: at 0.5, one simulated second takes
    two. Either way a step is at most :data:`MAX_STEP` simulated seconds, so a stalled machine
    does not make bodies jump.

    >>> walls = iter([100.0, 100.1, 110.0])
    >>> clock = StepClock(lambda: next(walls), real_time_factor=0.5, simulated=True)
    >>> [round(t, 6) for t in clock.tick()]  # (time, step): 0.1 wall seconds are 0.05 simulated ones
    [100.05, 0.05]
    >>> [round(t, 6) for t in clock.tick()]  # 9.9 wall seconds stalled: one step of MAX_STEP
    [100.25, 0.2]
    """

    def __init__(
        self, wall: Callable[[], float], real_time_factor: float = 1.0, simulated: bool = False
    ) -> None:
        if not 0 < real_time_factor <= 1 or (real_time_factor != 1 and not simulated):
            raise ValueError(f'real_time_factor: {real_time_factor!r} needs simulated time (0 < factor <= 1)')
        self.wall = wall
        self.real_time_factor = real_time_factor
        self.simulated = simulated
        self._wall = wall()
        self._time = self._wall

    def now(self) -> float:
        """The current time: the wall time in real time, else the simulated time of the last tick."""
        return self._time if self.simulated else self.wall()

    def tick(self) -> tuple[float, float]:
        """(the time now, the step since the last tick), both in seconds of this clock."""
        wall = self.wall()
        step = min(max(wall - self._wall, 0.0) * self.real_time_factor, MAX_STEP)
        self._wall = wall
        self._time = self._time + step if self.simulated else wall
        return self._time, step


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

    def truth(self) -> dict:
        """This robot's part of :meth:`Simulation.ground_truth`."""
        return {
            'position': [self.x, self.y],
            'yaw': self.yaw,
            'command': list(self.command),
            'contacts': self.contacts,
            'touching': sorted(self.touching),
            'blocked': self.blocked,
            'travelled': self.travelled,
        }


def _radius(body: Body) -> float:
    """Half the diagonal of a body's footprint: no part of it is farther from its centre."""
    return math.hypot(*body.size[:2]) / 2.0


class Simulation:
    """The moving parts of a world: call :meth:`step` with the time since the last step.

    :attr:`robots` holds every robot's state by name, in the world's order; :attr:`robot` is the
    first's (the only one in the paper's worlds).
    """

    def __init__(self, world: World, scene: Scene | None = None):
        self.world = world
        self.scene = scene if scene is not None else Scene(world)
        self.time = 0.0
        self.bodies = {robot.name: robot.body for robot in world.robots}
        self.robots = {
            name: RobotState(body.position[0], body.position[1], body.yaw)
            for name, body in self.bodies.items()
        }
        self.robot_name = world.robots[0].name
        self.robot = self.robots[self.robot_name]
        self.obstacles = [body.name for body in world.objects]
        self.walkers = [body for body in world.objects if body.moving]
        self.loops = {body.name: loop_of(body.position, body.waypoints) for body in self.walkers}
        self.robot_moved_at: float | None = None  # simulated time of any robot's first non-zero command
        # What each robot can run into: every object and the other robots; and how far each reaches.
        self._others = {
            name: [*self.obstacles, *(r for r in self.robots if r != name)] for name in self.robots
        }
        self._radius = {body.name: _radius(body) for body in (*world.objects, *self.bodies.values())}
        for name, state in self.robots.items():
            state.touching = self._touching(name)

    # -- commands ------------------------------------------------------------------------------
    def set_command(self, vx: float, vy: float, robot: str | None = None) -> None:
        """Robot ``robot``'s velocity in ``map`` (m/s; None: the first robot's); capped at its speed,
        NaN means stop."""
        name = self.robot_name if robot is None else robot
        speed = self.bodies[name].speed
        if not (math.isfinite(vx) and math.isfinite(vy)):
            vx = vy = 0.0
        norm = math.hypot(vx, vy)
        if norm > speed:
            vx, vy = vx * speed / norm, vy * speed / norm
        if norm > 0 and self.robot_moved_at is None:
            self.robot_moved_at = self.time
        self.robots[name].command = (vx, vy)

    # -- stepping ------------------------------------------------------------------------------
    def step(self, dt: float) -> None:
        """Advance ``dt`` seconds: humans first, then each robot in the world's order."""
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
        for name in self.robots:
            self._move_robot(name, dt)

    def _near(self, name: str, x: float, y: float, within: float) -> list[str]:
        """The obstacles of robot ``name`` that it could come within ``within`` metres of at (x, y):
        a cheap bound on centre distances, so PyBullet is asked about a few bodies only."""
        reach = self._radius[name] + within
        return [
            other
            for other in self._others[name]
            if math.dist((x, y), self.scene.pose(other)[:2]) <= reach + self._radius[other]
        ]

    def _penetration(self, name: str, x: float, y: float) -> dict[str, float]:
        """Depth by which robot ``name`` at (x, y) would overlap each obstacle or the floor edge (> 0)."""
        self.scene.set_pose(name, x, y, self.robots[name].yaw)
        depth = {
            other: -d
            for other, d in self.scene.distances(name, self._near(name, x, y, 0.0), 0.0).items()
            if d < 0
        }
        edge = self._beyond_edge(name, x, y)
        if edge > 0:
            depth[FLOOR_EDGE] = edge
        return depth

    def _beyond_edge(self, name: str, x: float, y: float) -> float:
        """How far robot ``name``'s footprint at (x, y) reaches over the floor's edge (<= 0: not)."""
        size, yaw = self.bodies[name].size, self.robots[name].yaw
        c, s = abs(math.cos(yaw)), abs(math.sin(yaw))
        hx = (c * size[0] + s * size[1]) / 2
        hy = (s * size[0] + c * size[1]) / 2
        width, height = self.world.floor_size
        return max(hx - x, x + hx - width, hy - y, y + hy - height)

    def _allowed(self, name: str, x: float, y: float, current: dict[str, float]) -> bool:
        return all(d <= current.get(other, 0.0) + 1e-9 for other, d in self._penetration(name, x, y).items())

    def _move_robot(self, name: str, dt: float) -> None:
        state = self.robots[name]
        start = (state.x, state.y)
        vx, vy = state.command
        goal = (start[0] + vx * dt, start[1] + vy * dt)
        state.blocked = False
        if goal != start:
            current = self._penetration(name, *start)
            if not self._allowed(name, *goal, current):
                state.blocked = True
                low, high = 0.0, 1.0  # largest free fraction of the step, by bisection
                for _ in range(12):
                    middle = (low + high) / 2
                    if self._allowed(name, start[0] + middle * vx * dt, start[1] + middle * vy * dt, current):
                        low = middle
                    else:
                        high = middle
                goal = (start[0] + low * vx * dt, start[1] + low * vy * dt)
        state.travelled += math.dist(start, goal)
        state.x, state.y = goal
        self.scene.set_pose(name, state.x, state.y, state.yaw)
        touching = self._touching(name)
        if state.blocked:
            touching |= set(self._penetration(name, goal[0] + vx * dt, goal[1] + vy * dt))
            self.scene.set_pose(name, state.x, state.y, state.yaw)
        new = touching - state.touching
        if new:
            state.contacts += len(new)
            log.info('%s contact with %s at (%.3f, %.3f)', name, ', '.join(sorted(new)), state.x, state.y)
        state.touching = touching

    def _touching(self, name: str) -> set[str]:
        state = self.robots[name]
        near = self._near(name, state.x, state.y, TOUCH)
        touching = set(self.scene.distances(name, near, TOUCH))
        if self._beyond_edge(name, state.x, state.y) > -TOUCH:
            touching.add(FLOOR_EDGE)
        return touching

    # -- state ---------------------------------------------------------------------------------
    def poses(self) -> dict[str, tuple[float, float, float]]:
        """Every body's pose {name: (x, y, yaw)}: robots, stations and objects."""
        return self.scene.poses()

    def ground_truth(self) -> dict:
        """The robots' true state and every pose, for tests and the scenario recorder only: the
        first robot's at the top level (the paper's worlds have one), every robot's in ``robots``."""
        first = self.robot.truth()
        robot = {key: first.pop(key) for key in ('position', 'yaw', 'command')}
        return {
            'time': self.time,
            'robot': robot,
            **first,
            'objects': {name: list(pose) for name, pose in self.poses().items()},
            'robots': {name: state.truth() for name, state in self.robots.items()},
        }
