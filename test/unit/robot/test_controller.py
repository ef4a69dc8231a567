"""Controller logic in a small kinematic simulation with late fixes (no ROS)."""

import pytest
from shapely.geometry import Point, box

from drvs.robot.controller import ARRIVED, BLOCKED, FAILED, Controller, ControllerSettings, DeadReckoning
from drvs.robot.occupancy import CostGrid, GridSpec
from drvs.robot.perception import Fix

SPEC = GridSpec((3.0, 2.0), 0.05)
RADIUS = 0.15 * 2**0.5  # half the diagonal of a 0.3 m robot
STATION = (2.6, 1.0)


def fix_at(position, stamp, seq):
    return Fix(
        position=position, outline=Point(position).buffer(0.15), stamp=stamp, seq=seq, vision_systems=('vs',)
    )


class Sim:
    """The true robot moves with the commanded velocity; fixes arrive ``latency`` s after capture."""

    def __init__(self, start, obstacles=(), latency=0.2, period=0.1, settings=None):
        self.grid = CostGrid(SPEC, RADIUS)
        self.controller = Controller(self.grid, settings or ControllerSettings(speed=0.5), now=0.0)
        self.true = start
        self.now = 0.0
        self.latency, self.period = latency, period
        self.captures = []  # (capture time, true position)
        self.fix = None
        self.seq = 0
        self.trace = [start]
        self.set_obstacles(obstacles)

    def set_obstacles(self, obstacles):
        self.obstacles = list(obstacles)
        self.controller.on_map_changed(self.grid.apply(self.obstacles))

    def run(self, seconds, until=None, fixes=True):
        for _ in range(int(round(seconds / self.period))):
            if fixes:
                self.captures.append((self.now, self.true))
                while self.captures and self.captures[0][0] <= self.now - self.latency:
                    stamp, position = self.captures.pop(0)
                    self.seq += 1
                    self.fix = fix_at(position, stamp, self.seq)
            vx, vy = self.controller.step(self.now, self.fix, fix_at(STATION, 0.0, 1))
            self.true = (self.true[0] + vx * self.period, self.true[1] + vy * self.period)
            self.trace.append(self.true)
            self.now += self.period
            if until and until(self):
                return
            if self.controller.state in (ARRIVED, FAILED):
                return


def clearance(sim):
    """The smallest distance between the true robot centre and any obstacle during the run."""
    return min(min(o.distance(Point(p)) for o in sim.obstacles) for p in sim.trace)


def test_dead_reckoning_integrates_commands_since_the_fix():
    reckoning = DeadReckoning()
    reckoning.command(0.0, 1.0, 0.0)
    reckoning.command(1.0, 0.0, 2.0)
    reckoning.command(2.0, 0.0, 0.0)
    assert reckoning.predict((0.0, 0.0), 0.5, 1.5) == pytest.approx((0.5, 1.0))
    assert reckoning.predict((0.0, 0.0), 0.5, 3.0) == pytest.approx((0.5, 2.0))


def test_reaches_the_station_despite_late_fixes():
    sim = Sim((0.4, 1.0))
    sim.run(15)
    assert sim.controller.state == ARRIVED
    assert Point(sim.true).distance(Point(STATION)) <= 0.1
    assert sim.controller.replans == 0


def test_replans_around_an_obstacle_that_appears_on_the_path():
    sim = Sim((0.4, 1.0))
    sim.run(10, until=lambda s: s.true[0] > 1.0)
    sim.set_obstacles([box(1.5, 0.7, 1.8, 1.3)])  # steps onto the straight path, 0.5 m ahead
    sim.run(20)
    assert sim.controller.state == ARRIVED
    assert sim.controller.replans >= 1
    assert clearance(sim) > 0.15  # the body (half width 0.15 m) never touched it


def test_changes_far_from_the_path_do_not_replan():
    sim = Sim((0.4, 1.0))
    sim.run(1)
    sim.set_obstacles([box(1.0, 0.0, 1.2, 0.1)])  # a box in a far corner
    sim.run(15)
    assert sim.controller.state == ARRIVED
    assert sim.controller.replans == 0


def test_a_change_beside_the_path_that_keeps_the_route_is_not_a_replan():
    sim = Sim((0.4, 1.0))
    sim.run(10, until=lambda s: s.true[0] > 1.0)
    sim.set_obstacles([box(1.6, 1.3, 1.9, 1.45)])  # 0.3 m beside the straight path: repaired, same route
    sim.run(20)
    assert sim.controller.state == ARRIVED
    assert sim.controller.replans == 0


def test_starting_inside_an_inflated_margin_leaves_it_by_the_cheapest_way():
    # an obstacle 5 cm west of the robot: the robot is inside its margin, the way east is free
    sim = Sim((0.5, 1.0), obstacles=[box(0.1, 0.5, 0.3, 1.5)])
    sim.run(15)
    assert sim.controller.state == ARRIVED
    assert sim.trace[5][0] > sim.trace[0][0]  # left eastwards, away from the obstacle


def test_a_walled_off_station_fails_after_the_unreachable_timeout():
    settings = ControllerSettings(speed=0.5, unreachable_timeout=1.0)
    sim = Sim((0.4, 1.0), obstacles=[box(2.0, 0.0, 2.1, 2.0)], settings=settings)
    sim.run(0.5)
    assert sim.controller.state == BLOCKED
    sim.run(5)
    assert sim.controller.state == FAILED
    assert (
        sim.controller.reason
        == 'goal unreachable: no way from (0.40, 1.00) to the station at (2.60, 1.00) for 1.0 s'
    )
    assert sim.controller.step(sim.now, sim.fix, fix_at(STATION, 0, 1)) == (0.0, 0.0)


def test_a_wall_that_opens_again_lets_the_robot_through():
    sim = Sim((0.4, 1.0), obstacles=[box(2.0, 0.0, 2.1, 2.0)])
    sim.run(1)
    assert sim.controller.state == BLOCKED
    sim.set_obstacles([])
    sim.run(15)
    assert sim.controller.state == ARRIVED


def test_no_fix_for_fix_timeout_stops_the_robot():
    sim = Sim((0.4, 1.0), settings=ControllerSettings(speed=0.5, fix_timeout=1.0))
    sim.run(1)
    sim.run(3, fixes=False)
    assert sim.controller.state == FAILED
    assert sim.controller.reason == 'no fix of the robot for 1.0 s'


def test_no_station_found_stops_the_robot():
    controller = Controller(CostGrid(SPEC, RADIUS), ControllerSettings(fix_timeout=1.0), now=0.0)
    for t in range(20):
        controller.step(t * 0.1, fix_at((0.4, 1.0), t * 0.1, t + 1), None)
    assert controller.state == FAILED
    assert controller.reason == 'no fix of the station for 1.0 s'


def test_arrival_needs_a_fix_taken_after_stopping():
    controller = Controller(CostGrid(SPEC, RADIUS), ControllerSettings(), now=0.0)
    station = fix_at(STATION, 0.0, 1)
    near = fix_at((2.55, 1.0), 0.0, 1)
    assert controller.step(0.1, near, station) == (0.0, 0.0)
    assert controller.state == 'arriving'
    controller.step(0.2, near, station)  # the same old fix: not yet confirmed
    assert controller.state == 'arriving'
    controller.step(0.3, fix_at((2.56, 1.0), 0.25, 2), station)
    assert controller.state == ARRIVED
    status = controller.status()
    assert status.state == 'arrived' and status.distance_to_goal == pytest.approx(0.04)
