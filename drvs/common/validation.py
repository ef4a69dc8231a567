"""Checks on what callers send the DRVS server, each failing with a message naming field and problem.

Pure functions, no ROS: the server (``drvs.ros.server``) calls them before it
registers or forwards anything. Checks that need the ROS master (does a service
exist, what type is it, who provides it) live in the server.

>>> region_of_interest((0.0, 0.0, 2.0, 1.0))
(0.0, 0.0, 2.0, 1.0)
>>> region_of_interest((2.0, 0.0, 1.0, 1.0))
Traceback (most recent call last):
...
drvs.common.validation.ValidationError: region_of_interest: min_x 2 is greater than max_x 1
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence

from shapely.geometry import LineString, MultiPoint, Point, Polygon
from shapely.geometry.base import BaseGeometry
from shapely.validation import explain_validity

from drvs.algorithms import AlgorithmSet, Parsed, parse_algorithm

__all__ = [
    'ValidationError',
    'field_of_view_polygon',
    'region_of_interest',
    'region_geometry',
    'ros_name',
    'global_ros_name',
    'request_fields',
    'rosrpc_uri',
]

_NAME = re.compile(r'^[~/]?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*$')
MAX_NAME_LENGTH = 256
MAX_COORDINATE = 1e6
"""Largest magnitude of a coordinate (metres) in a region of interest or a field of view.

Far beyond any floor. Without a bound, coordinates near 1e308 overflow GEOS's
arithmetic and matching fails on valid shapes (TopologyException: side location conflict).
"""
_WITHIN = f'coordinates must be between {-MAX_COORDINATE:g} and {MAX_COORDINATE:g}'


class ValidationError(ValueError):
    """Input the server refuses; the message names the field and the problem."""


def field_of_view_polygon(points: Sequence[Sequence[float]]) -> Polygon:
    """The field of view as a valid shapely polygon of positive area.

    ``points`` are the vertices (x, y) in order; the ring may or may not repeat
    its first vertex at the end.

    :raises ValidationError: fewer than 3 vertices, a coordinate that is not
        finite or beyond :data:`MAX_COORDINATE`, all vertices on one line (zero
        area), or a self-intersection.
    """
    points = [(float(p[0]), float(p[1])) for p in points]
    if len(points) < 3:
        raise ValidationError(f'field_of_view: {len(points)} vertices; a polygon needs at least 3')
    for index, (x, y) in enumerate(points):
        if not (-MAX_COORDINATE <= x <= MAX_COORDINATE and -MAX_COORDINATE <= y <= MAX_COORDINATE):
            if not (math.isfinite(x) and math.isfinite(y)):
                raise ValidationError(
                    f'field_of_view: vertex {index} is ({x}, {y}); coordinates must be finite'
                )
            raise ValidationError(f'field_of_view: vertex {index} is ({x}, {y}); {_WITHIN}')
    polygon = Polygon(points)
    if polygon.is_valid and polygon.area > 0.0:
        return polygon  # the common case, without the convex hull (most of the time of this check)
    if MultiPoint(points).convex_hull.area == 0.0:
        raise ValidationError('field_of_view: zero area (all vertices lie on one line)')
    if not polygon.is_valid:
        reason = explain_validity(polygon)
        where = reason.partition('[')[2].rstrip(']').split()
        at = f' at ({float(where[0]):g}, {float(where[1]):g})' if len(where) == 2 else ''
        if reason.startswith(('Self-intersection', 'Ring Self-intersection')):
            raise ValidationError(f'field_of_view: the outline crosses itself{at}')
        raise ValidationError(f'field_of_view: not a valid polygon: {reason}')
    if polygon.area == 0.0:
        raise ValidationError('field_of_view: zero area')
    return polygon


_BOX_FIELDS = ('min_x', 'min_y', 'max_x', 'max_y')


def region_of_interest(box: Sequence[float]) -> tuple[float, float, float, float]:
    """``(min_x, min_y, max_x, max_y)`` checked: finite, within :data:`MAX_COORDINATE`, min <= max.

    A region of zero width or height (a segment or a point) is allowed.
    """
    values = tuple([float(v) for v in box])
    if len(values) == 4:  # the common case in one test (every match starts here); the details below
        min_x, min_y, max_x, max_y = values
        if (
            -MAX_COORDINATE <= min_x <= max_x <= MAX_COORDINATE
            and -MAX_COORDINATE <= min_y <= max_y <= MAX_COORDINATE
        ):
            return min_x, min_y, max_x, max_y
    if len(values) != len(_BOX_FIELDS):
        raise ValidationError(
            f'region_of_interest: {len(values)} values; expected 4 (min_x, min_y, max_x, max_y)'
        )
    for field, value in zip(_BOX_FIELDS, values, strict=True):
        if not math.isfinite(value):
            raise ValidationError(f'region_of_interest: {field} is {value}; coordinates must be finite')
        if abs(value) > MAX_COORDINATE:
            raise ValidationError(f'region_of_interest: {field} is {value:g}; {_WITHIN}')
    min_x, min_y, max_x, max_y = values
    if min_x > max_x:
        raise ValidationError(f'region_of_interest: min_x {min_x:g} is greater than max_x {max_x:g}')
    if min_y > max_y:
        raise ValidationError(f'region_of_interest: min_y {min_y:g} is greater than max_y {max_y:g}')
    return min_x, min_y, max_x, max_y


def region_geometry(box: Sequence[float]) -> BaseGeometry:
    """The region as a shapely geometry: a rectangle, or a segment / point when it is degenerate."""
    min_x, min_y, max_x, max_y = box
    if min_x == max_x and min_y == max_y:
        return Point(min_x, min_y)
    if min_x == max_x or min_y == max_y:
        return LineString([(min_x, min_y), (max_x, max_y)])
    return Polygon([(min_x, min_y), (max_x, min_y), (max_x, max_y), (min_x, max_y)])


def ros_name(field: str, name: str) -> str:
    """``name`` if it is a legal ROS graph name (``/a/b``, ``a/b``, ``~a``)."""
    if not name:
        raise ValidationError(f'{field}: empty; expected a ROS name such as /robot/callback_coordinates')
    if len(name) > MAX_NAME_LENGTH:
        raise ValidationError(f'{field}: {len(name)} characters, longer than the limit of {MAX_NAME_LENGTH}')
    if not _NAME.fullmatch(name):  # not match(): its $ also matches before a trailing newline
        raise ValidationError(f'{field}: {name!r} is not a valid ROS name')
    return name


def global_ros_name(field: str, name: str) -> str:
    """``name`` if it is a legal global ROS name (starts with ``/``)."""
    ros_name(field, name)
    if not name.startswith('/'):
        raise ValidationError(f'{field}: {name!r} is not a global ROS name (it must start with /)')
    return name


_ROSRPC = re.compile(r'rosrpc://([A-Za-z0-9_.-]+|\[[0-9A-Fa-f:.]+\]):([0-9]{1,5})/?')
MAX_URI_LENGTH = 300


def rosrpc_uri(field: str, uri: str) -> str:
    """``uri`` if it is a ``rosrpc://host:port`` address (a ROS service's, as the master gives it).

    >>> rosrpc_uri('callback_uri', 'rosrpc://robot-a:41233')
    'rosrpc://robot-a:41233'
    >>> rosrpc_uri('callback_uri', 'http://a:1')
    Traceback (most recent call last):
    ...
    drvs.common.validation.ValidationError: callback_uri: 'http://a:1' is not a rosrpc://HOST:PORT address
    """
    if len(uri) > MAX_URI_LENGTH:
        raise ValidationError(f'{field}: {len(uri)} characters, longer than the limit of {MAX_URI_LENGTH}')
    found = _ROSRPC.fullmatch(uri)
    if found is None or not 0 < int(found.group(2)) < 65536:
        raise ValidationError(f'{field}: {uri!r} is not a rosrpc://HOST:PORT address')
    return uri


def request_fields(
    algorithm: str, box: Sequence[float], callback_service: str, algorithms: AlgorithmSet | None = None
) -> tuple[Parsed, tuple[float, float, float, float]]:
    """Check a DetectObjectBoundary request's own fields; return (parsed algorithm, region).

    :param algorithms: the :class:`drvs.algorithms.AlgorithmSet` to parse with (default:
        the built-ins and installed plugins).
    :raises drvs.algorithms.AlgorithmError: for the algorithm (from :func:`parse_algorithm`).
    :raises ValidationError: for the region or the callback service name.
    """
    model = parse_algorithm(algorithm, algorithms)
    region = region_of_interest(box)
    global_ros_name('callback_service', callback_service)
    return model, region


MAX_REQUEST_ID = 256
"""Longest ``request_id`` of a watch, in characters (the server keeps it)."""


def watch_terms(request_id: str, period: float, duration: float) -> bool:
    """Check a watch's own fields; True when it is to stand, False for a cancel (``duration`` 0).

    A cancel needs a valid ``request_id`` and ``duration`` only.

    >>> watch_terms('crate', 0.5, 10.0), watch_terms('crate', float('nan'), 0.0)
    (True, False)
    >>> watch_terms('crate', 0.0, 10.0)
    Traceback (most recent call last):
    ...
    drvs.common.validation.ValidationError: period: 0; expected a finite number of seconds greater than 0

    :raises ValidationError: naming the field: ``request_id`` empty or longer than
        :data:`MAX_REQUEST_ID`; ``duration`` not finite or negative; ``period`` not
        finite or not positive.
    """
    if not request_id:
        raise ValidationError('request_id: empty; it names the watch (renew or cancel it with the same)')
    if len(request_id) > MAX_REQUEST_ID:
        raise ValidationError(
            f'request_id: {len(request_id)} characters, longer than the limit of {MAX_REQUEST_ID}'
        )
    if not (math.isfinite(duration) and duration >= 0):
        raise ValidationError(f'duration: {duration:g}; expected a finite number of seconds, 0 to cancel')
    if duration == 0:
        return False
    if not (math.isfinite(period) and period > 0):
        raise ValidationError(f'period: {period:g}; expected a finite number of seconds greater than 0')
    return True
