"""The roles a robot asks about: one list (drvs/common/roles.py) for the robot and the world file checker."""

from drvs.common import roles
from drvs.robot import perception


def test_every_role_is_a_robot_role():
    assert roles.FLEET_ROLE in roles.SHARED_ROLES and set(perception.STATIC_ROLES) <= set(roles.ROBOT_ROLES)
    assert set(roles.ROBOT_ROLES) == {*roles.REQUIRED_ROLES, *roles.SHARED_ROLES}


def test_an_unknown_role_gets_the_nearest_or_the_list():
    assert roles.unknown_role('obstacles') == (
        'unknown role; did you mean obstacle? (roles: self, station, obstacle, human, robot)'
    )
    assert roles.unknown_role('pallet') == 'unknown role (roles: self, station, obstacle, human, robot)'
    assert roles.unknown_role('robot') is None
