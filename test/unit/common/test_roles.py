"""The roles a robot asks about: one list (drvs/common/roles.py) that the world file checker uses,
and that the robot's own constants must agree with until it imports it too."""

from drvs.common import roles
from drvs.robot import perception
from drvs.sim import world


def test_the_robot_and_the_checker_know_the_same_roles():
    assert perception.ROLES == roles.REQUIRED_ROLES == world.ROLES
    assert perception.LOCALISATION_ROLES == roles.LOCALISATION_ROLES == world.OWN_ROLES
    assert perception.FLEET_ROLE in roles.ROBOT_ROLES and set(perception.STATIC_ROLES) <= set(
        roles.ROBOT_ROLES
    )
    assert set(roles.ROBOT_ROLES) == {*roles.REQUIRED_ROLES, *roles.SHARED_ROLES}


def test_an_unknown_role_gets_the_nearest_or_the_list():
    assert roles.unknown_role('obstacles') == (
        'unknown role; did you mean obstacle? (roles: self, station, obstacle, human, robot)'
    )
    assert roles.unknown_role('pallet') == 'unknown role (roles: self, station, obstacle, human, robot)'
    assert roles.unknown_role('robot') is None
