"""World files (``worlds/*.yaml``): load and validate a scenario description.

Every error names the file, the key and what was expected, for example
``worlds/x.yaml: objects[2].size: expected 3 positive numbers [x, y, z], got [0.4, 0.6]``.
The keys are documented in ``worlds/README.md``; the stable core is in docs/design.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from drvs.algorithms import AlgorithmError, parse_algorithm
from drvs.tag_images import FAMILIES, FAMILY_NAMES

KINDS = ('static', 'human')
ROLES = ('self', 'station', 'obstacle', 'human')


class WorldError(ValueError):
    """A world file that cannot be used; the message names the file, the key and the problem."""


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
class World:
    path: Path
    floor_size: tuple[float, float]
    robot: Body
    station: Body
    objects: tuple[Body, ...]
    vision_systems: tuple[Camera, ...]
    colour_models: dict[str, str] = field(default_factory=dict)
    floor_colour: tuple[int, int, int] = (255, 255, 255)

    def camera(self, name: str) -> Camera:
        for camera in self.vision_systems:
            if camera.name == name:
                return camera
        known = ', '.join(c.name for c in self.vision_systems) or 'none'
        raise WorldError(f'{self.path}: vision_systems: no entry named {name!r} (known: {known})')


def box_footprint(centre, size, yaw: float) -> list[tuple[float, float]]:
    """Corners of a yawed rectangle centred at ``centre`` with ``size`` [x, y], counter-clockwise."""
    cx, cy = centre
    hx, hy = size[0] / 2.0, size[1] / 2.0
    c, s = math.cos(yaw), math.sin(yaw)
    return [
        (cx + c * dx - s * dy, cy + s * dx + c * dy)
        for dx, dy in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))
    ]


class _Reader:
    """Typed access to a YAML mapping, with errors that say file, key and expectation."""

    def __init__(self, path: Path):
        self.path = path

    def fail(self, key: str, expected: str, got) -> WorldError:
        return WorldError(f'{self.path}: {key}: expected {expected}, got {got!r}')

    def mapping(self, data, key: str) -> dict:
        if not isinstance(data, dict):
            raise self.fail(key, 'a mapping', data)
        return data

    def number(self, value, key: str, positive=False, minimum=None) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise self.fail(key, 'a finite number', value)
        if positive and value <= 0:
            raise self.fail(key, 'a positive number', value)
        if minimum is not None and value < minimum:
            raise self.fail(key, f'a number >= {minimum}', value)
        return float(value)

    def vector(self, value, key: str, n: int, what: str, positive=False) -> tuple[float, ...]:
        expected = f'{n} {"positive " if positive else ""}numbers {what}'
        if not isinstance(value, list | tuple) or len(value) != n:
            raise self.fail(key, expected, value)
        try:
            return tuple(self.number(v, key, positive=positive) for v in value)
        except WorldError:
            raise self.fail(key, expected, value) from None

    def colour(self, value, key: str) -> tuple[int, int, int]:
        if (
            not isinstance(value, list | tuple)
            or len(value) != 3
            or not all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 255 for v in value)
        ):
            raise self.fail(key, '3 integers 0-255 [r, g, b]', value)
        return tuple(value)

    def waypoints(self, value, key: str) -> tuple[tuple[float, float], ...]:
        if not isinstance(value, list) or len(value) < 2:
            raise self.fail(key, 'a list of at least 2 points [[x, y], ...]', value)
        return tuple(self.vector(p, f'{key}[{i}]', 2, '[x, y]') for i, p in enumerate(value))

    def unknown(self, data: dict, key: str, allowed) -> None:
        extra = sorted(set(data) - set(allowed))
        if extra:
            raise WorldError(
                f'{self.path}: {key}: unknown key(s) {", ".join(map(str, extra))}; '
                f'allowed: {", ".join(allowed)}'
            )


BODY_KEYS = (
    'name',
    'kind',
    'position',
    'size',
    'yaw',
    'colour',
    'waypoints',
    'speed',
    'loop',
    'wait_for_robot',
    'tag',
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


def _tag(r: _Reader, data, key: str, body_size: tuple[float, float, float]) -> Tag:
    data = r.mapping(data, key)
    r.unknown(data, key, TAG_KEYS)
    for required in TAG_KEYS:
        if required not in data:
            raise WorldError(f'{r.path}: {key}.{required}: missing')
    family = data['family']
    if family not in FAMILY_NAMES:
        raise r.fail(f'{key}.family', f'one of {", ".join(FAMILY_NAMES)}', family)
    count = FAMILIES[family].ids
    tag_id = data['id']
    if isinstance(tag_id, bool) or not isinstance(tag_id, int) or not 0 <= tag_id < count:
        raise r.fail(f'{key}.id', f'an integer 0-{count - 1} (an id of {family})', tag_id)
    size = r.number(data['size'], f'{key}.size', positive=True)
    smaller = min(body_size[:2])
    if size > smaller:
        raise r.fail(f'{key}.size', f"at most the body's smaller side, {smaller:g} m", size)
    return Tag(family, tag_id, size)


def _body(
    r: _Reader, data, key: str, default_name: str, moving_allowed: bool, tag_allowed: bool = False
) -> Body:
    data = r.mapping(data, key)
    r.unknown(data, key, BODY_KEYS)
    for required in ('position', 'size', 'colour'):
        if required not in data:
            raise WorldError(f'{r.path}: {key}.{required}: missing')
    kind = data.get('kind', 'static')
    if kind not in KINDS:
        raise r.fail(f'{key}.kind', ' or '.join(KINDS), kind)
    name = data.get('name', default_name)
    if not isinstance(name, str) or not name:
        raise r.fail(f'{key}.name', 'a non-empty string', name)
    waypoints, speed = (), 0.0
    if 'speed' in data:
        speed = r.number(data['speed'], f'{key}.speed', minimum=0)
    if 'waypoints' in data:
        if not moving_allowed:
            raise WorldError(f'{r.path}: {key}.waypoints: only objects of kind human move')
        waypoints = r.waypoints(data['waypoints'], f'{key}.waypoints')
    if kind == 'human' and moving_allowed and (not waypoints or speed <= 0):
        raise WorldError(f'{r.path}: {key}: a human needs waypoints (2 or more) and a positive speed')
    if kind == 'static' and waypoints:
        raise WorldError(f'{r.path}: {key}.waypoints: a static object cannot move; use kind: human')
    flags = {}
    for flag, default in (('loop', True), ('wait_for_robot', False)):
        value = flags[flag] = data.get(flag, default)
        if not isinstance(value, bool):
            raise r.fail(f'{key}.{flag}', 'true or false', value)
        if value != default and kind != 'human':
            raise WorldError(f'{r.path}: {key}.{flag}: only humans walk; {flag} applies to kind human')
    size = r.vector(data['size'], f'{key}.size', 3, '[x, y, z]', positive=True)
    tag = None
    if 'tag' in data:
        if not tag_allowed:
            raise WorldError(f'{r.path}: {key}.tag: only the robot and the station carry a tag')
        tag = _tag(r, data['tag'], f'{key}.tag', size)
    return Body(
        name=name,
        position=r.vector(data['position'], f'{key}.position', 2, '[x, y]'),
        size=size,
        colour=r.colour(data['colour'], f'{key}.colour'),
        yaw=r.number(data.get('yaw', 0.0), f'{key}.yaw'),
        kind=kind,
        waypoints=waypoints,
        speed=speed,
        **flags,
        tag=tag,
    )


def _camera(r: _Reader, data, key: str) -> Camera:
    data = r.mapping(data, key)
    r.unknown(data, key, CAMERA_KEYS)
    for required in ('name', 'position', 'fov_deg'):
        if required not in data:
            raise WorldError(f'{r.path}: {key}.{required}: missing')
    name = data['name']
    if not isinstance(name, str) or not name.replace('_', 'a').isalnum() or not name[0].isalpha():
        raise r.fail(f'{key}.name', 'a ROS node name (letters, digits, _; starting with a letter)', name)
    position = r.vector(data['position'], f'{key}.position', 3, '[x, y, z]')
    if position[2] <= 0:
        raise r.fail(f'{key}.position', 'a camera above the floor (z > 0)', list(position))
    fov = r.number(data['fov_deg'], f'{key}.fov_deg')
    if not 1.0 <= fov <= 170.0:
        raise r.fail(f'{key}.fov_deg', 'a vertical field of view between 1 and 170 degrees', fov)
    resolution = data.get('resolution', [800, 600])
    if (
        not isinstance(resolution, list)
        or len(resolution) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) and 16 <= v <= 4096 for v in resolution)
    ):
        raise r.fail(f'{key}.resolution', '2 integers 16-4096 [width, height]', resolution)
    target = r.vector(data.get('target', [position[0], position[1], 0.0]), f'{key}.target', 3, '[x, y, z]')
    up = r.vector(data.get('up', [0.0, 1.0, 0.0]), f'{key}.up', 3, '[x, y, z]')
    waypoints, speed = (), 0.0
    if 'waypoints' in data or 'speed' in data:
        waypoints = r.waypoints(data.get('waypoints'), f'{key}.waypoints')
        speed = r.number(data.get('speed'), f'{key}.speed', positive=True)
    distortion = ()
    if 'distortion' in data:
        distortion = r.vector(data['distortion'], f'{key}.distortion', 5, '[k1, k2, p1, p2, k3]')
        if any(abs(c) > 10.0 for c in distortion):
            raise r.fail(
                f'{key}.distortion',
                'plumb_bob coefficients [k1, k2, p1, p2, k3], each within +-10',
                list(distortion),
            )
    return Camera(
        name=name,
        position=position,
        fov_deg=fov,
        resolution=tuple(resolution),
        target=target,
        up=up,
        waypoints=waypoints,
        speed=speed,
        distortion=distortion,
    )


def _matches(model, colour) -> bool:
    """Whether ``model`` finds an object in an image of one flat ``colour``."""
    import numpy as np

    return bool(model.mask(np.full((1, 1, 3), colour, np.uint8)).any())


def load_world(path: str | Path) -> World:
    """Read and validate a world file.

    :raises WorldError: naming the file, the key and what was expected.
    """
    path = Path(path)
    r = _Reader(path)
    try:
        text = path.read_text()
    except OSError as error:
        raise WorldError(f'{path}: cannot read the world file: {error.strerror}') from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise WorldError(f'{path}: not valid YAML: {error}') from None
    data = r.mapping(data, '(top level)')
    r.unknown(
        data, '(top level)', ('floor', 'robot', 'station', 'objects', 'vision_systems', 'colour_models')
    )
    for required in ('floor', 'robot', 'station', 'vision_systems', 'colour_models'):
        if required not in data:
            raise WorldError(f'{path}: {required}: missing')

    floor = r.mapping(data['floor'], 'floor')
    r.unknown(floor, 'floor', ('size', 'colour'))
    if 'size' not in floor:
        raise WorldError(f'{path}: floor.size: missing')
    floor_size = r.vector(floor['size'], 'floor.size', 2, '[x, y]', positive=True)
    floor_colour = r.colour(floor.get('colour', [255, 255, 255]), 'floor.colour')

    robot_data = r.mapping(data['robot'], 'robot')
    robot = _body(
        r, {k: v for k, v in robot_data.items() if k != 'speed'}, 'robot', 'robot', False, tag_allowed=True
    )
    speed = r.number(robot_data.get('speed', 0.4), 'robot.speed', positive=True)
    robot = Body(**{**robot.__dict__, 'speed': speed})
    station = _body(r, data['station'], 'station', 'station', False, tag_allowed=True)
    if robot.tag is not None and station.tag is not None and robot.tag.label == station.tag.label:
        raise WorldError(
            f'{path}: station.tag: {station.tag.label} is also robot.tag; '
            'each tag (family and id) may be on one body only'
        )

    objects_data = data.get('objects') or []
    if not isinstance(objects_data, list):
        raise r.fail('objects', 'a list', objects_data)
    objects = tuple(
        _body(r, item, f'objects[{i}]', f'object{i}', True) for i, item in enumerate(objects_data)
    )
    names = [o.name for o in objects] + ['robot', 'station']
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise WorldError(
            f'{path}: objects: names must be unique (and not robot or station), repeated: '
            f'{", ".join(duplicates)}'
        )

    cameras_data = data['vision_systems']
    if not isinstance(cameras_data, list) or not cameras_data:
        raise r.fail('vision_systems', 'a non-empty list', cameras_data)
    cameras = tuple(_camera(r, item, f'vision_systems[{i}]') for i, item in enumerate(cameras_data))
    camera_names = [c.name for c in cameras]
    if len(set(camera_names)) != len(camera_names):
        raise WorldError(f'{path}: vision_systems: names must be unique, got {camera_names}')

    models = r.mapping(data['colour_models'], 'colour_models')
    for role in ROLES:
        if role not in models:
            raise WorldError(f'{path}: colour_models.{role}: missing (roles: {", ".join(ROLES)})')
    for role, text in models.items():
        try:
            model = parse_algorithm(text)
        except AlgorithmError as error:
            raise WorldError(f'{path}: colour_models.{role}: {error}') from None
        if model.name == 'colour' and _matches(model.params, floor_colour):
            raise WorldError(
                f'{path}: floor.colour: {list(floor_colour)} is matched by colour_models.{role} '
                f'({text}); the floor must be a colour that no colour model matches'
            )

    return World(
        path=path,
        floor_size=floor_size,
        robot=robot,
        station=station,
        objects=objects,
        vision_systems=cameras,
        colour_models=dict(models),
        floor_colour=floor_colour,
    )
