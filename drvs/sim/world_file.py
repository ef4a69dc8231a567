"""A world file's form: read ``worlds/*.yaml``, each key checked, every problem reported at once.

:func:`load_world` reads a file in two passes and raises one :class:`~drvs.sim.world.WorldError`
naming every problem of both: first the form of each entry (this module: types, ranges, keys
that do not apply to it), then whether the world is possible (:mod:`drvs.sim.world_sense`).
Each problem names the entry by its ``name`` and the key, for example::

    worlds/x.yaml: 2 problems:
      station.position: [8.0, 0.8] is outside the floor (x 0..7, y 0..5.5)
      object 'box1'.size: expected 3 positive numbers [x, y, z], got [0.4, 0.6]

The keys are documented in ``worlds/README.md``.
"""

from __future__ import annotations

import difflib
import math
import re
from collections.abc import Callable
from dataclasses import fields
from pathlib import Path

import yaml

from drvs.algorithms import AlgorithmError, parse_algorithm
from drvs.algorithms.tag_images import FAMILIES, FAMILY_NAMES
from drvs.common.roles import SHARED_ROLES, unknown_role
from drvs.sim.depth_noise import DepthNoise
from drvs.sim.world import (
    KINDS,
    OWN_ROLES,
    ROLES,
    Body,
    Camera,
    FleetRobot,
    Problem,
    Tag,
    World,
    WorldError,
)
from drvs.sim.world_sense import (
    Report,
    check_floor,
    check_models,
    check_names,
    check_overlaps,
    check_tags,
    check_views,
    check_walks,
    model_checks,
)

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
OBJECT_KEYS = ('name', 'kind', 'position', 'size', 'yaw', 'colour', 'decoy', 'shiny')
STATIC_KEYS = (*OBJECT_KEYS, 'bottom')
HUMAN_KEYS = (
    *OBJECT_KEYS,
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
    'depth_noise',
    'site',
)
DEPTH_NOISE_KEYS = tuple(field.name for field in fields(DepthNoise))
_ALL_KEYS = frozenset(
    (
        *TOP_KEYS,
        *FLOOR_KEYS,
        *FLEET_ROBOT_KEYS,
        *HUMAN_KEYS,
        *STATIC_KEYS,
        *TAG_KEYS,
        *CAMERA_KEYS,
        *DEPTH_NOISE_KEYS,
    )
)
_HUMANS_ONLY = 'applies to humans only: add kind: human to make it walk'
_TAGS_ONLY = 'only the robot and the station carry a tag'
_STATICS_ONLY = 'does not apply: only a static object may hang above the floor'
_FORMS = 'a world has robot: and station: (one robot) or robots: (a list of robots, each with its station)'


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
    r, g, b = _integers(value, 3, 0, 255, '[r, g, b]')
    return r, g, b


def _points(value) -> tuple[tuple[float, float], ...]:
    if not isinstance(value, list) or len(value) < 2:
        raise _expected('a list of at least 2 points [[x, y], ...]', value)
    points = []
    for i, point in enumerate(value):
        try:
            x, y = _vector(point, 2, '[x, y]')
        except _Invalid as error:
            raise _Invalid(error.message, f'[{i}]') from None
        points.append((x, y))
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


def _site_name(value) -> str:
    if not isinstance(value, str) or not re.fullmatch(r'[A-Za-z0-9_]{1,16}', value):
        raise _expected('a site name (1 to 16 letters, digits or _)', value)
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


_REQUIRED = object()


class _Entry:
    """The keys of one mapping of a world file, read one by one: a bad key is reported and reads
    as None, so the other keys (and entries) are still checked. ``broken`` says whether a value
    is missing or bad (a key that does not apply alone does not break the entry)."""

    def __init__(self, report: Report, label: str, data: dict, keys, what: str, hints=None, prefix=''):
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
        {**dict.fromkeys(HUMAN_KEYS[len(OBJECT_KEYS) :], _HUMANS_ONLY), 'tag': _TAGS_ONLY},
    ),
    'human': (HUMAN_KEYS, 'a human', {'tag': _TAGS_ONLY, 'bottom': _STATICS_ONLY}),
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


def _body(report: Report, data, role: str, where: str, name: str | None, fleet: bool = False):
    """A body (``role`` 'robot', 'station' or 'object') with its label for messages, or None when
    it is unusable (its problems are reported). ``where`` is the entry's place (``robot``,
    ``objects[2]``, ``robots[1]``, ``robots 'r1'.station``), ``name`` its default name (None: a
    name is required), ``fleet`` says it is an entry of ``robots:`` or the station of one."""
    if not isinstance(data, dict):
        report.add(report.entry(where), '', f'expected a mapping, got {data!r}')
        return None
    kind = data.get('kind', 'static') if role == 'object' else role
    label = report.entry(_label(data, where, role, fleet))
    keys: tuple[str, ...]
    if role == 'object' and kind not in KINDS:  # reported below; any object key may apply
        keys, what, hints = (*HUMAN_KEYS, 'bottom'), 'an object', {'tag': _TAGS_ONLY}
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
        values['shiny'] = entry.read('shiny', _flag, default=False)
        if kind != 'human':
            values['bottom'] = entry.read('bottom', _bounded, 0.0, 100.0, 'metres', default=0.0)
    else:
        values['tag'] = _tag(entry, size) if 'tag' in data else None
    if entry.broken:
        return None
    return label, Body(name=name, position=position, size=size, kind=kind, **values)


def _camera(report: Report, data, index: int) -> tuple[str, Camera] | None:
    """``vision_systems[index]`` with its label; None when it is unusable."""
    where = f'vision_systems[{index}]'
    if not isinstance(data, dict):
        report.add(report.entry(where), '', f'expected a mapping, got {data!r}')
        return None
    name = data.get('name')
    label = report.entry(f'vision_system {name!r}' if _is_node_name(name) else where)
    entry = _Entry(report, label, data, CAMERA_KEYS, 'a vision system')
    node_name = entry.read('name', _node_name)
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
    noise = _depth_noise(entry) if 'depth_noise' in data else None
    site = entry.read('site', _site_name, default='')
    if entry.broken:
        return None
    width, height = resolution
    return label, Camera(
        node_name, position, fov, (width, height), target, up, waypoints, speed, distortion, noise, site
    )


def _check_sites(report: Report, cameras: list[tuple[str, Camera]]) -> None:
    """Every vision system names its site, or none does (one site): a camera left out would belong
    to no site's server."""
    sites = sorted({camera.site for _, camera in cameras if camera.site})
    if not sites:
        return
    for label, camera in cameras:
        if not camera.site:
            report.add(
                label,
                'site',
                f'missing: the other vision systems name their site ({", ".join(sites)}); '
                "name this one's too",
            )


def _probability(value) -> float:
    if not _is_number(value) or not 0 <= value <= 1:
        raise _expected('a probability 0-1', value)
    return float(value)


def _depth_noise(entry: _Entry) -> DepthNoise | None:
    """A camera's ``depth_noise``: ``true`` (a Kinect-class sensor's defaults), ``false`` (perfect
    depth) or a mapping of :class:`DepthNoise`'s fields; problems reported as ``depth_noise.KEY``."""
    data = entry.data['depth_noise']
    if isinstance(data, bool):
        return DepthNoise() if data else None
    if not isinstance(data, dict):
        entry.problem(
            'depth_noise', f'expected true, false or a mapping of {", ".join(DEPTH_NOISE_KEYS)}, got {data!r}'
        )
        return None
    noise = _Entry(entry.report, entry.label, data, DEPTH_NOISE_KEYS, 'depth_noise', prefix='depth_noise.')
    defaults = DepthNoise()
    values = {
        'error': noise.read('error', _bounded, 0.0, 0.1, 'metres at 1 m', default=defaults.error),
        'edge_jump': noise.read('edge_jump', _bounded, 0.0, 10.0, 'metres', default=defaults.edge_jump),
        'edge_width': noise.read('edge_width', _count, 0, 20, default=defaults.edge_width),
        'edge_dropout': noise.read('edge_dropout', _probability, default=defaults.edge_dropout),
        'dark_level': noise.read('dark_level', _count, 0, 255, default=defaults.dark_level),
        'dark_dropout': noise.read('dark_dropout', _probability, default=defaults.dark_dropout),
        'shiny_dropout': noise.read('shiny_dropout', _probability, default=defaults.shiny_dropout),
        'seed': noise.read('seed', _count, 0, 2**32 - 1, default=None),
    }
    entry.broken = entry.broken or noise.broken
    return None if noise.broken else DepthNoise(**values)


def _bounded(value, low: float, high: float, unit: str) -> float:
    if not _is_number(value) or not low <= value <= high:
        raise _expected(f'a number {low:g}-{high:g} ({unit})', value)
    return float(value)


def _count(value, low: int, high: int) -> int:
    if not _is_integer(value, low, high):
        raise _expected(f'an integer {low}-{high}', value)
    return value


def _models(
    report: Report, data, where: str, required: dict[str, str], refuse: Callable[[str], str | None]
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


def _top_models(report: Report, data, fleet: bool | None, robots: int) -> dict[str, tuple[str, object]]:
    """The top-level ``colour_models``: every role in the single form, the shared roles of a fleet
    (``fleet`` None: the file has neither form, which is reported, so no role is missing)."""
    if not fleet:
        missing = f'missing (roles: {", ".join(ROLES)})'
        required = dict.fromkeys(ROLES if fleet is not None else (), missing)
        return _models(report, data, 'colour_models', required, unknown_role)
    missing = f'missing (roles: {", ".join(SHARED_ROLES)})'
    required = dict.fromkeys(SHARED_ROLES[:2], missing)
    if robots > 1:
        required['robot'] = f'missing: with several robots, a model that finds every robot ({missing[9:-1]})'
    own = "with robots:, each robot has its own: put it in the robot's colour_models"
    return _models(
        report, data, 'colour_models', required, lambda role: own if role in OWN_ROLES else unknown_role(role)
    )


def _fleet_robot(report: Report, data, index: int):
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
            lambda role: None if role in OWN_ROLES else unknown_role(role) or shared,
        )
    return label, robot, station, models


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

    report = Report()
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
    check_names(report, bodies, cameras)
    _check_sites(report, cameras)
    check_tags(report, bodies)
    if floor_size is not None:
        check_floor(report, bodies, floor_size)
    check_overlaps(report, bodies)
    check_walks(report, humans, statics)
    check_models(report, model_checks(models, crew, fleet, statics, humans), floor_colour, bodies)
    if floor_size is not None:
        check_views(report, cameras, floor_size)

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
