"""The blind robot's navigation logic: plan, follow, predict between fixes, re-plan, stop (no rospy).

Each control tick the node calls :meth:`Controller.step` with the newest fixes and
publishes the velocity it returns; the controller predicts the robot's position between
late fixes (:class:`DeadReckoning`), plans and repairs with D* Lite, follows the plan and
fails explicitly. What the robot does: docs/nodes/blind_robot.md; how: docs/design.md.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drvs.robot.dstar_lite import DStarLite
from drvs.robot.occupancy import CostGrid, crosses_margin
from drvs.robot.perception import Fix
from drvs.robot.robot_status import RobotStatus

log = logging.getLogger('rosout.' + __name__)

Point = tuple[float, float]

LOCALISING, MOVING, BLOCKED, ARRIVING, ARRIVED, FAILED = (
    'localising',
    'moving',
    'blocked',
    'arriving',
    'arrived',
    'failed',
)
FINAL_STATES = (ARRIVED, FAILED)


@dataclass(frozen=True)
class ControllerSettings:
    speed: float = 0.4  # m/s, the robot's top speed
    goal_tolerance: float = 0.1  # m
    fix_timeout: float = 5.0  # s without a new fix of the robot (or, at start, of the station)
    unreachable_timeout: float = 5.0  # s the goal may stay unreachable before the robot gives up
    lookahead: float = 0.2  # m along the path to the point the robot steers to
    replan_distance: float = 0.3  # m: map changes this close to the remaining path trigger a re-plan
    route_tolerance: float = 0.15  # m: a repaired path straying further from the old route is a re-plan
    approach_gain: float = 1.5  # 1/s: speed = min(speed, gain * distance to goal) near the goal
    min_speed: float = 0.05  # m/s, so the approach never stalls


class DeadReckoning:
    """Position between fixes: the fix plus the integral of the velocities commanded since it was taken."""

    def __init__(self) -> None:
        self._commands: list[tuple[float, float, float]] = []  # (from time, vx, vy), time-ordered

    def command(self, now: float, vx: float, vy: float) -> None:
        self._commands.append((now, vx, vy))

    def predict(self, position: Point, since: float, now: float) -> Point:
        x, y = position
        commands = self._commands
        # Forget commands that ended before ``since`` (keep the one in force at ``since``).
        first = 0
        while first + 1 < len(commands) and commands[first + 1][0] <= since:
            first += 1
        del commands[:first]
        for i, (start, vx, vy) in enumerate(commands):
            end = commands[i + 1][0] if i + 1 < len(commands) else now
            dt = min(end, now) - max(start, since)
            if dt > 0:
                x += vx * dt
                y += vy * dt
        return (x, y)


def _distance(a: Point, b: Point) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])


def route_changed(old: Sequence[Point], new: Sequence[Point], tolerance: float) -> bool:
    """Whether the new path leaves the old route by more than ``tolerance`` metres somewhere.

    Both are dense polylines (grid cell centres), so vertex distances stand for polyline distances.

    >>> route_changed([(0, 0), (1, 0), (2, 0)], [(0.1, 0.02), (2, 0)], 0.15)
    False
    >>> route_changed([(0, 0), (1, 0), (2, 0)], [(0, 0), (1, 0.5), (2, 0)], 0.15)
    True
    """
    if not old:
        return True
    a, b = np.asarray(old, dtype=float), np.asarray(new, dtype=float)
    distances = np.hypot(b[:, None, 0] - a[None, :, 0], b[:, None, 1] - a[None, :, 1])
    return bool(distances.min(axis=1).max() > tolerance)


class Controller:
    """Plans on ``grid`` with D* Lite and drives along the plan; see the module docstring."""

    def __init__(self, grid: CostGrid, settings: ControllerSettings, now: float):
        self.grid = grid
        self.settings = settings
        self.state = LOCALISING
        self.reason = ''
        self.replans = 0
        self.path: list[Point] = []
        self.position: Point | None = None
        self.goal: Point | None = None
        self.dead_reckoning = DeadReckoning()
        self._planner: DStarLite | None = None
        self._replan = False
        self._started = now
        self._last_fix: tuple[int, float] | None = None  # (seq, time it came in)
        self._blocked_since: float | None = None
        self._stopped_at: float | None = None
        self._progress = 0

    # -- inputs ----------------------------------------------------------------------------
    def on_map_changed(self, changes: Sequence[tuple[tuple[int, int], float]]) -> None:
        """Feed changed cells to the planner; flag a re-plan when they are on or near the path."""
        if not changes or self._planner is None:
            return
        self._planner.update_cells(changes)
        if self.state == BLOCKED or not self.path:
            self._replan = True
            return
        spec = self.grid.spec
        centres = np.array([spec.centre_of(cell) for cell, _ in changes])
        remaining = np.array(self.path[self._progress :] or self.path[-1:])
        near = self.settings.replan_distance + spec.resolution
        distances = np.hypot(
            centres[:, None, 0] - remaining[None, :, 0], centres[:, None, 1] - remaining[None, :, 1]
        )
        if distances.min() <= near:
            self._replan = True

    def fail(self, reason: str) -> None:
        """Stop for good and say why (logged once)."""
        if self.state in FINAL_STATES:
            return
        self.state = FAILED
        self.reason = reason
        log.error('robot stopped: %s', reason)

    # -- the control tick --------------------------------------------------------------------
    def step(self, now: float, fix: Fix | None, station: Fix | None) -> tuple[float, float]:
        """Decide the velocity (vx, vy) in ``map`` for now; records it for dead reckoning."""
        vx, vy = self._decide(now, fix, station)
        self.dead_reckoning.command(now, vx, vy)
        return vx, vy

    def _decide(self, now: float, fix: Fix | None, station: Fix | None) -> tuple[float, float]:
        s = self.settings
        if self.state in FINAL_STATES:
            return (0.0, 0.0)
        if fix is not None and (self._last_fix is None or fix.seq != self._last_fix[0]):
            self._last_fix = (fix.seq, now)
        last_heard = self._last_fix[1] if self._last_fix else self._started
        if now - last_heard > s.fix_timeout:
            self.fail(f'no fix of the robot for {s.fix_timeout:.1f} s')
            return (0.0, 0.0)
        if station is None and now - self._started > s.fix_timeout:
            self.fail(f'no fix of the station for {s.fix_timeout:.1f} s')
            return (0.0, 0.0)
        if fix is None or station is None:
            return (0.0, 0.0)

        self.position = self.dead_reckoning.predict(fix.position, fix.stamp, now)
        self._set_goal(station.position)
        assert self.goal is not None  # set just now
        to_goal = _distance(self.position, self.goal)

        if to_goal <= s.goal_tolerance:
            return self._arrive(now, fix)
        self._stopped_at = None
        if self.state in (LOCALISING, ARRIVING):
            self.state = MOVING

        self._plan()
        if not self.path:
            if self._blocked_since is None:
                self._blocked_since = now
                self.state = BLOCKED
                log.warning('goal unreachable from %s; waiting for the way to open', self._where())
            if now - self._blocked_since > s.unreachable_timeout:
                self.fail(
                    f'goal unreachable: no way from {self._where()} to the station at '
                    f'({self.goal[0]:.2f}, {self.goal[1]:.2f}) for {s.unreachable_timeout:.1f} s'
                )
            return (0.0, 0.0)
        if self._blocked_since is not None:
            log.info('the way to the station is open again')
        self._blocked_since = None
        self.state = MOVING
        return self._follow(to_goal)

    def _where(self) -> str:
        assert self.position is not None  # called once the robot is located
        return f'({self.position[0]:.2f}, {self.position[1]:.2f})'

    def _set_goal(self, goal: Point) -> None:
        """A new goal (or the station found elsewhere) needs a new search; D* Lite keeps its goal."""
        if self.goal is not None and _distance(goal, self.goal) <= self.settings.goal_tolerance / 2:
            return
        assert self.position is not None  # the robot is located before its goal is set
        self.goal = goal
        spec = self.grid.spec
        self._planner = DStarLite(self.grid.costs, spec.cell_of(self.position), spec.cell_of(goal))
        self.path = []
        self._replan = True

    def _plan(self) -> None:
        """(Re-)extract the path when the map changed near it, the robot left it, or it is blocked."""
        assert self.position is not None and self.goal is not None and self._planner is not None  # by _decide
        spec = self.grid.spec
        start = spec.cell_of(self.position)
        off_path = bool(self.path) and self._distance_to_path() > 2 * self.settings.lookahead
        if not (self._replan or off_path or not self.path):
            return
        self._planner.set_start(start)
        self._planner.compute_shortest_path()
        repaired = bool(self.path) and self._replan
        self._replan = False
        cells = self._planner.path()
        if not cells or crosses_margin(cells, self.grid.costs):
            self.path = []
            return
        previous = self.path[self._progress :]
        self.path = [self.position, *(spec.centre_of(c) for c in cells[1:-1]), self.goal]
        self._progress = 0
        # A repair that leaves the route where it was (a human moving beside it, an outline
        # a pixel wider) is not a re-plan: only a changed route counts and is logged as one.
        replan = repaired and route_changed(previous, self.path, self.settings.route_tolerance)
        if replan:
            self.replans += 1
        elif repaired:
            log.debug('map changed near the path; the route stays')
            return
        log.info(
            '%s from %s: %d cells, cost %.2f m%s',
            're-planned' if replan else 'planned',
            self._where(),
            len(cells),
            self._planner.path_cost() * spec.resolution,
            f' (re-plan {self.replans})' if replan else '',
        )

    def _distance_to_path(self) -> float:
        assert self.position is not None  # a path starts where the robot was located
        points = np.asarray(self.path)
        return float(np.hypot(points[:, 0] - self.position[0], points[:, 1] - self.position[1]).min())

    def _follow(self, to_goal: float) -> tuple[float, float]:
        """Steer to the point ``lookahead`` metres along the path past the nearest path vertex."""
        assert self.position is not None  # a path starts where the robot was located
        s = self.settings
        points = np.asarray(self.path)
        window = points[self._progress :]
        nearest = self._progress + int(
            np.argmin(np.hypot(window[:, 0] - self.position[0], window[:, 1] - self.position[1]))
        )
        self._progress = nearest
        target = self.path[-1]
        travelled = 0.0
        previous = self.position
        for point in self.path[nearest + 1 :]:
            travelled += _distance(previous, point)
            previous = point
            if travelled >= s.lookahead:
                target = point
                break
        dx, dy = target[0] - self.position[0], target[1] - self.position[1]
        norm = math.hypot(dx, dy)
        if norm < 1e-9:
            return (0.0, 0.0)
        speed = min(s.speed, max(s.min_speed, s.approach_gain * to_goal))
        return (speed * dx / norm, speed * dy / norm)

    def _arrive(self, now: float, fix: Fix) -> tuple[float, float]:
        """Stopped within tolerance by prediction; arrived when a later fix agrees."""
        assert self.goal is not None  # arriving means near the goal
        if self._stopped_at is None:
            self._stopped_at = now
            self.state = ARRIVING
        elif (
            fix.stamp >= self._stopped_at
            and _distance(fix.position, self.goal) <= self.settings.goal_tolerance
        ):
            self.state = ARRIVED
            log.info(
                'arrived at the station: %.3f m from its centre after %d re-plans',
                _distance(fix.position, self.goal),
                self.replans,
            )
        return (0.0, 0.0)

    # -- reporting ---------------------------------------------------------------------------
    def status(self) -> RobotStatus:
        """What the controller knows of the mission now (the node adds the rest)."""
        return RobotStatus(
            state=self.state,
            reason=self.reason,
            replans=self.replans,
            distance_to_goal=(
                None if self.position is None or self.goal is None else _distance(self.position, self.goal)
            ),
            position=self.position,
            goal=self.goal,
            path_length=len(self.path),
        )
