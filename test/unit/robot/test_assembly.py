"""The blind robot's parts from its parameters (drvs.robot.assembly)."""

import math

import pytest

from drvs.robot.assembly import assemble
from drvs.robot.mapping import HEADROOM
from drvs.robot.mission import fleet_robot
from drvs.robot.params import RobotParams
from drvs.sim.world_file import load_world


@pytest.mark.parametrize('name, rank', [('robot1', 0), ('robot2', 1)])
def test_a_fleet_robot_is_sized_by_its_body_and_waits_longer_the_later_its_name_sorts(name, rank):
    world = load_world('worlds/crossing.yaml')
    params = RobotParams(world='worlds/crossing.yaml', robot=name, yield_patience=1.0)
    parts = assemble(params, world, fleet_robot(world, name, f'/{name}'), f'/{name}')
    me = fleet_robot(world, name, f'/{name}')
    assert parts.robot_radius == pytest.approx(math.hypot(*me.body.size[:2]) / 2)
    assert (
        parts.settings.radius == parts.robot_radius
        and parts.settings.corridor_margin == params.roi_margin / 2
    )
    assert parts.yielding.patience == pytest.approx(1.0 * (1 + rank / 2))
    assert set(parts.fused_roles) == {'station', 'human', 'robot'}  # itself and static obstacles: per camera
    assert parts.watching


def test_a_given_radius_and_per_camera_answers():
    world = load_world('worlds/crossing.yaml')
    params = RobotParams(world='worlds/crossing.yaml', robot='robot1', robot_radius=0.3, fused=False)
    parts = assemble(params, world, fleet_robot(world, 'robot1', '/robot1'), '/robot1')
    assert (parts.robot_radius, parts.fused_roles) == (0.3, [])


def test_the_robot_drives_under_what_leaves_room_for_its_height_in_the_world_or_as_given():
    world = load_world('worlds/crossing.yaml')
    me = fleet_robot(world, 'robot1', '/robot1')
    parts = assemble(RobotParams(world='worlds/crossing.yaml', robot='robot1'), world, me, '/robot1')
    assert parts.map.head == pytest.approx(me.body.size[2] + HEADROOM)
    given = RobotParams(world='worlds/crossing.yaml', robot='robot1', robot_height=0.5)
    assert assemble(given, world, me, '/robot1').map.head == pytest.approx(0.5 + HEADROOM)
