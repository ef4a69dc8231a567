"""The roles a robot asks the vision systems about: the keys of a world file's ``colour_models``.

One list for the robot (drvs/robot, which asks for each role's algorithm) and for the world file
checker (drvs/sim/world_file.py, ``drvs_check_world``), so that a role name the robot would never
ask for is refused where it is written. What each role is: worlds/README.md (``colour_models``).

>>> unknown_role('humna')
'unknown role; did you mean human? (roles: self, station, obstacle, human, robot)'
>>> unknown_role('human') is None
True
"""

from __future__ import annotations

import difflib

__all__ = [
    'FLEET_ROLE',
    'LOCALISATION_ROLES',
    'REQUIRED_ROLES',
    'ROBOT_ROLES',
    'SHARED_ROLES',
    'unknown_role',
]

LOCALISATION_ROLES = ('self', 'station')
"""What a robot finds to know where it is and where it goes; each robot has models of its own."""
REQUIRED_ROLES = ('self', 'station', 'obstacle', 'human')
"""The roles every robot has a model for."""
SHARED_ROLES = ('obstacle', 'human', 'robot')
"""The roles a fleet's robots share (the top-level ``colour_models`` of ``robots:``); ``robot``
finds every robot, and is required with more than one."""
ROBOT_ROLES = ('self', 'station', 'obstacle', 'human', 'robot')
"""Every role a robot asks about; a world naming another is refused. A new kind of obstacle the
robot should ask about is added here (and to worlds/README.md)."""
FLEET_ROLE = 'robot'
"""The role whose model finds every robot of a fleet, the asking one too (the robot cuts its own
body out of what it finds: drvs/robot/perception.py ``cut_bodies``)."""


def unknown_role(role: object) -> str | None:
    """Why ``role`` is not a role (with the nearest known one), or None when it is one."""
    if role in ROBOT_ROLES:
        return None
    listing = f'(roles: {", ".join(ROBOT_ROLES)})'
    close = difflib.get_close_matches(str(role), ROBOT_ROLES, n=1)
    return f'unknown role; did you mean {close[0]}? {listing}' if close else f'unknown role {listing}'
