"""A vision system's processing: run an algorithm on a frame, put each outline on the floor in ``map``.

Outline vertices are lifted with the depth image where there is one, else met with the
floor plane; the frame's camera is a :class:`drvs.vision.camera.PinholeCamera` or a
:class:`drvs.vision.optics.CameraModel`. :class:`FrameCache` lets requests that arrive close
together share one render. How and why: docs/design.md ("Vision systems").
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import NamedTuple

import cv2
import numpy as np
from shapely.geometry import Polygon, box
from shapely.geometry.base import BaseGeometry

from drvs.algorithms import Parsed, PixelObject
from drvs.vision.frame import Frame

log = logging.getLogger('rosout.' + __name__)

Outline = list[tuple[float, float]]


class FloorObject(NamedTuple):
    """An object an algorithm found, on the floor (:func:`project_objects`).

    ``bounds`` and ``outline`` are worked out once per frame, not once per request
    that clips it (:func:`in_region`): shapely 1.8 takes about 18 µs for ``bounds``.
    """

    shape: Polygon
    ordered: list | None  # the corners in their own order (a tag, corner 0 first), or None
    label: str
    bounds: tuple[float, float, float, float]  # min_x, min_y, max_x, max_y
    outline: Outline  # the whole object as reported: ``ordered``, or ring(shape)
    confidence: float = 0.0  # the algorithm's (PixelObject.confidence); 0: unknown
    height: float = 0.0  # the object's top above the floor (PixelObject.top_height); 0: unknown
    clearance: float = 0.0  # the room under it (PixelObject.clearance); 0: on the floor or unknown

    @classmethod
    def of(cls, shape: Polygon, ordered: list | None, label: str, pixel_object: PixelObject) -> FloorObject:
        """``shape`` (``ordered``: its corners in their order, or None) of ``pixel_object``."""
        outline = ordered if ordered is not None else ring(shape)
        return cls(
            shape,
            ordered,
            label,
            shape.bounds,
            outline,
            pixel_object.confidence,
            pixel_object.top_height,
            pixel_object.clearance,
        )


class Located(NamedTuple):
    """An object as a request gets it (:func:`in_region`): its outline on the floor in ``map``
    (clipped to the region, counter-clockwise; a tag's corners whole, in their order), its label,
    the algorithm's confidence (0-1, 0: unknown; an object clipped keeps its whole one), the
    height of its top above the floor (metres; 0: unknown) and of its underside where it was
    seen to leave room under it (metres; 0: on the floor or unknown)."""

    outline: Outline
    label: str
    confidence: float = 0.0
    height: float = 0.0
    clearance: float = 0.0


def vertex_depths(frame: Frame, outline: np.ndarray) -> np.ndarray:
    """Depth at each outline vertex, read from the object's own pixels next to it.

    A vertex (u, v) lies on pixel edges; of the pixels around it, those whose
    centres are inside the outline belong to the object; the nearest depth among
    them is used (searching a little further out for a vertex on a thin spike).
    """
    depth = frame.depth
    if depth is None:
        raise ValueError('vertex_depths: the frame has no depth image')
    height, width = depth.shape
    contour = outline.astype(np.float32).reshape(-1, 1, 2)
    # The 2 x 2 pixels around every vertex at once (radius 1), with holes (0, NaN) left out.
    cu, cv = np.round(outline).astype(int).T
    rows = cv[:, None] + np.array([-1, -1, 0, 0])
    cols = cu[:, None] + np.array([-1, 0, -1, 0])
    on_image = (rows >= 0) & (rows < height) & (cols >= 0) & (cols < width)
    values = np.full(rows.shape, np.nan, np.float32)
    values[on_image] = depth[rows[on_image], cols[on_image]]
    valid = values > 0
    for i, k in zip(*np.nonzero(valid), strict=True):
        centre = (float(cols[i, k]) + 0.5, float(rows[i, k]) + 0.5)
        valid[i, k] = cv2.pointPolygonTest(contour, centre, False) >= 0
    depths = np.where(valid, values, np.inf).min(axis=1)
    for i in np.nonzero(~valid.any(axis=1))[0]:  # a thin spike: look further out
        depths[i] = _depth_further(depth, contour, int(cu[i]), int(cv[i]))
    return depths


def _depth_further(depth: np.ndarray, contour: np.ndarray, cu: int, cv: int) -> float:
    """:func:`vertex_depths` for a vertex with none of the object's pixels in its 2 x 2."""
    height, width = depth.shape
    for radius in (2, 3):
        best = None
        for row in range(max(cv - radius, 0), min(cv + radius, height)):
            for col in range(max(cu - radius, 0), min(cu + radius, width)):
                d = depth[row, col]
                if not d > 0:  # a hole in a depth camera's image (0 or NaN)
                    continue
                if best is not None and d >= best:
                    continue
                if cv2.pointPolygonTest(contour, (col + 0.5, row + 0.5), False) >= 0:
                    best = d
        if best is not None:
            return best
    # Degenerate outline: the nearest pixel whatever it is (NaN if a hole).
    found = depth[min(max(cv, 0), height - 1), min(max(cu, 0), width - 1)]
    return found if found > 0 else np.nan


def floor_points(frame: Frame, pixel_object: PixelObject) -> np.ndarray:
    """The outline's vertices put on the floor, (N, 3) in ``map``; rays that never meet it left out.

    An algorithm that worked out the object's ``footprint`` on the floor gives it as it is; an
    object that lies flat at a known ``height`` (a tag) is met with that plane; otherwise each
    vertex is lifted with the depth image and dropped onto the floor, or, without depth, met with
    the floor plane.
    """
    if pixel_object.footprint is not None:
        footprint = np.asarray(pixel_object.footprint, float).reshape(-1, 2)
        return footprint[np.all(np.isfinite(footprint), axis=1)]
    outline = np.asarray(pixel_object.outline, float)
    pixels = frame.to_camera(outline)
    if pixel_object.height is not None:
        points = frame.camera.pixel_to_floor(pixels, z=pixel_object.height)
    elif frame.depth is None:
        points = frame.camera.pixel_to_floor(pixels)
    else:
        points = frame.camera.pixel_to_point(pixels, vertex_depths(frame, outline))
        holes = ~np.all(np.isfinite(points), axis=1)
        if holes.any():  # no depth there: the floor plane
            points[holes] = frame.camera.pixel_to_floor(pixels)[holes]
    return points[np.all(np.isfinite(points), axis=1)]


def project_outline(frame: Frame, pixel_object: PixelObject) -> list[Polygon]:
    """The floor polygon(s) under an outline found in ``frame``, in ``map``."""
    points = floor_points(frame, pixel_object)
    if len(points) < 3:
        return []
    shape = Polygon(points[:, :2]).buffer(0)
    return _polygons(shape)


def _polygons(shape: BaseGeometry) -> list[Polygon]:
    if shape.is_empty:
        return []
    if shape.geom_type == 'Polygon':
        return [shape] if shape.area > 0 else []
    return [part for part in getattr(shape, 'geoms', []) if part.geom_type == 'Polygon' and part.area > 0]


def ring(shape: Polygon) -> Outline:
    """A polygon's exterior, counter-clockwise, without the closing vertex.

    What ``orient(shape, 1.0).exterior`` gives (the same signed-area sum, so the
    same choice), without building a new polygon, which costs more than the rest.
    """
    coords = [(float(x), float(y)) for x, y, *_ in shape.exterior.coords]
    xs = [x for x, _ in coords] + [coords[1][0]]
    ys = [y for _, y in coords] + [coords[1][1]]
    if sum(xs[i] * (ys[i + 1] - ys[i - 1]) for i in range(1, len(coords))) / 2.0 < 0.0:
        coords.reverse()
    return coords[:-1]


def on_floor(frame: Frame, algorithm: Parsed) -> list[FloorObject]:
    """Every object ``algorithm`` (a :class:`drvs.algorithms.Parsed`) finds in ``frame``, on the
    floor. Whatever the region asked for, so that
    several requests with one algorithm on one frame detect once (:func:`in_region` clips).

    Two stages: the algorithm segments the image (pixel outlines), then
    :func:`project_objects` puts them on the floor."""
    return project_objects(frame, algorithm.detect(frame))


def project_objects(frame: Frame, pixel_objects: list[PixelObject]) -> list[FloorObject]:
    """The objects an algorithm found in ``frame`` (pixel outlines) on the floor, as :func:`on_floor`
    gives them."""
    found = []
    for pixel_object in pixel_objects:
        if pixel_object.keep_order:
            points = floor_points(frame, pixel_object)
            if len(points) == len(pixel_object.outline):
                corners = [(float(x), float(y)) for x, y, _ in points]
                found.append(FloorObject.of(Polygon(corners), corners, pixel_object.label, pixel_object))
            continue
        for floor_shape in project_outline(frame, pixel_object):
            found.append(FloorObject.of(floor_shape, None, pixel_object.label, pixel_object))
    return found


def in_region(
    objects: list[FloorObject], region_of_interest: tuple[float, float, float, float]
) -> list[Located]:
    """(outline, label, confidence, height, clearance) of each of :func:`on_floor`'s ``objects``
    that intersects ``region_of_interest`` (min_x, min_y, max_x, max_y), clipped to it.

    An object whose vertex order means something (a tag, corner 0 first) is reported
    whole, in its own order, when it intersects the region.
    """
    low_x, low_y, high_x, high_y = region_of_interest
    region = None
    found = []
    for shape, ordered, label, (min_x, min_y, max_x, max_y), outline, confidence, height, under in objects:
        # Bounds first: an object wholly outside or wholly inside the region needs no GEOS
        # operation (the intersection was most of a one-camera request's time).
        if max_x < low_x or min_x > high_x or max_y < low_y or min_y > high_y:
            continue
        if low_x <= min_x and max_x <= high_x and low_y <= min_y and max_y <= high_y:
            found.append(Located(outline, label, confidence, height, under))
            continue
        if region is None:
            region = box(*region_of_interest)
        if ordered is not None:
            if shape.intersects(region):
                found.append(Located(outline, label, confidence, height, under))
            continue
        for part in _polygons(shape.intersection(region)):
            found.append(Located(ring(part), label, confidence, height, under))
    return found


def locate_labelled(
    frame: Frame, algorithm: Parsed, region_of_interest: tuple[float, float, float, float]
) -> list[Located]:
    """(outline, label, confidence) on the floor (``map``, counter-clockwise) of each object ``algorithm``
    (a :class:`drvs.algorithms.Parsed`) finds in ``frame`` that intersects
    ``region_of_interest`` (min_x, min_y, max_x, max_y), clipped to it (:func:`in_region`)."""
    return in_region(on_floor(frame, algorithm), region_of_interest)


def locate_objects(
    frame: Frame, algorithm: Parsed, region_of_interest: tuple[float, float, float, float]
) -> list[Outline]:
    """The outlines of :func:`locate_labelled`, without labels."""
    return [found.outline for found in locate_labelled(frame, algorithm, region_of_interest)]


def draw_detections(
    frame: Frame, outlines: list[Outline], colour: tuple[int, int, int] = (255, 0, 255)
) -> np.ndarray:
    """A copy of the frame's RGB with floor outlines drawn where they lie on the floor."""
    image = frame.rgb.copy()
    for outline in outlines:
        points = np.c_[np.asarray(outline), np.zeros(len(outline))]
        pixels = frame.camera.project_3d_to_pixel(points)
        if np.all(np.isfinite(pixels)):
            array = pixels - np.asarray(frame.sample_offset) - 0.5  # pixel centres
            cv2.polylines(image, [np.round(array).astype(np.int32)], True, colour, 2)
    return image


class FrameCache:
    """The last captured frame, shared by requests that arrive within ``max_age`` of its capture.

    ``capture(stamp)`` renders a frame stamped ``stamp`` (the capture's start on
    ``clock``: the state of the world it shows). A request that arrives while a
    capture is in progress, or at most ``max_age`` seconds after it finished,
    reuses it. Measuring from the end matters: a render holds the interpreter
    for its whole duration, so requests that came in during it are only seen,
    and timestamped, once it is done. :meth:`get` is thread-safe: concurrent
    requests wait for the one render in progress and then reuse it.
    """

    def __init__(
        self, capture: Callable[[float], Frame], max_age: float, clock: Callable[[], float] = time.time
    ):
        self.capture = capture
        self.max_age = max_age
        self.clock = clock
        self.renders = 0
        self.hits = 0
        self._frame: Frame | None = None
        self._ready_at = -math.inf
        self._lock = threading.Lock()

    @property
    def last(self) -> Frame | None:
        """The last frame captured, if any (no capture)."""
        return self._frame

    def get(self, arrival: float) -> tuple[Frame, bool]:
        """A frame for a request that arrived at ``arrival``: (frame, whether it was reused)."""
        with self._lock:
            if self._frame is not None and arrival <= self._ready_at + self.max_age:
                self.hits += 1
                return self._frame, True
            self._frame = self.capture(self.clock())
            self._ready_at = self.clock()
            self.renders += 1
            return self._frame, False
