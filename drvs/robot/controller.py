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

from drvs.robot.asked import Box, inside, intersection
from drvs.robot.dstar_lite import FREE, DStarLite
from drvs.robot.occupancy import INFLATED, CostGrid, crosses_margin
from drvs.robot.perception import Fix
from drvs.robot.plan import corridor, densify, nearest_on_path, point_along, shortcut
from drvs.robot.robot_status import RobotStatus
from drvs.robot.traffic import Mover, Yielding, clear_of_people

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
    corridor_margin: float = 0.375  # m around a plan whose obstacles must be known before it is followed
    approach_gain: float = 1.5  # 1/s: speed = min(speed, gain * distance to goal) near the goal
    min_speed: float = 0.05  # m/s, so the approach never stalls
    ahead: float = 0.6  # m of the old plan past the lookahead that must stay clear to follow it while waiting
    radius: float = 0.2  # m: the robot's, for keeping clear of people
    people_horizon: float = (
        2.0  # s ahead people's motion is predicted (:func:`drvs.robot.traffic.clear_of_people`)
    )


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


def _box_text(box: Box | None) -> str:
    return 'nowhere' if box is None else '({:.2f}, {:.2f})-({:.2f}, {:.2f})'.format(*box)


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

    def __init__(
        self, grid: CostGrid, settings: ControllerSettings, now: float, yielding: Yielding | None = None
    ):
        self.grid = grid
        self.settings = settings
        self.yielding = yielding  # gives way to other robots (None: never)
        self.yielding_to: Mover | None = None  # the robot it gives way to now
        self.keeping_clear_of: Mover | None = None  # the person it left its plan for now
        self.keeps_clear = 0  # times it left its plan for someone moving
        self._heading: Point = (0.0, 0.0)  # the last velocity it drove its plan at
        self.state = LOCALISING
        self.reason = ''
        self.replans = 0
        self.path: list[Point] = []  # the plan it follows
        self.pending: list[Point] | None = None  # a new plan, until the floor it crosses is known
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
        self._repaired = False  # whether the pending plan repairs the one followed (a re-plan if it moved)
        self._cells = 0  # grid cells of the pending plan, for the log
        self._waiting_since: float | None = None  # since when the pending plan waits for answers

    # -- inputs ----------------------------------------------------------------------------
    def on_map_changed(self, changes: Sequence[tuple[tuple[int, int], float]]) -> None:
        """Feed changed cells to the planner; flag a re-plan when they are on or near the path."""
        if not changes or self._planner is None:
            return
        self._planner.update_cells(changes)
        if self.state == BLOCKED or not self.path or self.pending is not None:
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
    def step(
        self,
        now: float,
        fix: Fix | None,
        station: Fix | None,
        known: Box | None = None,
        movers: Sequence[Mover] = (),
        people: Sequence[Mover] = (),
    ) -> tuple[float, float]:
        """Decide the velocity (vx, vy) in ``map`` for now; records it for dead reckoning.

        :param known: the floor whose obstacles the robot asked about and heard back on
            (:class:`drvs.robot.asked.AskedFloor`): a new plan is followed only once its
            corridor is inside it (None: anywhere).
        :param movers: the other robots, with their velocities: it stands still while it gives
            way to one (:class:`drvs.robot.traffic.Yielding`).
        :param people: whatever else moves (people), with their velocities: they give way to
            nobody, so the robot keeps clear of them (:func:`drvs.robot.traffic.clear_of_people`).
        """
        vx, vy = self._decide(now, fix, station, known)
        if self.yielding is not None and self.state == MOVING and self.position is not None:
            other = self.yielding.step(now, self.position, (vx, vy), movers)
            if other is not None and self.yielding_to is None:
                log.info('giving way to a robot at (%.2f, %.2f)', *other.position)
            self.yielding_to = other
            if other is not None:
                vx, vy = 0.0, 0.0
        if people and self.state in (MOVING, BLOCKED) and self.position is not None:
            s = self.settings
            hx, hy = self._heading
            norm = math.hypot(hx, hy)
            back = (-hx / norm * s.speed, -hy / norm * s.speed) if norm > 0 else (0.0, 0.0)
            (vx, vy), person = clear_of_people(
                self.position,
                (vx, vy),
                [p.at(now) for p in people],
                s.radius,
                s.people_horizon,
                back,
                self._free,
            )
            if person is not None and self.keeping_clear_of is None:
                log.info('keeping clear of someone moving at (%.2f, %.2f)', *person.position)
                self.keeps_clear += 1
            self.keeping_clear_of = person
        if math.hypot(vx, vy) > 0 and self.keeping_clear_of is None:
            self._heading = (vx, vy)
        self.dead_reckoning.command(now, vx, vy)
        return vx, vy

    def _decide(
        self, now: float, fix: Fix | None, station: Fix | None, known: Box | None
    ) -> tuple[float, float]:
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

        self._plan(known)
        if self.pending is not None:  # a plan over floor not asked about yet: wait for the answers
            if self._waiting_since is None:
                self._waiting_since = now
                log.info('asking about the floor of a new plan before following it')
            elif now - self._waiting_since > s.unreachable_timeout:
                self.fail(
                    f'no answers about the floor of its plan (obstacles in {_box_text(self.corridor)}) '
                    f'for {s.unreachable_timeout:.1f} s'
                )
                return (0.0, 0.0)
            if self._in_the_way():  # standing where something moving will pass: out of its way first
                log.info('in the way of something moving: following its new plan before the answers')
                self._take_pending()
            elif self.path and self._ahead_is_clear(known):
                return self._follow(to_goal)  # the old plan, over known floor, while the answers come
            else:
                return (0.0, 0.0)
        self._waiting_since = None
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
        self.path, self.pending, self._repaired = [], None, False
        self._replan = True

    def _plan(self, known: Box | None) -> None:
        """(Re-)extract the plan when the map changed near it, the robot left it, or it is blocked;
        follow a new plan only once its corridor is inside ``known`` (else it is :attr:`pending`)."""
        assert self.position is not None and self.goal is not None and self._planner is not None  # by _decide
        spec = self.grid.spec
        off_path = bool(self.path) and self._distance_to_path() > 2 * self.settings.lookahead
        if self._replan or off_path or not (self.path or self.pending):
            self._planner.set_start(spec.cell_of(self.position))
            self._planner.compute_shortest_path()
            self._repaired = self._repaired or (bool(self.path) and self._replan)
            self._replan = False
            cells = self._planner.path()
            if not cells or crosses_margin(cells, self.grid.costs):
                self.path, self.pending, self._repaired = [], None, False
                return
            self.pending, self._cells = self._smoothed(cells), len(cells)
        if self.pending is None or not (known is None or inside(self._corridor(self.pending), known)):
            return
        self._take_pending()

    def _take_pending(self) -> None:
        """Follow the pending plan from now on; a changed route counts (and is logged) as a re-plan."""
        assert self.pending is not None and self._planner is not None  # by _plan
        spec = self.grid.spec
        previous = self.path[self._progress :]
        self.path, self.pending = self.pending, None
        self._progress = 0
        repaired, self._repaired = self._repaired, False
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
            self._cells,
            self._planner.path_cost() * spec.resolution,
            f' (re-plan {self.replans})' if replan else '',
        )

    @property
    def corridor(self) -> Box | None:
        """The floor the robot must know the obstacles of: around its pending plan, else around
        the rest of the plan it follows (None without either)."""
        plan = self.pending if self.pending is not None else self.path[self._progress :]
        return self._corridor(plan) if plan else None

    def _corridor(self, plan: Sequence[Point]) -> Box:
        """``plan``'s box grown by ``corridor_margin``, on the floor."""
        width, height = self.grid.spec.size
        return intersection(corridor(plan, self.settings.corridor_margin), (0.0, 0.0, width, height))

    def _smoothed(self, cells: Sequence[tuple[int, int]]) -> list[Point]:
        """The grid path ``cells`` from the robot to the goal as straight segments over free cells
        (:func:`drvs.robot.plan.shortcut`), a point every cell along them."""
        assert self.position is not None and self.goal is not None  # by _decide
        spec, costs = self.grid.spec, self.grid.costs
        points = [self.position, *(spec.centre_of(c) for c in cells[1:-1]), self.goal]
        free = [bool(costs[c] == FREE) for c in cells]
        if len(cells) == 1:  # the robot and its goal in one cell
            free = free * 2
        return densify(shortcut(points, free, costs, spec.resolution), spec.resolution)

    def _free(self, point: Point) -> bool:
        """Whether a robot centred on ``point`` stands on the floor, outside every obstacle's margin."""
        width, height = self.grid.spec.size
        r = self.settings.radius  # the robot's body stays on the floor
        inside_floor = r <= point[0] <= width - r and r <= point[1] <= height - r
        return inside_floor and bool(self.grid.costs[self.grid.spec.cell_of(point)] < INFLATED)

    def _in_the_way(self) -> bool:
        """Whether the robot stands in a margin the map holds (another robot's or a person's
        floor ahead of them, :func:`drvs.robot.traffic.swept`): waiting there, it would be run into."""
        assert self.position is not None  # by _decide
        return bool(self.grid.costs[self.grid.spec.cell_of(self.position)] >= INFLATED)

    def _ahead_is_clear(self, known: Box | None) -> bool:
        """Whether the plan the robot follows stays over free, known floor for its stopping
        distance (``ahead``) past the point of it nearest the robot."""
        assert self.position is not None  # by _decide
        s, spec = self.settings, self.grid.spec
        segment, fraction = nearest_on_path(self.path, self.position, self._progress)
        reach = s.lookahead + s.ahead
        points = [
            point_along(self.path, segment, fraction, d) for d in np.arange(0.0, reach, spec.resolution / 2)
        ]
        if known is not None and not inside(corridor(points, s.corridor_margin), known):
            return False
        return all(self.grid.costs[spec.cell_of(p)] < INFLATED for p in points)

    def _distance_to_path(self) -> float:
        assert self.position is not None  # a path starts where the robot was located
        points = np.asarray(self.path)
        return float(np.hypot(points[:, 0] - self.position[0], points[:, 1] - self.position[1]).min())

    def _follow(self, to_goal: float) -> tuple[float, float]:
        """Pure pursuit: steer to the point ``lookahead`` metres along the plan past the point of
        it nearest the robot (on a straight segment, the robot converges onto it and stays)."""
        assert self.position is not None  # a path starts where the robot was located
        s = self.settings
        segment, fraction = nearest_on_path(self.path, self.position, self._progress)
        self._progress = segment
        target = point_along(self.path, segment, fraction, s.lookahead)
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
