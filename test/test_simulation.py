"""world_sim's core: waypoint loops, the robot's speed cap, stopping at obstacles, counting contacts."""

import math

import pytest
import yaml

from drvs.simulation import FLOOR_EDGE, Simulation, loop_of, mount_position, position_on_loop
from drvs.world import load_world

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
def simulation(tmp_path):
    def make(walker=None, **robot):
        data = yaml.safe_load(yaml.safe_dump(WORLD))
        data['robot'].update(robot)
        data['objects'][1].update(walker or {})
        path = tmp_path / 'world.yaml'
        path.write_text(yaml.safe_dump(data))
        sim = Simulation(load_world(path))
        made.append(sim)
        return sim

    made = []
    yield make
    for sim in made:
        sim.scene.close()


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
