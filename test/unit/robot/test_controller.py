"""Controller logic in a small kinematic simulation with late fixes (no ROS)."""

import math
import random

import pytest
from shapely.geometry import LineString, Point, box

from drvs.robot.asked import inside
from drvs.robot.controller import (
    ARRIVED,
    BLOCKED,
    FAILED,
    MOVING,
    Controller,
    ControllerSettings,
    DeadReckoning,
)
from drvs.robot.occupancy import CostGrid, GridSpec
from drvs.robot.perception import Fix
from drvs.robot.traffic import Mover, Yielding

SPEC = GridSpec((3.0, 2.0), 0.05)
RADIUS = 0.15 * 2**0.5  # half the diagonal of a 0.3 m robot
STATION = (2.6, 1.0)


def fix_at(position, stamp, seq):
    return Fix(
        position=position, outline=Point(position).buffer(0.15), stamp=stamp, seq=seq, vision_systems=('vs',)
    )


class Sim:
    """The true robot moves with the commanded velocity in ``map`` (world_sim's holonomic robot);
    fixes arrive ``latency`` s after capture, off by gaussian ``noise`` (m, seeded)."""

    def __init__(
        self,
        start,
        obstacles=(),
        latency=0.2,
        period=0.1,
        settings=None,
        spec=SPEC,
        station=STATION,
        noise=0.0,
    ):
        self.grid = CostGrid(spec, RADIUS)
        self.controller = Controller(self.grid, settings or ControllerSettings(speed=0.5), now=0.0)
        self.station = station
        self.noise, self.rng = noise, random.Random(7)
        self.true = start
        self.now = 0.0
        self.latency, self.period = latency, period
        self.captures = []  # (capture time, true position)
        self.fix = None
        self.seq = 0
        self.trace = [start]
        self.closest = math.inf  # metres between the true robot centre and the nearest person
        self.set_obstacles(obstacles)

    def set_obstacles(self, obstacles):
        self.obstacles = list(obstacles)
        self.controller.on_map_changed(self.grid.apply(self.obstacles))

    people = None  # now -> the people (Movers) at now, seen now

    def run(self, seconds, until=None, fixes=True, known=None):
        for _ in range(int(round(seconds / self.period))):
            if fixes:
                self.captures.append((self.now, self.true))
                while self.captures and self.captures[0][0] <= self.now - self.latency:
                    stamp, (x, y) = self.captures.pop(0)
                    self.seq += 1
                    seen = (x + self.rng.gauss(0.0, self.noise), y + self.rng.gauss(0.0, self.noise))
                    self.fix = fix_at(seen, stamp, self.seq)
            people = self.people(self.now) if self.people else ()
            vx, vy = self.controller.step(
                self.now, self.fix, fix_at(self.station, 0.0, 1), known, people=people
            )
            self.closest = min([self.closest, *(p.outline.distance(Point(self.true)) for p in people)])
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


@pytest.mark.parametrize('noise', [0.0, 0.01])
@pytest.mark.parametrize('station', [(3.6, 2.3), (3.6, 0.9), (1.2, 2.6)])
def test_follows_a_straight_plan_at_any_angle_within_a_few_centimetres(station, noise):
    # On an open floor the plan is one straight segment, whatever D* Lite's 8-connected staircase;
    # after settling the true robot stays within 3 cm of it, with late (and noisy) fixes.
    start = (0.4, 0.5)
    sim = Sim(start, spec=GridSpec((4.0, 3.0), 0.05), station=station, noise=noise)
    sim.run(1.0)
    plan = sim.controller.path
    line = LineString([plan[0], plan[-1]])
    assert plan[-1] == pytest.approx(station) and Point(plan[0]).distance(Point(start)) < 4 * noise + 1e-9
    assert max(line.distance(Point(p)) for p in plan) < 1e-9
    sim.run(20)
    assert sim.controller.state == ARRIVED and sim.controller.path == plan
    settled = [p for p in sim.trace if Point(p).distance(Point(start)) > 0.3]
    assert max(line.distance(Point(p)) for p in settled) < 0.03


def test_replans_around_an_obstacle_that_appears_on_the_path():
    sim = Sim((0.4, 1.0))
    sim.run(10, until=lambda s: s.true[0] > 1.0)
    sim.set_obstacles([box(1.5, 0.7, 1.8, 1.3)])  # steps onto the straight path, 0.5 m ahead
    sim.run(20)
    assert sim.controller.state == ARRIVED
    assert sim.controller.replans >= 1
    assert clearance(sim) > 0.15  # the body (half width 0.15 m) never touched it


def test_a_plan_over_floor_not_asked_about_waits_for_the_answers():
    # The robot knows the obstacles of a band around the straight way only; a box across it
    # makes the way round leave the band: the robot stops, keeps its old plan, and follows the
    # new one only once the floor around it is known.
    band = (0.0, 0.5, 3.0, 1.5)
    sim = Sim((0.4, 1.0))
    sim.run(10, until=lambda s: s.true[0] > 1.0, known=band)
    assert sim.controller.pending is None and inside(sim.controller.corridor, band)
    followed = sim.controller.path
    sim.set_obstacles([box(1.5, 0.45, 1.8, 1.55)])
    sim.run(1.0, known=band)
    stopped = sim.true
    assert sim.controller.pending is not None and not inside(sim.controller.corridor, band)
    assert sim.controller.path is followed and sim.controller.replans == 0
    assert sim.controller.state == MOVING and sim.controller.step(
        sim.now, sim.fix, fix_at(STATION, 0, 1), band
    ) == (0, 0)
    sim.run(1.0, known=band)
    assert sim.true == stopped  # it waits
    sim.run(20, known=(0.0, 0.0, 3.0, 2.0))  # answered: the whole floor
    assert sim.controller.state == ARRIVED and sim.controller.replans == 1
    assert clearance(sim) > 0.15


def test_while_the_answers_come_the_robot_follows_its_old_plan_as_far_as_it_is_clear():
    # A box far ahead makes the new plan leave the known band: the robot does not stop where it
    # is (someone might walk into it) but follows its old plan until its stretch ahead is no
    # longer clear, and never enters the box's margin.
    band = (0.0, 0.5, 3.0, 1.5)
    sim = Sim((0.4, 1.0))
    sim.run(10, until=lambda s: s.true[0] > 0.8, known=band)
    sim.set_obstacles([box(2.1, 0.45, 2.3, 1.55)])
    sim.run(0.2, known=band)
    assert sim.controller.pending is not None and sim.controller.replans == 0
    start = sim.true[0]
    sim.run(3.0, known=band)
    assert sim.true[0] > start + 0.2  # it kept going
    assert sim.true[0] < 2.1 - RADIUS  # and stopped short of the box's margin
    moved = sim.true
    sim.run(1.0, known=band)
    assert sim.true == moved
    sim.run(20, known=(0.0, 0.0, 3.0, 2.0))
    assert sim.controller.state == ARRIVED and clearance(sim) > 0.15


def test_a_robot_waiting_in_the_way_of_something_moving_follows_its_new_plan_at_once():
    # The map holds the floor ahead of a person (swept) where the robot stands: waiting there
    # for the answers about its new plan's floor, it would be walked into.
    band = (0.0, 0.8, 3.0, 1.2)  # narrower than any new plan's corridor
    sim = Sim((0.4, 1.0))
    sim.run(10, until=lambda s: s.true[0] > 1.0)
    here = sim.true
    sim.set_obstacles([box(here[0] - 0.1, here[1] + 0.05, here[0] + 0.3, here[1] + 0.5)])
    sim.run(0.1, known=band)
    assert sim.controller.pending is None and sim.controller.replans == 1
    sim.run(1.0, known=band)
    assert Point(sim.true).distance(Point(here)) > 0.1  # it moved out of the way


@pytest.mark.parametrize('crossing_at', [1.0, 1.6, 2.2])
def test_a_person_walking_across_the_plan_is_never_touched(crossing_at):
    # People give way to nobody: whenever a person's way crosses the robot's, the robot waits
    # before it, or steps out of it, and still arrives.
    sim = Sim((0.4, 1.0), settings=ControllerSettings(speed=0.5, radius=RADIUS))
    walk = 0.4  # m/s southwards across y = 1, over x = 1.5, reaching the plan at ``crossing_at`` s

    def people(now):
        y = 1.0 + walk * (crossing_at - now)
        return [Mover(box(1.3, y - 0.2, 1.7, y + 0.2), (0.0, -walk), now)]

    sim.people = people
    sim.run(20)
    assert sim.controller.state == ARRIVED
    assert sim.closest > RADIUS  # the body never touched the person
    assert sim.controller.keeps_clear >= (1 if crossing_at > 1.0 else 0)


def test_no_answers_about_the_floor_of_a_plan_fail_after_the_unreachable_timeout():
    sim = Sim((0.4, 1.0), settings=ControllerSettings(speed=0.5, unreachable_timeout=2.0))
    sim.run(5, known=(0.0, 0.0, 1.0, 1.0))
    assert sim.controller.state == FAILED and sim.true == (0.4, 1.0)
    assert sim.controller.reason == (
        'no answers about the floor of its plan (obstacles in (0.03, 0.62)-(2.98, 1.38)) for 2.0 s'
    )


def test_it_stands_while_it_gives_way_to_another_robot():
    grid = CostGrid(SPEC, RADIUS)
    controller = Controller(grid, ControllerSettings(speed=0.5), now=0.0, yielding=Yielding(1.5, 0.47, 1.0))
    station, here = fix_at(STATION, 0.0, 1), fix_at((0.4, 1.0), 0.0, 1)
    assert controller.step(0.0, here, station) == pytest.approx((0.5, 0.0))
    crossing = Mover(box(1.05, 0.45, 1.35, 0.75), (0.0, 0.4))  # will cross its way 0.8 m ahead
    assert controller.step(0.1, here, station, movers=[crossing]) == (0.0, 0.0)
    assert controller.yielding_to is crossing and controller.state == MOVING
    assert controller.dead_reckoning.predict((0.4, 1.0), 0.0, 0.3) == pytest.approx((0.45, 1.0))  # stood
    passed = Mover(box(1.05, 1.65, 1.35, 1.95), (0.0, 0.4))
    assert controller.step(0.2, here, station, movers=[passed]) == pytest.approx((0.5, 0.0))
    assert controller.yielding_to is None


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
