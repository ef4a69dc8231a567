"""World files (``worlds/*.yaml``): load a scenario description, refusing one that makes no sense.

A file is read in two passes, and every problem of both is reported at once in one
:class:`WorldError`: first the form of each entry (types, ranges, keys that do not
apply to it), then, over the entries that read well, whether the world is possible
(bodies on the floor and apart, human walks clear of the boxes, colour models that
find what they are meant to find and nothing else, cameras that see the floor).
Each problem names the entry by its ``name`` and the key, for example::

    worlds/x.yaml: 2 problems:
      station.position: [8.0, 0.8] is outside the floor (x 0..7, y 0..5.5)
      object 'box1'.size: expected 3 positive numbers [x, y, z], got [0.4, 0.6]

A world has one robot (``robot:`` and ``station:``, the paper's form) or a fleet
(``robots:``, each robot with its station and its own ``self`` and ``station``
colour models, the shared roles at the top); :attr:`World.robots` lists them alike
(:class:`FleetRobot`), a fleet's entries labelled ``robots 'r2'``, ``robots 'r2'.station``
and ``robots 'r2'.colour_models``.

The keys are documented in ``worlds/README.md``; the stable core is in docs/design.md.
"""

from __future__ import annotations

import difflib
import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from shapely.geometry import MultiPoint, Polygon

from drvs.algorithms import AlgorithmError, ColourModel, parse_algorithm
from drvs.algorithms.apriltag import TagQuery
from drvs.camera import PinholeCamera
from drvs.tag_images import FAMILIES, FAMILY_NAMES

KINDS = ('static', 'human')
ROLES = ('self', 'station', 'obstacle', 'human')
"""The roles of the single form's colour_models, all required."""
OWN_ROLES = ('self', 'station')
"""The roles each robot of ``robots:`` has a model of its own for, in its own ``colour_models``."""
SHARED_ROLES = ('obstacle', 'human', 'robot')
"""The roles of a fleet's top-level colour_models; ``robot`` (a model that finds every robot) is
required with more than one robot, optional otherwise (also in the single form)."""

TOP_KEYS = (
    'floor',
    'robot',
    'station',
    'robots',
    'objects',
    'vision_systems',
    'colour_models',
    'real_time_factor',
)
FLOOR_KEYS = ('size', 'colour')
ROBOT_KEYS = ('name', 'position', 'size', 'yaw', 'colour', 'speed', 'tag')
FLEET_ROBOT_KEYS = (*ROBOT_KEYS, 'station', 'colour_models')
STATION_KEYS = ('name', 'position', 'size', 'yaw', 'colour', 'tag')
STATIC_KEYS = ('name', 'kind', 'position', 'size', 'yaw', 'colour', 'decoy')
HUMAN_KEYS = (
    *STATIC_KEYS,
    'waypoints',
    'speed',
    'loop',
    'wait_for_robot',
    'through_obstacles',
)
TAG_KEYS = ('family', 'id', 'size')
CAMERA_KEYS = (
    'name',
    'position',
    'fov_deg',
    'resolution',
    'target',
    'up',
    'waypoints',
    'speed',
    'distortion',
)
_ALL_KEYS = frozenset((*TOP_KEYS, *FLOOR_KEYS, *FLEET_ROBOT_KEYS, *HUMAN_KEYS, *TAG_KEYS, *CAMERA_KEYS))
_HUMANS_ONLY = 'applies to humans only: add kind: human to make it walk'
_TAGS_ONLY = 'only the robot and the station carry a tag'
_FORMS = 'a world has robot: and station: (one robot) or robots: (a list of robots, each with its station)'

AREA = 1e-9
"""Square metres below which two footprints touch rather than overlap."""
EDGE = 1e-9
"""Metres a footprint may reach past the floor's edge (rounding)."""


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

    def __init__(self, path: str | Path, problems):
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
    the robot and the station may carry a :class:`Tag` on top."""

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
    frames it publishes (:mod:`drvs.lens`).
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


def box_footprint(centre, size, yaw: float) -> list[tuple[float, float]]:
    """Corners of a yawed rectangle centred at ``centre`` with ``size`` [x, y], counter-clockwise."""
    cx, cy = centre
    hx, hy = size[0] / 2.0, size[1] / 2.0
    c, s = math.cos(yaw), math.sin(yaw)
    return [
        (cx + c * dx - s * dy, cy + s * dx + c * dy)
        for dx, dy in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))
    ]


# -- pass 1: the form of each entry ---------------------------------------------------------------
class _Invalid(Exception):
    """A value that cannot be read; ``where`` is a suffix of its key (``[1]`` for a list item)."""

    def __init__(self, message: str, where: str = ''):
        super().__init__(message)
        self.message, self.where = message, where


def _expected(what: str, got) -> _Invalid:
    return _Invalid(f'expected {what}, got {got!r}')


def _is_number(value) -> bool:
    return not isinstance(value, bool) and isinstance(value, int | float) and math.isfinite(value)


def _is_integer(value, low: int, high: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and low <= value <= high


def _number(value, positive: bool = False) -> float:
    if not _is_number(value):
        raise _expected('a finite number', value)
    if positive and value <= 0:
        raise _expected('a positive number', value)
    return float(value)


def _vector(value, n: int, what: str, positive: bool = False) -> tuple[float, ...]:
    if (
        not isinstance(value, list | tuple)
        or len(value) != n
        or not all(_is_number(v) and (v > 0 or not positive) for v in value)
    ):
        raise _expected(f'{n} {"positive " if positive else ""}numbers {what}', value)
    return tuple(float(v) for v in value)


def _integers(value, n: int, low: int, high: int, what: str) -> tuple[int, ...]:
    if (
        not isinstance(value, list | tuple)
        or len(value) != n
        or not all(_is_integer(v, low, high) for v in value)
    ):
        raise _expected(f'{n} integers {low}-{high} {what}', value)
    return tuple(value)


def _colour(value) -> tuple[int, int, int]:
    return _integers(value, 3, 0, 255, '[r, g, b]')


def _points(value) -> tuple[tuple[float, float], ...]:
    if not isinstance(value, list) or len(value) < 2:
        raise _expected('a list of at least 2 points [[x, y], ...]', value)
    points = []
    for i, point in enumerate(value):
        try:
            points.append(_vector(point, 2, '[x, y]'))
        except _Invalid as error:
            raise _Invalid(error.message, f'[{i}]') from None
    return tuple(points)


def _flag(value) -> bool:
    if not isinstance(value, bool):
        raise _expected('true or false', value)
    return value


def _factor(value) -> float:
    if not _is_number(value) or not 0 < value <= 1:
        raise _expected('a number in (0, 1]', value)
    return float(value)


def _one_of(value, choices: tuple[str, ...], expected: str) -> str:
    if value not in choices:
        raise _expected(expected, value)
    return value


def _tag_id(value, family: str) -> int:
    count = FAMILIES[family].ids
    if not _is_integer(value, 0, count - 1):
        raise _expected(f'an integer 0-{count - 1} (an id of {family})', value)
    return value


def _body_name(value) -> str:
    if not isinstance(value, str) or not value:
        raise _expected('a non-empty string', value)
    return value


def _is_node_name(value) -> bool:
    return isinstance(value, str) and value[:1].isalpha() and value.replace('_', 'a').isalnum()


def _node_name(value) -> str:
    if not _is_node_name(value):
        raise _expected('a ROS node name (letters, digits, _; starting with a letter)', value)
    return value


def _list(value, non_empty: bool) -> list:
    if value is None and not non_empty:
        return []
    if not isinstance(value, list) or (non_empty and not value):
        raise _expected('a non-empty list' if non_empty else 'a list', value)
    return value


def _mapping(value) -> dict:
    if not isinstance(value, dict):
        raise _expected('a mapping', value)
    return value


class _Report:
    """The problems found so far; :meth:`sorted` lists them in the order the file names its entries."""

    def __init__(self):
        self.problems: list[Problem] = []
        self.entries: list[str] = ['', 'floor']

    def entry(self, label: str) -> str:
        self.entries.append(label)
        return label

    def add(self, entry: str, key: str, message: str) -> None:
        self.problems.append(Problem(entry, key, message))

    def sorted(self) -> list[Problem]:
        order = {label: i for i, label in reversed(list(enumerate(self.entries)))}  # first mention
        return sorted(self.problems, key=lambda problem: order.get(problem.entry, len(order)))


_REQUIRED = object()


class _Entry:
    """The keys of one mapping of a world file, read one by one: a bad key is reported and reads
    as None, so the other keys (and entries) are still checked. ``broken`` says whether a value
    is missing or bad (a key that does not apply alone does not break the entry)."""

    def __init__(self, report: _Report, label: str, data: dict, keys, what: str, hints=None, prefix=''):
        self.report, self.label, self.data, self.prefix = report, label, data, prefix
        self.broken = False
        for key in data:
            if key not in keys:
                self.report.add(label, prefix + str(key), _unknown_key(key, keys, what, hints or {}))

    def problem(self, key: str, message: str) -> None:
        self.report.add(self.label, self.prefix + key, message)
        self.broken = True

    def read(self, key: str, reader: Callable, *args, default=_REQUIRED, missing: str = 'missing'):
        """``reader(value, *args)`` of ``key``; ``default`` (as is) when it is absent."""
        if key not in self.data:
            if default is _REQUIRED:
                self.problem(key, missing)
                return None
            return default
        try:
            return reader(self.data[key], *args)
        except _Invalid as error:
            self.problem(key + error.where, error.message)
            return None


def _unknown_key(key, keys: tuple[str, ...], what: str, hints: dict[str, str]) -> str:
    """Why ``key`` is refused in an entry whose keys are ``keys``; "did you mean" when one is close.

    >>> _unknown_key('posiiton', ('name', 'position'), 'the robot', {})
    'unknown key; did you mean position? (keys of the robot: name, position)'
    """
    listing = f'(keys of {what}: {", ".join(keys)})'
    if key in hints:
        return f'{hints[key]} {listing}'
    if key in _ALL_KEYS:
        return f'does not apply to {what} {listing}'
    close = difflib.get_close_matches(str(key), keys, n=1) or difflib.get_close_matches(
        str(key), sorted(_ALL_KEYS), n=1
    )
    return f'unknown key; did you mean {close[0]}? {listing}' if close else f'unknown key {listing}'


def _tag(entry: _Entry, body_size) -> Tag | None:
    """The ``tag`` of the robot or the station; its problems are reported as ``tag.KEY``."""
    data = entry.read('tag', _mapping)
    if data is None:
        return None
    tag = _Entry(entry.report, entry.label, data, TAG_KEYS, 'a tag', prefix='tag.')
    family = tag.read('family', _one_of, FAMILY_NAMES, f'one of {", ".join(FAMILY_NAMES)}')
    tag_id = tag.read('id', _tag_id, family) if family is not None else None
    side = tag.read('size', _number, True)
    if side is not None and body_size is not None and side > min(body_size[:2]):
        smaller = min(body_size[:2])
        tag.problem('size', f"expected at most the body's smaller side, {smaller:g} m, got {side!r}")
    entry.broken = entry.broken or tag.broken
    return None if tag.broken else Tag(family, tag_id, side)


_BODY_KEYS = {
    # entry kind: (its keys, what it is called, why some other keys do not apply)
    'robot': (ROBOT_KEYS, 'the robot', {'waypoints': 'does not apply: only humans walk'}),
    'fleet robot': (FLEET_ROBOT_KEYS, 'a robot of robots', {'waypoints': 'does not apply: only humans walk'}),
    'station': (STATION_KEYS, 'the station', {'speed': 'does not apply: the station does not move'}),
    'static': (
        STATIC_KEYS,
        'a static object',
        {**dict.fromkeys(HUMAN_KEYS[len(STATIC_KEYS) :], _HUMANS_ONLY), 'tag': _TAGS_ONLY},
    ),
    'human': (HUMAN_KEYS, 'a human', {'tag': _TAGS_ONLY}),
}


def _label(data: dict, where: str, role: str, fleet: bool) -> str:
    """An entry's label: ``where`` unless a usable name gives a better one (``robot 'r1'``,
    ``object 'box1'``, ``human 'walker'``, ``robots 'r1'``; a robot's name is its node name)."""
    name = data.get('name')
    usable = _is_node_name(name) if role == 'robot' else isinstance(name, str) and name != ''
    if fleet:
        return f'robots {name!r}' if role == 'robot' and usable else where
    noun = ('human' if data.get('kind') == 'human' else 'object') if role == 'object' else role
    return f'{noun} {name!r}' if usable and name != where else where


def _body(report: _Report, data, role: str, where: str, name: str | None, fleet: bool = False):
    """A body (``role`` 'robot', 'station' or 'object') with its label for messages, or None when
    it is unusable (its problems are reported). ``where`` is the entry's place (``robot``,
    ``objects[2]``, ``robots[1]``, ``robots 'r1'.station``), ``name`` its default name (None: a
    name is required), ``fleet`` says it is an entry of ``robots:`` or the station of one."""
    if not isinstance(data, dict):
        report.add(report.entry(where), '', f'expected a mapping, got {data!r}')
        return None
    kind = data.get('kind', 'static') if role == 'object' else role
    label = report.entry(_label(data, where, role, fleet))
    if role == 'object' and kind not in KINDS:  # reported below; any object key may apply
        keys, what, hints = HUMAN_KEYS, 'an object', {'tag': _TAGS_ONLY}
    else:
        keys, what, hints = _BODY_KEYS['fleet robot' if fleet and kind == 'robot' else kind]
    entry = _Entry(report, label, data, keys, what, hints)
    reader = _node_name if role == 'robot' else _body_name
    name = entry.read('name', reader, default=_REQUIRED if name is None else name)
    if role == 'object':
        entry.read('kind', _one_of, KINDS, 'static or human', default=kind)
    position = entry.read('position', _vector, 2, '[x, y]')
    size = entry.read('size', _vector, 3, '[x, y, z]', True)
    values = {
        'colour': entry.read('colour', _colour),
        'yaw': entry.read('yaw', _number, default=0.0),
    }
    if role == 'robot':
        values['speed'] = entry.read('speed', _number, True, default=0.4)
    if kind == 'human':
        values['waypoints'] = entry.read('waypoints', _points, missing='missing: the points a human walks to')
        values['speed'] = entry.read('speed', _number, True, missing='missing: how fast a human walks, m/s')
        for flag, default in (('loop', True), ('wait_for_robot', False), ('through_obstacles', False)):
            values[flag] = entry.read(flag, _flag, default=default)
    if role == 'object':
        values['decoy'] = entry.read('decoy', _flag, default=False)
    else:
        values['tag'] = _tag(entry, size) if 'tag' in data else None
    if entry.broken:
        return None
    return label, Body(name=name, position=position, size=size, kind=kind, **values)


def _camera(report: _Report, data, index: int) -> tuple[str, Camera] | None:
    """``vision_systems[index]`` with its label; None when it is unusable."""
    where = f'vision_systems[{index}]'
    if not isinstance(data, dict):
        report.add(report.entry(where), '', f'expected a mapping, got {data!r}')
        return None
    name = data.get('name')
    label = report.entry(f'vision_system {name!r}' if _is_node_name(name) else where)
    entry = _Entry(report, label, data, CAMERA_KEYS, 'a vision system')
    entry.read('name', _node_name)
    position = entry.read('position', _vector, 3, '[x, y, z]')
    if position is not None and position[2] <= 0:
        entry.problem('position', f'expected a camera above the floor (z > 0), got {list(position)}')
    fov = entry.read('fov_deg', _number)
    if fov is not None and not 1.0 <= fov <= 170.0:
        entry.problem('fov_deg', f'expected a vertical field of view between 1 and 170 degrees, got {fov!r}')
    resolution = entry.read('resolution', _integers, 2, 16, 4096, '[width, height]', default=(800, 600))
    below = None if position is None else (position[0], position[1], 0.0)
    target = entry.read('target', _vector, 3, '[x, y, z]', default=below)
    up = entry.read('up', _vector, 3, '[x, y, z]', default=(0.0, 1.0, 0.0))
    waypoints, speed = (), 0.0
    if 'waypoints' in data or 'speed' in data:
        mount = 'missing: a moving mount needs both waypoints and speed'
        waypoints = entry.read('waypoints', _points, missing=mount)
        speed = entry.read('speed', _number, True, missing=mount)
    distortion = entry.read('distortion', _vector, 5, '[k1, k2, p1, p2, k3]', default=())
    if distortion and any(abs(c) > 10.0 for c in distortion):
        entry.problem(
            'distortion',
            f'expected plumb_bob coefficients [k1, k2, p1, p2, k3], each within +-10, got {list(distortion)}',
        )
    if entry.broken:
        return None
    return label, Camera(name, position, fov, tuple(resolution), target, up, waypoints, speed, distortion)


def _models(
    report: _Report, data, where: str, required: dict[str, str], refuse: Callable[[str], str | None]
) -> dict[str, tuple[str, object]]:
    """Role -> (algorithm string, parsed parameters) of each colour model of the mapping at ``where``
    that parses. ``required``: role -> the message when it is missing; ``refuse(role)``: why a role
    does not belong here, or None."""
    report.entry(where)
    try:
        data = _mapping(data)
    except _Invalid as error:
        report.add(where, '', error.message)
        return {}
    models = {}
    for role, message in required.items():
        if role not in data:
            report.add(where, role, message)
    for role, text in data.items():
        refused = refuse(str(role))
        if refused:
            report.add(where, str(role), refused)
            continue
        if not isinstance(text, str):
            report.add(where, str(role), f'expected an algorithm string, got {text!r}')
            continue
        try:
            models[role] = (text, parse_algorithm(text).params)
        except AlgorithmError as error:
            report.add(where, str(role), str(error))
    return models


def _top_models(report: _Report, data, fleet: bool | None, robots: int) -> dict[str, tuple[str, object]]:
    """The top-level ``colour_models``: every role in the single form, the shared roles of a fleet
    (``fleet`` None: the file has neither form, which is reported, so no role is missing)."""
    if not fleet:
        missing = f'missing (roles: {", ".join(ROLES)})'
        required = dict.fromkeys(ROLES if fleet is not None else (), missing)
        return _models(report, data, 'colour_models', required, lambda role: None)
    missing = f'missing (roles: {", ".join(SHARED_ROLES)})'
    required = dict.fromkeys(SHARED_ROLES[:2], missing)
    if robots > 1:
        required['robot'] = f'missing: with several robots, a model that finds every robot ({missing[9:-1]})'
    own = "with robots:, each robot has its own: put it in the robot's colour_models"
    return _models(report, data, 'colour_models', required, lambda role: own if role in OWN_ROLES else None)


def _fleet_robot(report: _Report, data, index: int):
    """``robots[index]``: its label, its body and its station (each (label, Body) or None), and its
    own models."""
    where = f'robots[{index}]'
    robot = _body(report, data, 'robot', where, None, fleet=True)
    if not isinstance(data, dict):
        return where, robot, None, {}
    label = _label(data, where, 'robot', True)
    for key in ('station', 'colour_models'):
        if key not in data:
            report.add(label, key, 'missing')
    station = None
    if 'station' in data:
        default = f'{data["name"]}_station' if _is_node_name(data.get('name')) else f'station{index}'
        station = _body(report, data['station'], 'station', f'{label}.station', default, fleet=True)
    models = {}
    if 'colour_models' in data:
        shared = "a shared role: put it in the top-level colour_models (a robot's own are self and station)"
        missing = f'missing (roles: {", ".join(OWN_ROLES)})'
        models = _models(
            report,
            data['colour_models'],
            f'{label}.colour_models',
            dict.fromkeys(OWN_ROLES, missing),
            lambda role: None if role in OWN_ROLES else shared,
        )
    return label, robot, station, models


# -- pass 2: whether the world is possible ----------------------------------------------------------
def _n(value: float) -> str:
    return f'{round(value, 3):g}'


def _floor_text(floor) -> str:
    return f'the floor (x 0..{_n(floor[0])}, y 0..{_n(floor[1])})'


def _off_floor(point, footprint, floor) -> str | None:
    """Why a body at ``point`` with ``footprint`` is not on the floor, or None."""
    if not (0 <= point[0] <= floor[0] and 0 <= point[1] <= floor[1]):
        return f'{list(point)} is outside {_floor_text(floor)}'
    xs, ys = [p[0] for p in footprint], [p[1] for p in footprint]
    past = max(-min(xs), max(xs) - floor[0], -min(ys), max(ys) - floor[1])
    if past <= EDGE:
        return None
    return (
        f'{list(point)} puts its footprint (x {_n(min(xs))}..{_n(max(xs))}, y {_n(min(ys))}..{_n(max(ys))}) '
        f'past the edge of {_floor_text(floor)}: move it {_n(past)} m further in'
    )


def _check_floor(report: _Report, bodies, floor) -> None:
    """Every body, and a human at each of its waypoints, stands within the floor."""
    for label, body in bodies:
        reason = _off_floor(body.position, body.footprint(), floor)
        if reason:
            report.add(label, 'position', reason)
        for i, point in enumerate(body.waypoints):
            reason = _off_floor(point, box_footprint(point, body.size, body.yaw), floor)
            if reason:
                report.add(label, f'waypoints[{i}]', reason)


def _check_overlaps(report: _Report, bodies) -> None:
    """Bodies at their start poses may touch, not overlap; the later one in the file is named."""
    shapes = [(label, Polygon(body.footprint())) for label, body in bodies]
    for i, (label, shape) in enumerate(shapes):
        for other, other_shape in shapes[:i]:
            if shape.intersection(other_shape).area > AREA:
                report.add(
                    label, 'position', f'overlaps {other}: move one of them (bodies may touch, not overlap)'
                )


def _walk(human: Body) -> list[tuple[float, float]]:
    """The points a human walks through in order, back to ``position`` when it loops."""
    points: list[tuple[float, float]] = []
    for point in (human.position, *human.waypoints):
        if not points or point != points[-1]:
            points.append(point)
    if human.loop and len(points) > 2 and points[-1] != points[0]:
        points.append(points[0])
    return points


def _check_walks(report: _Report, humans, statics) -> None:
    """A human's walk keeps clear of the static objects unless it says ``through_obstacles: true``
    (the simulation walks it through them). Its start pose is :func:`_check_overlaps`' business."""
    boxes = [(label, Polygon(body.footprint())) for label, body in statics]
    advice = 'or add through_obstacles: true if it should walk through'
    for label, human in humans:
        if human.through_obstacles:
            continue
        inside = set()  # points where it stands in a box: its walks to and from them are not reported
        for i, point in [(None, human.position), *enumerate(human.waypoints)]:
            shape = Polygon(box_footprint(point, human.size, human.yaw))
            for other, box in boxes:
                if shape.intersection(box).area > AREA:
                    inside.add(point)
                    if i is not None:  # the start is _check_overlaps' business
                        message = f'{list(point)} puts it inside {other}: move it, {advice}'
                        report.add(label, f'waypoints[{i}]', message)
        points = _walk(human)
        for a, b in itertools.pairwise(points):
            if a in inside or b in inside:
                continue
            corners = box_footprint(a, human.size, human.yaw) + box_footprint(b, human.size, human.yaw)
            swept = MultiPoint(corners).convex_hull
            for other, box in boxes:
                if swept.intersection(box).area > AREA:
                    message = f'its walk from {list(a)} to {list(b)} crosses {other}: reroute it, {advice}'
                    report.add(label, 'waypoints', message)


_MISSED = {
    'self': 'the robot would not find itself',
    'station': 'the robot would not find its station',
    'obstacle': 'the robot would not see this obstacle',
    'human': 'the robot would not see this human',
    'robot': 'the other robots would not see this robot',
}
_TAKEN_FOR = {
    'self': 'the robot',
    'station': 'the station',
    'obstacle': 'an obstacle',
    'human': 'a human',
    'robot': 'a robot',
}
_OBSTACLES = {'obstacle', 'human'}
"""Roles the robot plans around alike: the model of one may also find the bodies of the other."""
_DECOY = ' (or decoy: true if that is on purpose)'


def _finds(model: ColourModel | TagQuery, body: Body) -> bool:
    """Whether ``model`` finds ``body``: its colour (a flat colour), or its tag."""
    if isinstance(model, ColourModel):
        return all(lo <= c <= hi for lo, c, hi in zip(model.lower, body.colour, model.upper, strict=True))
    tag = body.tag
    return tag is not None and tag.family == model.family and (not model.ids or tag.id in model.ids)


@dataclass(eq=False)
class _Model:
    """A colour model to check: where the file gives it, its role, what it finds, and the bodies
    it is meant to find."""

    where: str  # 'colour_models' or "robots 'r1'.colour_models"
    role: str
    algorithm: str
    params: object
    meant: list[tuple[str, Body]]
    taken_for: str

    @property
    def name(self) -> str:
        return f'{self.where}.{self.role} ({self.algorithm})'


def _model_checks(models: dict, crew: list, fleet: bool, statics, humans) -> list[_Model]:
    """Each colour model with the bodies it is meant to find: the shared ones (``models``) those of
    their role, each robot's own ``self`` and ``station`` its body and its station."""
    robots = [robot for _, robot, _, _ in crew if robot is not None]
    meant = {'obstacle': statics, 'human': humans, 'robot': robots}
    checks = []
    for label, robot, station, own in crew:
        who = f'robot {robot[1].name!r}' if robot else label
        for role, (text, params) in own.items():
            body = robot if role == 'self' else station
            if fleet:
                where, taken_for = (
                    f'{label}.colour_models',
                    who if role == 'self' else f'the station of {who}',
                )
            else:
                where, taken_for = 'colour_models', _TAKEN_FOR[role]
            checks.append(_Model(where, role, text, params, [body] if body else [], taken_for))
    for role, (text, params) in models.items():
        checks.append(
            _Model('colour_models', role, text, params, meant.get(role, []), _TAKEN_FOR.get(role, ''))
        )
    return checks


def _check_models(report: _Report, models: list[_Model], floor_colour, bodies) -> None:
    """No colour model matches the floor; each model finds the bodies it is meant for and no other
    body (of ``bodies``, all of them). Only ``colour`` and ``apriltag`` models of the known roles say
    what they find (``motion`` and plugins are not checked); decoys are left out. The robot plans
    around obstacles and humans alike, so either of their models may find the bodies of either."""
    for model in models:
        if isinstance(model.params, ColourModel) and floor_colour is not None:
            if _finds(model.params, _flat(floor_colour)):
                message = (
                    f'{list(floor_colour)} is matched by {model.name}; '
                    'the floor must be a colour that no colour model matches'
                )
                report.add('floor', 'colour', message)
    checked = [
        model
        for model in models
        if model.role in _MISSED and isinstance(model.params, ColourModel | TagQuery)
    ]
    for model in checked:
        role = model.role
        key = 'colour' if isinstance(model.params, ColourModel) else 'tag'
        own = [(label, body) for label, body in model.meant if not body.decoy]
        if key == 'tag' and role in _OBSTACLES:
            if own:
                report.add(model.where, role, f'finds tags, and objects carry none: {_MISSED[role]}')
            continue
        alike = [other for other in models if other is model or {role, other.role} <= _OBSTACLES]
        decoy = _DECOY if role in _OBSTACLES else ''
        for label, body in own:
            if any(_finds(other.params, body) for other in alike if other in checked):
                continue
            if key == 'colour':
                message = (
                    f'{list(body.colour)} is not matched by {model.name}: {_MISSED[role]}; '
                    f'change the colour or widen the model{decoy}'
                )
            elif body.tag is None:
                query = model.params
                wanted = query.family + (f' (id {", ".join(map(str, query.ids))})' if query.ids else '')
                message = f'missing: {model.name} looks for a {wanted} tag: {_MISSED[role]}'
            else:
                message = (
                    f'{body.tag.label} is not found by {model.name}: {_MISSED[role]}; '
                    'change the tag or the model'
                )
            report.add(label, key, message)
        allowed = {id(body) for other in alike for _, body in other.meant}
        for label, body in bodies:
            if id(body) in allowed or body.decoy or not _finds(model.params, body):
                continue
            found = list(body.colour) if key == 'colour' else body.tag.label
            remedy = (
                'change the colour or narrow the model' if key == 'colour' else 'list its ids in the model'
            )
            message = (
                f'{found} is matched by {model.name} too: it would be taken for {model.taken_for}; '
                f'{remedy}{_DECOY if body.kind in KINDS else ""}'
            )
            report.add(label, key, message)


def _flat(colour) -> Body:
    """A body of one flat colour, for :func:`_finds`."""
    return Body('', (0.0, 0.0), (1.0, 1.0, 1.0), colour)


def _check_views(report: _Report, cameras, floor) -> None:
    """Each camera sees some of the floor, from its position and from each waypoint of its mount."""
    for label, camera in cameras:
        forward = np.subtract(camera.target, camera.position)
        if not forward.any():
            report.add(label, 'target', 'equals position: the camera has no viewing direction')
            continue
        if np.linalg.norm(np.cross(forward / np.linalg.norm(forward), camera.up)) < 1e-9:  # as PinholeCamera
            report.add(
                label,
                'up',
                f'{list(camera.up)} does not point across the viewing direction: choose one that does',
            )
            continue
        model = PinholeCamera.from_config(camera)
        straight_down = camera.target == (camera.position[0], camera.position[1], 0.0)
        stops = [('position' if straight_down else 'target', '', model)]
        for i, (x, y) in enumerate(camera.waypoints):
            stops.append((f'waypoints[{i}]', f'from {[x, y]} ', model.moved_to(x, y)))
        for key, where, view in stops:
            seen = view.floor_footprint(floor)
            if len(seen) < 3 or Polygon(seen).area <= AREA:
                message = (
                    f'{where}the camera sees none of {_floor_text(floor)} and would register no field of '
                    'view: move it over the floor or aim its target at it'
                )
                report.add(label, key, message)


def _check_names(report: _Report, bodies, cameras) -> None:
    """Body names are unique (objects may not take ``robot`` or ``station``); vision system names
    too, and none is a robot's (both are node names)."""
    seen: dict[str, str] = {}
    for label, body in bodies:
        if body.kind in KINDS and body.name in ('robot', 'station'):
            report.add(label, 'name', f'{body.name!r} is reserved for the {body.name}; choose another name')
        elif body.name in seen:
            report.add(
                label, 'name', f'{body.name!r} is the name of {seen[body.name]} too; names must be unique'
            )
        seen.setdefault(body.name, label)
    robots = {body.name: label for label, body in bodies if body.kind == 'robot'}
    names: set[str] = set()
    for label, camera in cameras:
        if camera.name in names:
            report.add(
                label, 'name', f'{camera.name!r} names another vision system too; names must be unique'
            )
        elif camera.name in robots:
            message = f'{camera.name!r} is the name of {robots[camera.name]} too; node names must be unique'
            report.add(label, 'name', message)
        names.add(camera.name)


def _check_tags(report: _Report, bodies) -> None:
    """Each tag (family and id) is on one body only; the later one in the file is named."""
    seen: dict[str, str] = {}
    for label, body in bodies:
        if body.tag is None:
            continue
        if body.tag.label in seen:
            message = (
                f'{body.tag.label} is also {seen[body.tag.label]}.tag; '
                'each tag (family and id) may be on one body only'
            )
            report.add(label, 'tag', message)
        seen.setdefault(body.tag.label, label)


# -- the loader -----------------------------------------------------------------------------------
class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader, refusing a key given twice in one mapping (plain YAML keeps the last)."""

    def construct_mapping(self, node, deep=False):
        keys = set()
        for key_node, _ in node.value:
            if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == 'tag:yaml.org,2002:merge':
                continue  # a '<<: *anchor' merge may be overridden
            key = self.construct_object(key_node)
            if key in keys:
                raise yaml.constructor.ConstructorError(
                    'while reading a mapping', node.start_mark, f'{key!r} is given twice', key_node.start_mark
                )
            keys.add(key)
        return super().construct_mapping(node, deep)


def _yaml_problem(error: yaml.YAMLError) -> str:
    """A YAML syntax error on one line: where, what, and the construct it happened in."""
    mark = getattr(error, 'problem_mark', None)
    if mark is None:
        return 'not valid YAML: ' + ' '.join(str(error).split())
    text = f'not valid YAML: line {mark.line + 1}, column {mark.column + 1}: {error.problem}'
    context = getattr(error, 'context_mark', None)
    if error.context and context is not None:
        text += f' ({error.context} at line {context.line + 1}, column {context.column + 1})'
    return text


def load_world(path: str | Path) -> World:
    """Read a world file and check that it makes sense.

    :raises WorldError: listing every problem found, each naming the entry and the key.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as error:
        raise WorldError(path, [Problem('', '', f'cannot read the world file: {error.strerror}')]) from None
    except UnicodeDecodeError as error:
        message = f'cannot read the world file: not UTF-8 text (byte {error.start})'
        raise WorldError(path, [Problem('', '', message)]) from None
    try:
        data = yaml.load(text, Loader=_UniqueKeyLoader)  # a SafeLoader
    except yaml.YAMLError as error:
        raise WorldError(path, [Problem('', '', _yaml_problem(error))]) from None
    if not isinstance(data, dict):
        message = f'expected a mapping with the keys {", ".join(TOP_KEYS)}, got {data!r}'
        raise WorldError(path, [Problem('', '', message)])

    report = _Report()
    top = _Entry(report, '', data, TOP_KEYS, 'a world file')
    floor_size, floor_colour = None, (255, 255, 255)
    floor = top.read('floor', _mapping, default=None)
    if floor is not None:
        entry = _Entry(report, 'floor', floor, FLOOR_KEYS, 'the floor')
        floor_size = entry.read('size', _vector, 2, '[x, y]', True)
        floor_colour = entry.read('colour', _colour, default=floor_colour)
    if 'floor' not in data:
        top.problem('floor', 'missing')
    fleet = 'robots' in data
    given = [key for key in ('robot', 'station') if key in data]
    for key in given if fleet else ():
        top.problem(key, f'given with robots: too; {_FORMS}')
    if not fleet and not given:
        top.problem('robot', f'missing: {_FORMS}')
    for key in ('robot', 'station') if given and not fleet else ():
        if key not in data:
            top.problem(key, 'missing')
    for required in ('vision_systems', 'colour_models'):
        if required not in data:
            top.problem(required, 'missing')
    robot = _body(report, data['robot'], 'robot', 'robot', 'robot') if 'robot' in data else None
    station = _body(report, data['station'], 'station', 'station', 'station') if 'station' in data else None
    items = top.read('robots', _list, True, default=[])
    crew = [_fleet_robot(report, item, i) for i, item in enumerate(items or [])]
    items = top.read('objects', _list, False, default=[])
    objects = [
        _body(report, item, 'object', f'objects[{i}]', f'object{i}') for i, item in enumerate(items or [])
    ]
    items = top.read('vision_systems', _list, True, default=[])
    cameras = [_camera(report, item, i) for i, item in enumerate(items or [])]
    form = fleet if fleet or given else None
    models = _top_models(report, data['colour_models'], form, len(crew)) if 'colour_models' in data else {}
    real_time_factor = top.read('real_time_factor', _factor, default=1.0)

    # Pass 2, over the entries that read well.
    if not fleet:  # the single form's self and station models are the robot's own
        crew = [('robot', robot, station, {role: models.pop(role) for role in OWN_ROLES if role in models})]
    bodies = [body for _, *pair, _ in crew for body in pair if body is not None]  # robot, station
    bodies += [body for body in objects if body is not None]
    cameras = [camera for camera in cameras if camera is not None]
    statics = [(label, body) for label, body in bodies if body.kind == 'static']
    humans = [(label, body) for label, body in bodies if body.kind == 'human']
    _check_names(report, bodies, cameras)
    _check_tags(report, bodies)
    if floor_size is not None:
        _check_floor(report, bodies, floor_size)
    _check_overlaps(report, bodies)
    _check_walks(report, humans, statics)
    _check_models(report, _model_checks(models, crew, fleet, statics, humans), floor_colour, bodies)
    if floor_size is not None:
        _check_views(report, cameras, floor_size)

    if report.problems:
        raise WorldError(path, report.sorted())
    shared = dict(data['colour_models'])
    return World(
        path=path,
        floor_size=floor_size,
        robots=tuple(
            FleetRobot(robot[1].name, robot[1], station[1], {**shared, **{r: t for r, (t, _) in own.items()}})
            for _, robot, station, own in crew
        ),
        objects=tuple(body for _, body in objects),
        vision_systems=tuple(camera for _, camera in cameras),
        floor_colour=floor_colour,
        real_time_factor=real_time_factor,
    )
