"""A world: floor, robots and their stations, objects and cameras, as loaded from a world file.

The file's keys are read by :mod:`drvs.sim.world_file` (:func:`~drvs.sim.world_file.load_world`),
which reports every problem at once through :class:`WorldError`; whether a world makes sense is
checked by :mod:`drvs.sim.world_sense`. The keys are documented in ``worlds/README.md``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from drvs.common.roles import LOCALISATION_ROLES, REQUIRED_ROLES
from drvs.sim.depth_noise import DepthNoise

KINDS = ('static', 'human')
ROLES = REQUIRED_ROLES
"""The roles of the single form's colour_models, all required (:mod:`drvs.common.roles`)."""
OWN_ROLES = LOCALISATION_ROLES
"""The roles each robot of ``robots:`` has a model of its own for, in its own ``colour_models``;
the fleet's top-level ones are :data:`drvs.common.roles.SHARED_ROLES`."""


@dataclass(frozen=True)
class Problem:
    """One thing wrong in a world file: the entry (by its name, '' for the file), the key, what."""

    entry: str
    key: str
    message: str

    def __str__(self) -> str:
        where = '.'.join(part for part in (self.entry, self.key) if part)
        return f'{where}: {self.message}' if where else self.message


class WorldError(ValueError):
    """A world file that cannot be used, with every :class:`Problem` found in it.

    ``str()`` is the single problem on one line (``FILE: entry.key: problem``), or
    ``FILE: N problems:`` followed by one indented line per problem.
    """

    def __init__(self, path: str | Path, problems: Iterable[Problem]):
        self.path = Path(path)
        self.problems = tuple(problems)
        if len(self.problems) == 1:
            text = f'{self.path}: {self.problems[0]}'
        else:
            lines = [f'{self.path}: {len(self.problems)} problems:']
            lines += [f'  {problem}' for problem in self.problems]
            text = '\n'.join(lines)
        super().__init__(text)


@dataclass(frozen=True)
class Tag:
    """An AprilTag lying on top of a body, centred, turned with it: ``size`` is its black square's
    side in metres. Its printed top points along the body's +y axis, its printed right along +x
    (the body's heading)."""

    family: str
    id: int
    size: float

    @property
    def label(self) -> str:
        """What the ``apriltag`` algorithm labels it: ``tag36h11:3``."""
        return f'{self.family}:{self.id}'


@dataclass(frozen=True)
class Body:
    """A box standing on the floor: footprint centre, size [x, y, z] in metres, yaw in radians;
    the robot and the station may carry a :class:`Tag` on top. A static object may hang
    ``bottom`` metres above the floor (a shelf): it spans heights bottom to bottom + size z."""

    name: str
    position: tuple[float, float]
    size: tuple[float, float, float]
    colour: tuple[int, int, int]
    yaw: float = 0.0
    kind: str = 'static'
    waypoints: tuple[tuple[float, float], ...] = ()
    speed: float = 0.0
    loop: bool = True
    wait_for_robot: bool = False
    tag: Tag | None = None
    through_obstacles: bool = False
    decoy: bool = False
    shiny: bool = False
    bottom: float = 0.0

    @property
    def top(self) -> float:
        """Metres above the floor of its top."""
        return self.bottom + self.size[2]

    @property
    def moving(self) -> bool:
        return len(self.waypoints) >= 2 and self.speed > 0

    def footprint(self) -> list[tuple[float, float]]:
        """The four floor corners of the box at its start pose, counter-clockwise."""
        return box_footprint(self.position, self.size[:2], self.yaw)


@dataclass(frozen=True)
class Camera:
    """An overhead vision system: its optical centre, where it looks, field of view and resolution.

    ``fov_deg`` is the vertical field of view (as PyBullet's
    ``computeProjectionMatrixFOV``); image rows run along ``up`` (default +y of
    ``map``). ``waypoints`` and ``speed`` move the camera mount (x, y; height kept).
    ``distortion`` is the lens's plumb_bob model (k1, k2, p1, p2, k3), as in a
    CameraInfo's ``D``; empty for an ideal pinhole. The simulation applies it to the
    frames it publishes (:mod:`drvs.sim.lens`). ``depth_noise``: how its depth images fall short
    of perfect (:mod:`drvs.sim.depth_noise`); None for perfect depth. ``site``: the site whose
    server it registers with (``scripts/run_scenario.sh --sites``); empty in a world of one site.
    """

    name: str
    position: tuple[float, float, float]
    fov_deg: float
    resolution: tuple[int, int]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    waypoints: tuple[tuple[float, float], ...] = ()
    speed: float = 0.0
    distortion: tuple[float, ...] = ()
    depth_noise: DepthNoise | None = None
    site: str = ''

    @property
    def moving(self) -> bool:
        return len(self.waypoints) >= 2 and self.speed > 0


@dataclass(frozen=True)
class FleetRobot:
    """One robot of the world with its station.

    ``name`` is the body's name and the node name of its blind_robot (``robot`` in the single
    form); ``colour_models`` its complete role -> algorithm map: the world's shared roles
    (obstacle, human, robot, ...) and its own ``self`` and ``station``.
    """

    name: str
    body: Body
    station: Body
    colour_models: dict[str, str]


@dataclass(frozen=True)
class World:
    """A loaded world file. ``robots`` has one entry in the single ``robot:``/``station:`` form;
    :attr:`robot`, :attr:`station` and :attr:`colour_models` are the first robot's.
    ``real_time_factor`` below 1 runs the world on ROS simulated time (``/clock``) that much slower."""

    path: Path
    floor_size: tuple[float, float]
    robots: tuple[FleetRobot, ...]
    objects: tuple[Body, ...]
    vision_systems: tuple[Camera, ...]
    floor_colour: tuple[int, int, int] = (255, 255, 255)
    real_time_factor: float = 1.0

    @property
    def robot(self) -> Body:
        return self.robots[0].body

    @property
    def station(self) -> Body:
        return self.robots[0].station

    @property
    def colour_models(self) -> dict[str, str]:
        return self.robots[0].colour_models

    def tag_heights(self) -> dict[str, float]:
        """{"FAMILY:ID": height} of the tags on top of the robots and stations."""
        return {
            f'{body.tag.family}:{body.tag.id}': float(body.size[2])
            for robot in self.robots
            for body in (robot.body, robot.station)
            if body.tag is not None
        }

    def fleet_robot(self, name: str) -> FleetRobot:
        for robot in self.robots:
            if robot.name == name:
                return robot
        raise WorldError(self.path, [_unknown_entry('robots', name, [r.name for r in self.robots])])

    def camera(self, name: str) -> Camera:
        for camera in self.vision_systems:
            if camera.name == name:
                return camera
        raise WorldError(
            self.path, [_unknown_entry('vision_systems', name, [c.name for c in self.vision_systems])]
        )


def _unknown_entry(where: str, name: str, known: list[str]) -> Problem:
    return Problem(where, '', f'no entry named {name!r} (known: {", ".join(known) or "none"})')


def box_footprint(centre: Sequence[float], size: Sequence[float], yaw: float) -> list[tuple[float, float]]:
    """Corners of a yawed rectangle centred at ``centre`` with ``size`` [x, y], counter-clockwise."""
    cx, cy = centre
    hx, hy = size[0] / 2.0, size[1] / 2.0
    c, s = math.cos(yaw), math.sin(yaw)
    return [
        (cx + c * dx - s * dy, cy + s * dx + c * dy)
        for dx, dy in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))
    ]
