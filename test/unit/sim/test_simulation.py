"""world_sim's core: waypoint loops, the robots' speed caps, stopping at obstacles and each other,
counting contacts, the step clock."""

import doctest
import math

import pytest
import yaml

import drvs.sim.simulation
from drvs.sim.simulation import (
    FLOOR_EDGE,
    MAX_STEP,
    Simulation,
    StepClock,
    loop_of,
    mount_position,
    position_on_loop,
)
from drvs.sim.world_file import load_world

WORLD = {
    'floor': {'size': [4.0, 3.0]},
    'robot': {'position': [0.5, 1.5], 'size': [0.3, 0.3, 0.2], 'colour': [0, 200, 0], 'speed': 0.5},
    'station': {'position': [3.5, 2.7], 'size': [0.4, 0.3, 0.1], 'colour': [0, 0, 220]},
    'objects': [
        {'name': 'wall', 'position': [2.0, 1.5], 'size': [0.4, 1.0, 0.5], 'colour': [60, 60, 60]},
        {
            'name': 'walker',
            'kind': 'human',
            'position': [0.5, 2.6],
            'size': [0.3, 0.3, 1.7],
            'colour': [220, 0, 0],
            'waypoints': [[0.5, 2.6], [0.5, 0.4]],
            'speed': 0.5,
        },
    ],
    'vision_systems': [
        {
            'name': 'vs1',
            'position': [1.0, 1.0, 3.0],
            'fov_deg': 60,
            'waypoints': [[1.0, 1.0], [3.0, 1.0]],
            'speed': 0.5,
        }
    ],
    'colour_models': {
        'self': 'colour:0,150,0,80,255,80',
        'station': 'colour:0,0,150,80,80,255',
        'obstacle': 'colour:40,40,40,90,90,90',
        'human': 'colour:150,0,0,255,80,80',
    },
}


@pytest.fixture
def simulations(tmp_path):
    """``make(world, walker=None, **robot)``: a Simulation of a copy of ``world`` whose walker
    and single robot take those keys; every one made is closed at the end."""
    made = []

    def make(world, walker=None, **robot):
        data = yaml.safe_load(yaml.safe_dump(world))
        if robot:
            data['robot'].update(robot)
        data['objects'][1].update(walker or {})
        path = tmp_path / f'world{len(made)}.yaml'
        path.write_text(yaml.safe_dump(data))
        made.append(Simulation(load_world(path)))
        return made[-1]

    yield make
    for sim in made:
        sim.scene.close()


@pytest.fixture
def simulation(simulations):
    return lambda walker=None, **robot: simulations(WORLD, walker, **robot)


def run(sim, seconds, dt=0.05):
    for _ in range(round(seconds / dt)):
        sim.step(dt)


@pytest.mark.parametrize(
    'elapsed, expected',
    [
        (0.0, (0.0, 0.0)),
        (1.0, (1.0, 0.0)),
        (2.5, (2.0, 0.5)),
        (5.0, (0.0, 1.0)),
        (5.5, (0.0, 0.5)),
        (7.0, (1.0, 0.0)),
    ],
)
def test_a_loop_is_walked_at_its_speed_and_repeats(elapsed, expected):
    loop = loop_of((0.0, 0.0), [(2.0, 0.0), (2.0, 1.0), (0.0, 1.0)])
    assert position_on_loop(loop, 1.0, elapsed) == pytest.approx(expected)


@pytest.mark.parametrize(
    'elapsed, expected', [(1.0, (1.0, 0.0)), (2.5, (2.0, 0.5)), (3.0, (2.0, 1.0)), (99.0, (2.0, 1.0))]
)
def test_a_path_that_does_not_loop_ends_standing_at_its_last_waypoint(elapsed, expected):
    path = loop_of((0.0, 0.0), [(2.0, 0.0), (2.0, 1.0)])
    assert position_on_loop(path, 1.0, elapsed, closed=False) == pytest.approx(expected)


def test_a_loop_starts_at_the_position_and_goes_back_to_it():
    assert loop_of((0, 0), [(1, 0), (1, 1)]) == [(0, 0), (1, 0), (1, 1)]
    assert loop_of((1, 1), [(1, 1), (2, 2), (1, 1)]) == [(1, 1), (2, 2)]


def test_humans_walk_their_waypoints_back_and_forth(simulation):
    sim = simulation()
    run(sim, 2.2)  # 1.1 m down the 2.2 m leg
    assert sim.poses()['walker'][:2] == pytest.approx((0.5, 1.5), abs=1e-6)
    run(sim, 4.4)  # down and back: one full loop later
    assert sim.poses()['walker'][:2] == pytest.approx((0.5, 1.5), abs=1e-6)


def test_a_walker_waiting_for_the_robot_starts_with_its_first_move_and_stands_at_the_end(simulation):
    sim = simulation(walker={'wait_for_robot': True, 'loop': False})
    run(sim, 3.0)
    assert sim.poses()['walker'][:2] == pytest.approx((0.5, 2.6))  # the robot has not moved yet
    sim.set_command(0.0, 0.1)
    run(sim, 2.0)  # 1 m down the 2.2 m leg
    assert sim.poses()['walker'][:2] == pytest.approx((0.5, 1.6), abs=1e-6)
    run(sim, 10.0)  # to the end, then it stands
    assert sim.poses()['walker'][:2] == pytest.approx((0.5, 0.4), abs=1e-6)


def test_the_robot_speed_is_capped(simulation):
    sim = simulation(position=[0.5, 0.5])
    sim.set_command(3.0, 4.0)  # 5 m/s asked, 0.5 allowed, same direction
    run(sim, 1.0)
    assert sim.robot.command == pytest.approx((0.3, 0.4))
    assert (sim.robot.x, sim.robot.y) == pytest.approx((0.8, 0.9))
    assert sim.robot.travelled == pytest.approx(0.5)


def test_the_robot_stops_at_an_obstacle_and_counts_one_contact(simulation):
    sim = simulation(position=[1.0, 1.5])
    sim.set_command(0.5, 0.0)
    run(sim, 3.0)  # would reach x = 2.5, through the wall
    assert sim.robot.x == pytest.approx(1.8 - 0.15, abs=0.002)  # touching the wall's face at x = 1.8
    assert sim.robot.x <= 1.65
    assert sim.robot.blocked and sim.robot.touching == {'wall'}
    assert sim.robot.contacts == 1
    sim.set_command(-0.5, 0.0)  # back off, then hit it again: a second contact
    run(sim, 0.5)
    assert sim.robot.touching == set()
    sim.set_command(0.5, 0.0)
    run(sim, 1.0)
    assert sim.robot.contacts == 2
    truth = sim.ground_truth()
    assert truth['contacts'] == 2 and truth['touching'] == ['wall']
    assert truth['robot']['position'] == pytest.approx([1.65, 1.5], abs=0.002)


def test_the_robot_stays_on_the_floor(simulation):
    sim = simulation(position=[3.5, 1.5])
    sim.set_command(0.5, 0.0)
    run(sim, 2.0)
    assert sim.robot.x == pytest.approx(4.0 - 0.15, abs=0.002)
    assert sim.robot.touching == {FLOOR_EDGE} and sim.robot.contacts == 1


def test_a_human_walking_into_the_robot_is_a_contact_and_the_robot_can_leave(simulation):
    sim = simulation(position=[0.5, 1.5])  # on the walker's line
    run(sim, 1.8)
    assert 'walker' in sim.robot.touching and sim.robot.contacts == 1
    sim.set_command(0.5, 0.0)  # sideways, out of the walker's way
    run(sim, 1.0)
    assert sim.robot.x == pytest.approx(1.0)
    assert 'walker' not in sim.robot.touching


def test_a_not_finite_command_stops_the_robot(simulation):
    sim = simulation()
    sim.set_command(math.nan, 0.1)
    assert sim.robot.command == (0.0, 0.0)


def test_a_camera_mount_moves_along_its_waypoints(simulation):
    camera = simulation().world.camera('vs1')
    assert mount_position(camera, 0.0) == (1.0, 1.0)
    assert mount_position(camera, 2.0) == pytest.approx((2.0, 1.0))
    assert mount_position(camera, 6.0) == pytest.approx((2.0, 1.0))  # on its way back


# -- fleets ---------------------------------------------------------------------------------------
def fleet_robot(name, position, colour, station, speed=0.5):
    return {
        'name': name,
        'position': position,
        'size': [0.3, 0.3, 0.2],
        'colour': colour,
        'speed': speed,
        'station': {'position': station, 'size': [0.4, 0.3, 0.1], 'colour': [colour[2], 0, 220]},
        'colour_models': {
            'self': f'colour:0,170,{max(colour[2] - 15, 0)},30,230,{colour[2] + 15}',
            'station': f'colour:{max(colour[2] - 15, 0)},0,200,{colour[2] + 15},30,240',
        },
    }


FLEET = {
    **{key: value for key, value in WORLD.items() if key not in ('robot', 'station', 'colour_models')},
    'robots': [
        fleet_robot('r1', [0.5, 0.5], [0, 200, 0], [3.5, 2.7]),
        fleet_robot('r2', [1.5, 0.5], [0, 200, 160], [3.5, 0.3], speed=0.2),
    ],
    'colour_models': {key: WORLD['colour_models'][key] for key in ('obstacle', 'human')}
    | {'robot': 'colour:0,170,0,30,230,175'},
}


@pytest.fixture
def fleet(simulations):
    return lambda walker=None: simulations(FLEET, walker)


def test_every_robot_is_driven_by_its_own_command_at_its_own_speed(fleet):
    sim = fleet()
    assert list(sim.robots) == ['r1', 'r2'] and sim.robot is sim.robots['r1']
    sim.set_command(0.0, 1.0)  # no robot named: the first
    sim.set_command(0.0, 1.0, 'r2')  # capped at r2's 0.2 m/s
    run(sim, 1.0)
    assert (sim.robots['r1'].x, sim.robots['r1'].y) == pytest.approx((0.5, 1.0))
    assert (sim.robots['r2'].x, sim.robots['r2'].y) == pytest.approx((1.5, 0.7))
    assert sim.poses()['r2'][:2] == pytest.approx((1.5, 0.7))


def test_a_robot_stops_at_another_and_both_count_the_contact(fleet):
    sim = fleet()
    sim.set_command(0.5, 0.0, 'r1')  # into r2, which stands
    run(sim, 2.0)
    r1, r2 = sim.robots['r1'], sim.robots['r2']
    assert r1.x == pytest.approx(1.5 - 0.3, abs=0.002) and r1.x <= 1.2
    assert r1.blocked and not r2.blocked
    assert (r1.touching, r1.contacts) == ({'r2'}, 1)
    assert (r2.touching, r2.contacts) == ({'r1'}, 1)
    assert (r2.x, r2.y) == (1.5, 0.5)
    sim.set_command(0.0, 0.0, 'r1')
    sim.set_command(0.2, 0.0, 'r2')  # r2 drives away: the touch ends for both
    run(sim, 0.5)
    assert r1.touching == set() and r2.touching == set()
    truth = sim.ground_truth()
    assert set(truth) == {
        'time',
        'robot',
        'contacts',
        'touching',
        'blocked',
        'travelled',
        'objects',
        'robots',
    }
    assert set(truth['robots']) == {'r1', 'r2'}
    assert truth['robots']['r2'] == {
        'position': pytest.approx([1.6, 0.5]),
        'yaw': 0.0,
        'command': pytest.approx([0.2, 0.0]),
        'contacts': 1,
        'touching': [],
        'blocked': False,
        'travelled': pytest.approx(0.1),
    }
    first = truth['robots']['r1']  # the top-level keys are the first robot's, as in the paper's worlds
    assert truth['robot'] == {key: first[key] for key in ('position', 'yaw', 'command')}
    assert [truth[key] for key in ('contacts', 'touching', 'blocked', 'travelled')] == [
        first[key] for key in ('contacts', 'touching', 'blocked', 'travelled')
    ]
    assert {'r1', 'r1_station', 'r2', 'r2_station', 'wall', 'walker'} == set(truth['objects'])


def test_robots_driving_into_each_other_stop_apart(fleet):
    sim = fleet()
    sim.set_command(0.5, 0.0, 'r1')
    sim.set_command(-0.2, 0.0, 'r2')
    run(sim, 3.0)
    r1, r2 = sim.robots['r1'], sim.robots['r2']
    assert r2.x - r1.x == pytest.approx(0.3, abs=0.002) and r2.x - r1.x >= 0.3 - 1e-9
    assert r1.contacts == r2.contacts == 1 and r1.blocked and r2.blocked


def test_a_walker_waiting_for_the_robots_starts_when_any_robot_moves(fleet):
    sim = fleet(walker={'wait_for_robot': True, 'loop': False})
    run(sim, 1.0)
    assert sim.poses()['walker'][:2] == pytest.approx((0.5, 2.6))
    sim.set_command(0.0, 0.1, 'r2')
    run(sim, 1.0)
    assert sim.poses()['walker'][:2] == pytest.approx((0.5, 2.1), abs=1e-6)


def test_the_step_clock_follows_the_wall_clock_or_runs_slower_on_simulated_time():
    assert doctest.testmod(drvs.sim.simulation).failed == 0
    walls = iter([100.0, 100.1, 100.4, 100.5])
    clock = StepClock(lambda: next(walls))  # real time: the wall time, with each step capped
    assert clock.tick() == pytest.approx((100.1, 0.1))
    assert clock.tick() == pytest.approx((100.4, MAX_STEP))  # 0.3 s since the last tick
    assert clock.now() == 100.5  # the wall clock's, between ticks too
    with pytest.raises(ValueError):
        StepClock(lambda: 0.0, real_time_factor=0.5)  # slower than real time needs simulated time
