"""``elevation[:MIN_HEIGHT[,MAX_HEIGHT]]``: everything standing on the floor, from a depth image.

Each pixel's depth and the camera's calibrated pose give the point it sees; points higher than
MIN_HEIGHT above the floor (z = 0 in ``map``) are dropped onto the floor, gathered on a grid and
grouped into regions; each region is one object, reported as its footprint on the floor (not the
perspective outline of its top) with its measured top height. Method, confidence and limits:
docs/design.md ("The built-in algorithms"); the string: docs/interface.md ("Algorithms").

>>> Elevation().parse('0.05,1.2')
ElevationParams(min_height=0.05, max_height=1.2)
>>> Elevation().parse('').min_height == DEFAULT_MIN_HEIGHT
True
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from drvs.algorithms.base import Algorithm, AlgorithmError, FrameProblem, PixelObject, outlines_of_mask

if TYPE_CHECKING:
    from drvs.vision.frame import Frame

DEFAULT_MIN_HEIGHT = 0.03
"""Metres: what stands less high above the floor is floor, when ``MIN_HEIGHT`` is not given
(three times a structured-light sensor's error at 3 m once filtered, :data:`MEDIAN`)."""
MEDIAN = 5
"""Side (pixels) of the median filter over the heights: a depth camera's noise down by about
four, edges kept."""
MIN_CELL = 0.01
"""Metres: the side of the floor grid's cells, or :data:`CELL_FACTOR` times the camera's ground
sampling distance at the farthest raised points where that is larger (so that every cell of a
surface holds a point)."""
CELL_FACTOR = 1.2
CLOSING = 3
"""Side (cells) of the closing that joins the points of one object across the gaps between them."""
TOP_PERCENTILE = 95
"""An object's top: this percentile of its points' heights (stray pixels above it do not count)."""
MAX_CACHED_RAYS = 4
"""Cameras whose per-pixel rays are kept (a fixed camera's never change)."""


class DepthProblem(FrameProblem):
    """A frame that ``elevation`` cannot use (no depth, or depth that does not fit the image);
    the message says what is wrong."""


@dataclass(frozen=True)
class ElevationParams:
    """``elevation[:MIN_HEIGHT[,MAX_HEIGHT]]`` parsed: metres above the floor; ``max_height``
    None for no limit."""

    min_height: float = DEFAULT_MIN_HEIGHT
    max_height: float | None = None

    def format(self) -> str:
        top = '' if self.max_height is None else f',{self.max_height:g}'
        return f'elevation:{self.min_height:g}{top}'


def _metres(field: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0):
        raise AlgorithmError(f'algorithm: elevation {field} must be a number of metres >= 0, got {text!r}')
    return value


def parse_elevation(params: str) -> ElevationParams:
    """``MIN_HEIGHT[,MAX_HEIGHT]`` (metres) -> :class:`ElevationParams`.

    :raises AlgorithmError: more than two fields, a field that is not a number >= 0, or
        MAX_HEIGHT not above MIN_HEIGHT.
    """
    text = params.strip()
    if not text:
        return ElevationParams()
    parts = text.split(',')
    if len(parts) > 2:
        raise AlgorithmError(
            f'algorithm: elevation takes MIN_HEIGHT[,MAX_HEIGHT] (metres), '
            f'got {len(parts)} fields in {params!r}'
        )
    low = _metres('MIN_HEIGHT', parts[0].strip())
    if len(parts) == 1:
        return ElevationParams(low)
    high = _metres('MAX_HEIGHT', parts[1].strip())
    if high <= low:
        raise AlgorithmError(f'algorithm: elevation MAX_HEIGHT {high:g} is not above MIN_HEIGHT {low:g}')
    return ElevationParams(low, high)


def depth_problem(frame: Frame) -> str | None:
    """Why ``frame``'s depth cannot be used, or None: none, another size than the colour image,
    not one channel of numbers, or not one valid pixel (0, NaN and infinity are holes)."""
    depth = frame.depth
    if depth is None:
        return 'the frame has no depth image (a camera without depth cannot run elevation)'
    height, width = frame.rgb.shape[:2]
    if depth.ndim != 2 or depth.dtype.kind not in 'fiu':
        return f'the depth image is not one channel of numbers (shape {depth.shape}, {depth.dtype})'
    if depth.shape != (height, width):
        return (
            f'the depth image is {depth.shape[1]}x{depth.shape[0]} but the colour image '
            f'{width}x{height}: depth must be registered to the colour image'
        )
    if not np.any(np.isfinite(depth) & (depth > 0)):
        return 'the depth image has no valid pixel (every one 0, NaN or infinite)'
    return None


class Elevation(Algorithm):
    """The elevation algorithm: objects standing on the floor, from a frame's depth image.

    :param min_area: fewest pixels above MIN_HEIGHT that make an object (fewer: noise).
    :param epsilon: Douglas-Peucker tolerance of the footprints, in grid cells.
    """

    name = 'elevation'
    syntax = 'elevation[:MIN_HEIGHT[,MAX_HEIGHT]]'
    needs_depth = True

    def __init__(self, min_area: float = 20.0, epsilon: float = 1.0):
        self.min_area = min_area
        self.epsilon = epsilon
        self._rays: dict[tuple, np.ndarray] = {}  # per optics and pose
        self._grids: dict[tuple, np.ndarray] = {}  # per optics: see _rays_of
        self._lock = threading.Lock()  # guards _rays and _grids

    def parse(self, params: str) -> ElevationParams:
        return parse_elevation(params)

    def frame_problem(self, frame: Frame) -> str | None:
        """Why ``frame`` cannot be used (:func:`depth_problem`, naming the algorithm), or None."""
        problem = depth_problem(frame)
        return f'elevation: {problem}' if problem else None

    def detect(self, frame: Frame, params: ElevationParams) -> list[PixelObject]:
        """Objects standing in ``frame``: footprints in ``map`` with their top heights.

        :raises DepthProblem: the frame's depth cannot be used (:func:`depth_problem`).
        """
        problem = self.frame_problem(frame)
        if problem:
            raise DepthProblem(problem)
        heights, raw, depth, rays = self.heights(frame)
        # Raised: above MIN both filtered (not noise) and as measured (not a neighbour's height
        # lent by the filter, which would put the point out along the ray, past the object's edge).
        raised = (heights > params.min_height) & (raw > params.min_height)
        rows, cols = np.nonzero(raised)
        if len(rows) < max(self.min_area, 1):
            return []
        distance = depth[rows, cols].astype(np.float64)
        ray = rays[rows, cols].astype(np.float64)
        eye = np.asarray(frame.camera.eye, float)
        x = eye[0] + ray[:, 0] * distance
        y = eye[1] + ray[:, 1] * distance
        z = heights[rows, cols]
        cell = max(MIN_CELL, CELL_FACTOR * float(np.percentile(distance, 95)) * _pixel_angle(rays))
        return self._regions(frame, params, x, y, z, cell)

    # -- the heights -------------------------------------------------------------------------------
    def heights(self, frame: Frame) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(height above the floor median-filtered, height as measured, depth, ray) of every pixel.

        A hole (0, NaN, infinite depth) has height 0 and depth 0, so it is never raised itself; for
        the filter it lends its neighbours the highest valid height within :data:`MEDIAN` / 2 of
        it, so that a sensor's holes along an object's edge do not eat into the object.
        A ray is the pixel's viewing direction in ``map`` scaled to 1 along the optical axis, so a
        point is ``eye + ray * depth``.
        """
        import cv2

        assert frame.depth is not None  # detect() checked
        rays = self._rays_of(frame)
        depth = np.asarray(frame.depth, np.float32)
        valid = (
            np.isfinite(depth) & (depth > 0) & np.isfinite(rays[..., 2])
        )  # a lens may not invert everywhere
        depth = np.where(valid, depth, 0).astype(np.float32)
        eye_z = np.float32(frame.camera.eye[2])
        raw = np.where(valid, eye_z + rays[..., 2] * depth, 0).astype(np.float32)
        lent = raw
        if not valid.all():  # for the filter only, a hole takes the highest valid height next to it
            kernel = np.ones((MEDIAN, MEDIAN), np.uint8)
            lent = np.where(valid, raw, cv2.dilate(np.where(valid, raw, -np.inf).astype(np.float32), kernel))
            lent = np.where(np.isfinite(lent), lent, 0).astype(np.float32)
        return cv2.medianBlur(lent, MEDIAN), raw, depth, rays

    def _rays_of(self, frame: Frame) -> np.ndarray:
        """(H, W, 3) float32 rays of the frame's pixel centres.

        A ray is ``e3 + p * e1 + q * e2``: (p, q) per pixel depend on the optics alone (for a lens,
        undistorting every pixel: long), kept per camera; the basis (e1, e2, e3) on its pose.
        The rays of the last :data:`MAX_CACHED_RAYS` poses are kept too.
        """
        camera = frame.camera
        height, width = frame.depth.shape if frame.depth is not None else frame.rgb.shape[:2]
        optics, basis = _optics_and_basis(camera)
        key = (optics, frame.sample_offset, height, width)
        posed = (key, np.asarray(basis).tobytes())
        with self._lock:
            rays = self._rays.get(posed)
            grid = self._grids.get(key)
        if rays is not None:
            return rays
        if grid is None:
            rows, cols = np.mgrid[0:height, 0:width]
            pixels = frame.to_camera(np.c_[cols.ravel() + 0.5, rows.ravel() + 0.5])
            grid = _grid(camera, pixels).astype(np.float32).reshape(height, width, 2)
        e1, e2, e3 = (np.asarray(axis, np.float32) for axis in basis)
        rays = e3 + grid[..., :1] * e1 + grid[..., 1:] * e2
        rays.setflags(write=False)
        with self._lock:
            for cache in (self._rays, self._grids):
                if len(cache) >= MAX_CACHED_RAYS:
                    cache.pop(next(iter(cache)))
            self._rays[posed] = rays
            self._grids[key] = grid
        return rays

    # -- the regions -------------------------------------------------------------------------------
    def _regions(
        self,
        frame: Frame,
        params: ElevationParams,
        x: np.ndarray,
        y: np.ndarray,
        z: np.ndarray,
        cell: float,
    ) -> list[PixelObject]:
        """The raised points (x, y, height) gathered on a floor grid of ``cell`` metres, one object
        per connected region of the grid."""
        import cv2

        x0, y0 = float(x.min()) - 2 * cell, float(y.min()) - 2 * cell
        columns = ((x - x0) / cell).astype(np.int64)
        rows = ((y - y0) / cell).astype(np.int64)
        shape = (int(rows.max()) + 3, int(columns.max()) + 3)
        flat = rows * shape[1] + columns
        counts = np.bincount(flat, minlength=shape[0] * shape[1]).reshape(shape)
        occupied = (counts > 0).astype(np.uint8) * 255
        closed = cv2.morphologyEx(occupied, cv2.MORPH_CLOSE, np.ones((CLOSING, CLOSING), np.uint8))
        count, labels = cv2.connectedComponents(closed, connectivity=8)
        point_labels = labels.ravel()[flat]
        found = []
        for label in range(1, count):
            mine = point_labels == label
            if np.count_nonzero(mine) < max(self.min_area, 1):
                continue
            top = float(np.percentile(z[mine], TOP_PERCENTILE))
            if params.max_height is not None and top > params.max_height:
                continue
            region = np.where(labels == label, 255, 0).astype(np.uint8)
            # A part smaller than the closing, joined to the rest at a corner, is a spur of its edge.
            for part in outlines_of_mask(region, CLOSING * CLOSING, self.epsilon, evidence=occupied & region):
                footprint = _inset(
                    np.c_[x0 + part.outline[:, 0] * cell, y0 + part.outline[:, 1] * cell], cell
                )
                if footprint is None:
                    continue
                found.append(
                    PixelObject(
                        outline=_in_image(frame, footprint),
                        area=float(np.count_nonzero(mine)),
                        confidence=part.confidence,
                        footprint=footprint,
                        top_height=top,
                    )
                )
        return found


def _inset(footprint: np.ndarray, cell: float) -> np.ndarray | None:
    """The outline of a region's cells moved in by half a cell: the cells at its edge are only
    partly covered (half on average), so the outline on their outer edges is too large."""
    from shapely.geometry import Polygon

    shape = Polygon(footprint).buffer(-cell / 2.0, join_style=2, mitre_limit=2.0)
    if shape.geom_type == 'MultiPolygon':  # a ragged edge's one-cell spurs come off: the body stays
        shape = max(shape.geoms, key=lambda part: part.area)
    if shape.is_empty or shape.geom_type != 'Polygon':
        return None
    return np.asarray(shape.exterior.coords)[:-1]


def _optics_and_basis(camera: Any) -> tuple[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """What a camera's per-pixel (p, q) depend on, and its pose's basis (e1, e2, e3) in ``map``."""
    if hasattr(camera, 'K'):  # drvs.vision.optics.CameraModel: normalized (x, y) in its optical frame
        rotation = np.asarray(camera.rotation, float)
        optics = (camera.K.tobytes(), camera.D, camera.width, camera.height)
        return optics, (rotation[:, 0], rotation[:, 1], rotation[:, 2])
    right, up, forward = camera.axes()  # drvs.vision.camera.PinholeCamera
    return (camera.width, camera.height, camera.fov_deg), (right, up, forward)


def _grid(camera: Any, pixels: np.ndarray) -> np.ndarray:
    """(p, q) of each pixel position, (N, 2): see :func:`_optics_and_basis`."""
    if hasattr(camera, 'K'):
        return np.asarray(camera.undistort(pixels), float)
    t = camera.tan_half_fov
    x_ndc = 2.0 * pixels[:, 0] / camera.width - 1.0
    y_ndc = 1.0 - 2.0 * pixels[:, 1] / camera.height
    return np.c_[x_ndc * t * camera.aspect, y_ndc * t]


def _pixel_angle(rays: np.ndarray) -> float:
    """Radians between the rays of two neighbouring pixels at the image's centre (1 / focal length)."""
    height, width = rays.shape[:2]
    row, col = height // 2, min(width // 2, width - 2)
    return float(np.linalg.norm(rays[row, col + 1] - rays[row, col]))


def _in_image(frame: Frame, footprint: np.ndarray) -> np.ndarray:
    """Where a footprint on the floor shows in the frame's array pixels (NaN behind the camera)."""
    points = np.c_[footprint, np.zeros(len(footprint))]
    return frame.camera.project_3d_to_pixel(points) - np.asarray(frame.sample_offset)
