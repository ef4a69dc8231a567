"""Whether a world is possible: bodies on the floor and apart, walks clear of the boxes, colour
models that find what they should and nothing else, cameras that see the floor (pass 2 of
:func:`drvs.sim.world_file.load_world`)."""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from shapely.geometry import MultiPoint, Polygon

from drvs.algorithms import ColourModel
from drvs.algorithms.apriltag import TagQuery
from drvs.sim.world import (
    KINDS,
    Body,
    Camera,
    Problem,
    box_footprint,
)
from drvs.vision.camera import PinholeCamera

Labelled = tuple[str, Body]
"""A body with the label of its entry in the file (``objects[2]``)."""
CrewEntry = tuple[str, Labelled | None, Labelled | None, dict[str, tuple[str, object]]]
"""A robot's entry: its label, its body and its station's (None where they did not read), and its
own colour models by role (text, parsed)."""

AREA = 1e-9
"""Square metres below which two footprints touch rather than overlap."""
EDGE = 1e-9
"""Metres a footprint may reach past the floor's edge (rounding)."""


class Report:
    """The problems found so far; :meth:`sorted` lists them in the order the file names its entries."""

    def __init__(self) -> None:
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


# -- pass 2: whether the world is possible ----------------------------------------------------------
def _n(value: float) -> str:
    return f'{round(value, 3):g}'


def _floor_text(floor: tuple[float, float]) -> str:
    return f'the floor (x 0..{_n(floor[0])}, y 0..{_n(floor[1])})'


def _off_floor(
    point: tuple[float, float], footprint: Sequence[tuple[float, float]], floor: tuple[float, float]
) -> str | None:
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


def check_floor(report: Report, bodies: Iterable[Labelled], floor: tuple[float, float]) -> None:
    """Every body, and a human at each of its waypoints, stands within the floor."""
    for label, body in bodies:
        reason = _off_floor(body.position, body.footprint(), floor)
        if reason:
            report.add(label, 'position', reason)
        for i, point in enumerate(body.waypoints):
            reason = _off_floor(point, box_footprint(point, body.size, body.yaw), floor)
            if reason:
                report.add(label, f'waypoints[{i}]', reason)


def check_overlaps(report: Report, bodies: Iterable[Labelled]) -> None:
    """Bodies at their start poses may touch, not overlap; the later one in the file is named. A
    body hanging above another (a shelf over a box, over the robot's start) does not overlap it."""
    shapes = [(label, body, Polygon(body.footprint())) for label, body in bodies]
    for i, (label, body, shape) in enumerate(shapes):
        for other, other_body, other_shape in shapes[:i]:
            if body.bottom >= other_body.top or other_body.bottom >= body.top:
                continue
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


def check_walks(report: Report, humans: Iterable[Labelled], statics: Iterable[Labelled]) -> None:
    """A human's walk keeps clear of the static objects unless it says ``through_obstacles: true``
    (the simulation walks it through them), or passes under them. Its start pose is
    :func:`check_overlaps`' business."""
    advice = 'or add through_obstacles: true if it should walk through'
    for label, human in humans:
        if human.through_obstacles:
            continue
        boxes = [(other, Polygon(body.footprint())) for other, body in statics if body.bottom < human.top]
        inside = set()  # points where it stands in a box: its walks to and from them are not reported
        for i, point in [(None, human.position), *enumerate(human.waypoints)]:
            shape = Polygon(box_footprint(point, human.size, human.yaw))
            for other, box in boxes:
                if shape.intersection(box).area > AREA:
                    inside.add(point)
                    if i is not None:  # the start is check_overlaps' business
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


def _finds(model: object, body: Body) -> bool:
    """Whether ``model`` (a :class:`ColourModel` or :class:`TagQuery`) finds ``body``: its colour
    (a flat colour), or its tag."""
    if isinstance(model, ColourModel):
        return all(lo <= c <= hi for lo, c, hi in zip(model.lower, body.colour, model.upper, strict=True))
    tag = body.tag
    return (
        isinstance(model, TagQuery)
        and tag is not None
        and tag.family == model.family
        and (not model.ids or tag.id in model.ids)
    )


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


def model_checks(
    models: dict[str, tuple[str, object]],
    crew: Sequence[CrewEntry],
    fleet: bool,
    statics: list[Labelled],
    humans: list[Labelled],
) -> list[_Model]:
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


def check_models(
    report: Report,
    models: list[_Model],
    floor_colour: tuple[int, int, int] | None,
    bodies: Sequence[Labelled],
) -> None:
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
                assert isinstance(query, TagQuery)  # key 'tag'
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
            found = list(body.colour) if key == 'colour' or body.tag is None else body.tag.label
            remedy = (
                'change the colour or narrow the model' if key == 'colour' else 'list its ids in the model'
            )
            message = (
                f'{found} is matched by {model.name} too: it would be taken for {model.taken_for}; '
                f'{remedy}{_DECOY if body.kind in KINDS else ""}'
            )
            report.add(label, key, message)


def _flat(colour: tuple[int, int, int]) -> Body:
    """A body of one flat colour, for :func:`_finds`."""
    return Body('', (0.0, 0.0), (1.0, 1.0, 1.0), colour)


def check_views(report: Report, cameras: Iterable[tuple[str, Camera]], floor: tuple[float, float]) -> None:
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


def check_names(report: Report, bodies: Sequence[Labelled], cameras: Iterable[tuple[str, Camera]]) -> None:
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


def check_tags(report: Report, bodies: Iterable[Labelled]) -> None:
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
