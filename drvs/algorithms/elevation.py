"""``elevation[:MIN_HEIGHT[,MAX_HEIGHT]]``: everything standing on the floor, from a depth image.

Each pixel's depth and the camera's calibrated pose give the point it sees; points higher than
MIN_HEIGHT above the floor (z = 0 in ``map``) are dropped onto the floor, gathered on a grid and
grouped into regions; each region is one object, reported as its footprint on the floor (not the
perspective outline of its top) with its measured top height, and with the free space under it
where the camera sees floor under it (its clearance). Method, confidence and limits:
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
UNDER_CELLS = 4
"""Grid cells a ray to the floor must run under an object's footprint to prove room under it: a
ray that grazes it proves nothing, and a noisy sensor scatters a side face's points a few cells
out from it (with twice a Kinect-class sensor's error, 3 cells made a box on the floor seem to
leave 13 cm under it)."""
PROOF = 3
"""Floor pixels seen under an object that prove room under it; the clearance is the entry height of
the PROOF-th highest (one or two stray pixels do not lift it)."""
NOISE_SIGMAS = 3
"""The sensor's depth error scatters an object's side-face points out from it, up to about three
standard deviations: the footprint the rays are walked back through reaches that much too far
towards the camera, and their entry heights are too high by as much as the same error of the
floor's heights (the ray's height over the floor, eye height times distance walked over distance
to the camera, grows as the side face's points scatter out). That much comes off the clearance."""
LEAST_CLEARANCE = 2
"""Times MIN_HEIGHT: a lower clearance is reported as 0. The noisy top of a pallet lower than that
shows pixels lower than MIN_HEIGHT (floor) that seem to prove room under it; a robot needs more."""
UNDERSIDE_PERCENTILE = 1
"""The lowest side-face point of an object: this percentile of its raised points' measured heights
(a table's legs or a box standing beside a shelf bring it down to the floor)."""


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
        self._rays: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}  # per optics and pose: see _posed
        self._grids: dict[tuple, np.ndarray] = {}  # per optics: see _posed
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
        # The pixels that see the floor (measured lower than MIN), at their rays' point on the floor:
        # the sensor's depth error moves a point along its ray, off the floor.
        floor = (self._posed(frame)[1], (depth > 0) & (raw < params.min_height), raw)
        return self._regions(frame, params, (x, y, z, raw[rows, cols]), cell, floor)

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
        """(H, W, 3) float32 rays of the frame's pixel centres (:meth:`_posed`)."""
        return self._posed(frame)[0]

    def _posed(self, frame: Frame) -> tuple[np.ndarray, np.ndarray]:
        """(H, W, 3) float32 rays of the frame's pixel centres, and where each meets the floor:
        (H, W, 3) float32 x, y and horizontal distance from the camera (NaN: it never does).

        A ray is ``e3 + p * e1 + q * e2``: (p, q) per pixel depend on the optics alone (for a lens,
        undistorting every pixel: long), kept per camera; the basis (e1, e2, e3) on its pose.
        The rays of the last :data:`MAX_CACHED_RAYS` poses are kept too.
        """
        camera = frame.camera
        height, width = frame.depth.shape if frame.depth is not None else frame.rgb.shape[:2]
        optics, basis = _optics_and_basis(camera)
        key = (optics, frame.sample_offset, height, width)
        posed = (key, np.asarray(basis).tobytes(), tuple(camera.eye))
        with self._lock:
            kept = self._rays.get(posed)
            grid = self._grids.get(key)
        if kept is not None:
            return kept
        if grid is None:
            rows, cols = np.mgrid[0:height, 0:width]
            pixels = frame.to_camera(np.c_[cols.ravel() + 0.5, rows.ravel() + 0.5])
            grid = _grid(camera, pixels).astype(np.float32).reshape(height, width, 2)
        e1, e2, e3 = (np.asarray(axis, np.float32) for axis in basis)
        rays = e3 + grid[..., :1] * e1 + grid[..., 1:] * e2
        rays.setflags(write=False)
        floor = _floor_of(np.asarray(camera.eye, float), rays)
        with self._lock:
            if len(self._rays) >= MAX_CACHED_RAYS:
                self._rays.pop(next(iter(self._rays)))
            if len(self._grids) >= MAX_CACHED_RAYS:
                self._grids.pop(next(iter(self._grids)))
            self._rays[posed] = (rays, floor)
            self._grids[key] = grid
        return rays, floor

    # -- the regions -------------------------------------------------------------------------------
    def _regions(
        self,
        frame: Frame,
        params: ElevationParams,
        points: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
        cell: float,
        floor: tuple[np.ndarray, np.ndarray, np.ndarray],
    ) -> list[PixelObject]:
        """The raised ``points`` (x, y, filtered height, measured height) gathered on a floor grid of
        ``cell`` metres, one object per connected region of the grid; ``floor``: where every
        pixel's ray meets the floor, which pixels see the floor and every pixel's measured height
        (:func:`_under`): they prove room under an object."""
        import cv2

        x, y, z, measured = points
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
        tops = np.zeros(count)
        kept = []
        for label in range(1, count):
            mine = point_labels == label
            if np.count_nonzero(mine) < max(self.min_area, 1):
                continue
            tops[label] = float(np.percentile(z[mine], TOP_PERCENTILE))
            if params.max_height is None or tops[label] <= params.max_height:
                kept.append((label, mine))
        # Each cell's height, the mean of its points' (the closing's gaps: their neighbours' highest):
        # a ray lower than that is under it.
        sums = np.bincount(flat, weights=z, minlength=shape[0] * shape[1]).reshape(shape)
        highest = (sums / np.maximum(counts, 1)).astype(np.float32)
        gaps = cv2.dilate(highest, np.ones((CLOSING, CLOSING), np.uint8))
        highest = np.where(counts > 0, highest, gaps)
        grid = _Grid(labels, highest, x0, y0, cell)
        under = _under(grid, floor, np.asarray(frame.camera.eye, float), tops)
        found = []
        for label, mine in kept:
            top = float(tops[label])
            underside = float(np.percentile(measured[mine], UNDERSIDE_PERCENTILE))
            clearance = _clearance(under.get(label), top, underside, params.min_height)
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
                        clearance=clearance,
                    )
                )
        return found


# -- the room under an object ------------------------------------------------------------------------
@dataclass(frozen=True)
class _Grid:
    """The floor grid's labelled regions: ``labels[row, col]`` (0: no object) and the height
    ``highest[row, col]`` of the cell whose lower corner is ``(x0 + col * cell, y0 + row * cell)``."""

    labels: np.ndarray
    highest: np.ndarray
    x0: float
    y0: float
    cell: float

    def label_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The label of the cell under each point (x, y); 0 off the grid."""
        return self.at(x, y)[0]

    def at(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The label and the height of the cell under each point (x, y); 0 off the grid."""
        cols = np.floor((x - self.x0) / self.cell).astype(np.int64)
        rows = np.floor((y - self.y0) / self.cell).astype(np.int64)
        rows_n, cols_n = self.labels.shape
        on = (rows >= 0) & (rows < rows_n) & (cols >= 0) & (cols < cols_n)
        labels = np.zeros(len(x), self.labels.dtype)
        labels[on] = self.labels[rows[on], cols[on]]
        highest = np.zeros(len(x), self.highest.dtype)
        highest[on] = self.highest[rows[on], cols[on]]
        return labels, highest


NOWHERE = -1e9
"""Where :func:`_floor_of` puts a ray that never meets the floor: far off any grid."""


def _floor_of(eye: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Where each ray meets the floor, (H, W, 3) float32: x, y and the horizontal distance from the
    camera; :data:`NOWHERE` (and 0) for a ray that never does."""
    down = np.isfinite(rays[..., 2]) & (rays[..., 2] < 0)
    with np.errstate(divide='ignore', invalid='ignore'):
        reach = np.where(down, np.float32(eye[2]) / -rays[..., 2], 0.0)
    dx, dy = rays[..., 0] * reach, rays[..., 1] * reach
    floor = np.stack(
        [np.where(down, eye[0] + dx, NOWHERE), np.where(down, eye[1] + dy, NOWHERE), np.hypot(dx, dy)],
        axis=-1,
    ).astype(np.float32)
    floor.setflags(write=False)
    return floor


def _under(
    grid: _Grid, floor: tuple[np.ndarray, np.ndarray, np.ndarray], eye: np.ndarray, tops: np.ndarray
) -> dict[int, tuple[np.ndarray, float]]:
    """Region label -> the heights at which the rays of the floor pixels seen inside its footprint
    entered it, lower than its top (``tops[label]``; 0: not an object), only those that ran
    :data:`UNDER_CELLS` under it; and the standard deviation of those floor pixels' measured
    heights (the sensor's noise there). ``floor``: where every pixel's ray meets the floor
    (:func:`_floor_of`), which pixels see the floor and every pixel's measured height.

    A ray descends from the camera to the floor: its highest point under the object is where it
    went under it, and the object's underside there is higher still. Walked back from the floor
    point towards the camera a cell at a time while it stays in the region and lower than the height
    of the cell it is over (where it is higher, it passed over that part: a lower box merged with a
    shelf, or the footprint off); the region's edge cell is half covered on average, so half a cell
    comes off the distance under it.
    """
    import cv2

    points, seen, raw = floor
    # Every pixel's cell's label at once (nearest: rounding v - 0.5 is flooring v; off the grid 0),
    # then only the floor pixels in a region, exactly.
    scale = np.float32(1.0 / grid.cell)
    cols = (points[..., 0] - np.float32(grid.x0 + grid.cell / 2)) * scale
    rows = (points[..., 1] - np.float32(grid.y0 + grid.cell / 2)) * scale
    under = cv2.remap(
        grid.labels.astype(np.float32), cols, rows, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT
    )
    chosen = np.flatnonzero(seen & (under > 0))
    x, y, reach = (points.reshape(-1, 3)[chosen, i].astype(np.float64) for i in range(3))
    measured = raw.ravel()[chosen]
    labels = grid.label_at(x, y)
    inside = np.nonzero(labels)[0]
    if len(inside) == 0:
        return {}
    x, y, reach, labels, measured = x[inside], y[inside], reach[inside], labels[inside], measured[inside]
    ux, uy = (eye[0] - x) / np.maximum(reach, 1e-9), (eye[1] - y) / np.maximum(reach, 1e-9)
    # Not past the point below the camera, nor above the top.
    furthest = np.minimum(reach, tops[labels] * reach / eye[2] + grid.cell / 2)
    step = grid.cell
    run = np.zeros(len(x))  # metres walked back still inside the region
    walking = np.arange(len(x))
    distance = step
    while len(walking):
        walking = walking[furthest[walking] > distance]
        back, highest = grid.at(x[walking] + ux[walking] * distance, y[walking] + uy[walking] * distance)
        walking = walking[(back == labels[walking]) & (highest > eye[2] * distance / reach[walking])]
        run[walking] = distance
        distance += step
    run -= grid.cell / 2
    deep = run >= UNDER_CELLS * grid.cell
    entered = eye[2] * run[deep] / reach[deep]
    deep[deep] = entered < tops[labels[deep]]
    entered = eye[2] * run[deep] / reach[deep]
    found = {}
    for label in np.unique(labels[deep]).tolist():
        # The sensor's noise: the floor's heights below its median (those above MIN are not floor).
        noise = max(0.0, -float(np.percentile(measured[labels == label], 16)))
        found[label] = (entered[labels[deep] == label], noise)
    return found


def _clearance(
    under: tuple[np.ndarray, float] | None, top: float, underside: float, min_height: float
) -> float:
    """An object's clearance: the entry height of the :data:`PROOF`-th highest ray seen under it
    less :data:`NOISE_SIGMAS` times the sensor's noise there (:func:`_under`), no higher than its
    lowest side-face point (``underside``); 0 without proof (unknown: on the floor) or when lower
    than :data:`LEAST_CLEARANCE` times ``min_height``."""
    if under is None or len(under[0]) < PROOF:
        return 0.0
    entered, noise = under
    clearance = float(min(np.partition(entered, -PROOF)[-PROOF] - NOISE_SIGMAS * noise, underside))
    return clearance if clearance >= LEAST_CLEARANCE * min_height else 0.0


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
