"""RViz markers of what DRVS knows: registered fields of view, and recent detections.

Everything is in the ``map`` frame on ``/drvs/markers`` (visualization_msgs/MarkerArray):

- the server publishes one outline (a LINE_STRIP, namespace ``fields_of_view``) and one
  name (TEXT_VIEW_FACING, namespace ``names``) per registered vision system, and
  deletes the markers of those that left (``DELETEALL`` first, then the current set);
- each vision system publishes the outlines it sends in a callback (namespace
  ``detections/<vision system>/<algorithm>``), coloured by algorithm name, with a
  lifetime so old detections fade from the view by themselves.

Marker ids are stable per vision system (its position in the sorted registry), so
RViz replaces a marker in place rather than stacking copies. A detection's id is the
outline's index in its callback, in a namespace of its own per vision system and
algorithm string: the next answer to the same question from the same camera replaces
it, and no camera's markers replace another's or the fields of view. (RViz's
``DELETEALL`` clears every namespace of the display, so a change of the registry also
clears the detections shown at that moment; the next callbacks bring them back.)
"""

from __future__ import annotations

import colorsys
import zlib
from collections.abc import Iterable, Sequence

import rospy
from geometry_msgs.msg import Point
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

FRAME = 'map'
LINE_WIDTH = 0.03
TEXT_HEIGHT = 0.25
DETECTION_LIFETIME = 3.0
"""Seconds a detection outline stays in RViz unless a newer callback replaces it: long enough to
see the answer to one request asked by hand, short enough that a moving object leaves no trail."""
FIELD_OF_VIEW_COLOUR = (0.1, 0.5, 1.0, 0.9)


def markers_topic(register_service: str) -> str:
    """The server's marker topic, next to its registration service (a global name).

    A vision system publishes its detections there, beside the server's fields of view.

    >>> markers_topic('/drvs/register_vision_service')
    '/drvs/markers'
    """
    return register_service.rsplit('/', 1)[0] + '/markers'


def algorithm_colour(algorithm: str) -> tuple[float, float, float, float]:
    """A colour for an algorithm string, the same every time for the same NAME.

    >>> algorithm_colour('colour:0,0,150,80,80,255') == algorithm_colour('colour:1,2,3,4,5,6')
    True
    """
    name = algorithm.split(':', 1)[0]
    hue = (zlib.crc32(name.encode()) % 360) / 360.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.85, 0.95)
    return (r, g, b, 0.95)


def _marker(namespace: str, marker_id: int, kind: int, stamp, colour) -> Marker:
    marker = Marker(ns=namespace, id=marker_id, type=kind, action=Marker.ADD)
    marker.header.frame_id = FRAME
    marker.header.stamp = stamp
    marker.pose.orientation.w = 1.0
    marker.color = ColorRGBA(*colour)
    return marker


def outline_marker(
    namespace: str, marker_id: int, points: Sequence[Sequence[float]], colour, stamp, z: float = 0.01
) -> Marker:
    """A closed LINE_STRIP through ``points`` (x, y) just above the floor."""
    marker = _marker(namespace, marker_id, Marker.LINE_STRIP, stamp, colour)
    marker.scale.x = LINE_WIDTH
    ring = [Point(float(x), float(y), z) for x, y, *_ in points]
    marker.points = ring + ring[:1]
    return marker


def text_marker(namespace: str, marker_id: int, text: str, position, colour, stamp) -> Marker:
    marker = _marker(namespace, marker_id, Marker.TEXT_VIEW_FACING, stamp, colour)
    marker.scale.z = TEXT_HEIGHT
    marker.text = text
    marker.pose.position = Point(float(position[0]), float(position[1]), 0.3)
    return marker


def registry_markers(entries: Iterable[tuple[str, Sequence[Sequence[float]]]], stamp=None) -> MarkerArray:
    """Every registered field of view: (service name, field of view) -> outline + name markers.

    The array starts with a DELETEALL, so vision systems that left disappear from RViz.
    """
    stamp = stamp if stamp is not None else rospy.Time(0)
    clear = Marker(action=Marker.DELETEALL)
    clear.header.frame_id = FRAME
    markers = [clear]
    for marker_id, (service, points) in enumerate(sorted(entries)):
        if len(points) < 3:
            continue
        name = service.rsplit('/', 2)[-2] if service.count('/') >= 2 else service
        markers.append(outline_marker('fields_of_view', marker_id, points, FIELD_OF_VIEW_COLOUR, stamp))
        centre = (sum(p[0] for p in points) / len(points), sum(p[1] for p in points) / len(points))
        markers.append(text_marker('names', marker_id, name, centre, FIELD_OF_VIEW_COLOUR, stamp))
    return MarkerArray(markers=markers)


def detection_markers(
    vision_system: str,
    algorithm: str,
    outlines: Sequence[Sequence[Sequence[float]]],
    stamp=None,
    lifetime: float = DETECTION_LIFETIME,
) -> MarkerArray:
    """The outlines of one callback, coloured by algorithm, fading after ``lifetime`` seconds."""
    stamp = stamp if stamp is not None else rospy.Time(0)
    colour = algorithm_colour(algorithm)
    namespace = f'detections/{vision_system.strip("/")}/{algorithm}'  # one per camera and question
    markers = []
    for marker_id, points in enumerate(outlines):
        marker = outline_marker(namespace, marker_id, points, colour, stamp, z=0.02)
        marker.lifetime = rospy.Duration(lifetime)
        markers.append(marker)
    return MarkerArray(markers=markers)
