"""A calibrated camera as ROS describes it: CameraInfo intrinsics and distortion, and its pose on tf.

:class:`CameraModel` is the model of any camera whose frames arrive on a topic (where
:mod:`drvs.vision.camera` is the simulation's ideal camera); every method takes and returns
DRVS corner pixel coordinates (OpenCV's + :data:`OPENCV_OFFSET`). The conventions:
docs/interface.md ("Units and frames"); why undistortion iterates: docs/design.md.

>>> camera = PinholeCamera(eye=(2.0, 1.0, 3.0), target=(2.0, 1.0, 0.0), fov_deg=60, width=800, height=600)
>>> lens = CameraModel.from_pinhole(camera, distortion=(-0.25, 0.08, 0.0, 0.0, 0.0))
>>> camera.project_3d_to_pixel((3.0, 0.0, 0.0)).round(2).tolist()  # ideal
[573.21, 473.21]
>>> lens.project_3d_to_pixel((3.0, 0.0, 0.0)).round(2).tolist()  # barrel: pulled towards the centre
[564.27, 464.27]
>>> lens.pixel_to_floor(lens.project_3d_to_pixel((3.0, 0.0, 0.0))).round(9).tolist()
[3.0, 0.0, 0.0]
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from drvs.vision.camera import PinholeCamera

if TYPE_CHECKING:
    from shapely.geometry import Polygon

OPENCV_OFFSET = 0.5
"""DRVS corner coordinates minus this are OpenCV / ROS pixel coordinates."""

DISTORTION_LENGTHS = (0, 4, 5, 8, 12)
"""Numbers of coefficients of OpenCV's pinhole distortion model understood here: none,
(k1, k2, p1, p2), plumb_bob (+ k3), rational_polynomial (+ k4, k5, k6), + thin prism
(s1, s2, s3, s4). Not OpenCV's tilted sensor (14) nor the fisheye model (ROS equidistant)."""

UNDISTORT_TOLERANCE = 1e-6
"""Pixels: an undistorted position must distort back to within this of its pixel."""

_CV_CRITERIA = (
    1 | 2,
    10,
    1e-9,
)  # cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS: 10 steps, or closer than 1e-9
_NEWTON_GOAL = 1e-9  # pixels
_NEWTON_ITERATIONS = 50
_NEWTON_HALVINGS = 30

FOOTPRINT_RANGE_FACTOR = 10.0
""":meth:`CameraModel.floor_footprint` drops rays before they could meet the floor beyond
this many times ``max_range`` (times the ray's slope factor), so every vertex is finite."""
FOOTPRINT_CIRCLE_SEGMENTS = 64


def intrinsics_of(camera: PinholeCamera, sample_offset: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """The 3x3 ``K`` (OpenCV convention) of the images a :class:`PinholeCamera` renders.

    ``sample_offset`` is the renderer's (:data:`drvs.sim.scene.TINY_RENDERER_SAMPLE` for
    :meth:`drvs.sim.scene.Scene.render`): array pixel (r, c) shows what the ideal model sees
    at (c + 0.5, r + 0.5) + sample_offset. PyBullet's pixels are square:
    fx = fy = (height / 2) / tan(fov / 2), principal point at the image centre.

    >>> camera = PinholeCamera(eye=(0, 0, 3), target=(0, 0, 0), fov_deg=90, width=800, height=600)
    >>> intrinsics_of(camera, (-0.5, 0.5)).round(9).tolist()
    [[300.0, 0.0, 400.0], [0.0, 300.0, 299.0], [0.0, 0.0, 1.0]]
    """
    focal = (camera.height / 2.0) / camera.tan_half_fov
    cx = camera.width / 2.0 - sample_offset[0] - OPENCV_OFFSET
    cy = camera.height / 2.0 - sample_offset[1] - OPENCV_OFFSET
    return np.array([[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]])


def optical_pose_of(camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """(rotation, translation) of the camera's optical frame in ``map``.

    The rotation's columns are the optical frame's axes in ``map``: x right, y down
    (against the image's up), z forward; the translation is the eye.
    """
    right, up, forward = camera.axes()
    return np.column_stack([right, -up, forward]), np.asarray(camera.eye, float)


def _frozen(array: ArrayLike) -> np.ndarray:
    array = np.array(array, dtype=float)  # a private copy
    array.setflags(write=False)
    return array


def _batch(values: ArrayLike, width: int, what: str) -> tuple[np.ndarray, bool]:
    """``values`` as an (N, width) float array, and whether a single (width,) row was given."""
    array = np.asarray(values, float)
    single = array.ndim == 1
    array = np.atleast_2d(array)
    if array.ndim != 2 or array.shape[1] != width:
        raise ValueError(f'{what}: expected shape ({width},) or (N, {width}), got {np.shape(values)}')
    return array, single


@dataclass(frozen=True, eq=False)
class CameraModel:
    """A pinhole camera with OpenCV lens distortion, posed in ``map``.

    :param K: 3x3 intrinsics, OpenCV convention (skew is ignored, as OpenCV does).
    :param D: distortion coefficients, OpenCV's order (plumb_bob 5, rational_polynomial 8;
        () for none; see :data:`DISTORTION_LENGTHS`).
    :param width: image width in pixels.
    :param height: image height in pixels.
    :param rotation: 3x3, ``map`` <- optical frame (columns: optical x right, y down,
        z forward, in ``map``).
    :param translation: (3,), the optical centre in ``map``.

    Equality is identity (``eq=False``): the fields are numpy arrays.
    """

    K: np.ndarray
    D: tuple[float, ...]
    width: int
    height: int
    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        K = _frozen(self.K)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f'CameraModel: K: expected a finite 3x3 matrix with fx, fy > 0, got {self.K!r}')
        D = tuple(float(c) for c in np.ravel(self.D))
        if len(D) not in DISTORTION_LENGTHS or not all(math.isfinite(c) for c in D):
            raise ValueError(
                f'CameraModel: D: expected {", ".join(map(str, DISTORTION_LENGTHS))} finite coefficients '
                f'(OpenCV order), got {len(D)}: {list(D)}'
            )
        for name in ('width', 'height'):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value <= 0:
                raise ValueError(f'CameraModel: {name}: expected a positive integer, got {value!r}')
            object.__setattr__(self, name, int(value))
        rotation = _frozen(self.rotation)
        if (
            rotation.shape != (3, 3)
            or not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-6)
            or np.linalg.det(rotation) <= 0
        ):
            raise ValueError(f'CameraModel: rotation: expected a 3x3 rotation matrix, got {self.rotation!r}')
        translation = _frozen(np.ravel(self.translation))
        if translation.shape != (3,) or not np.all(np.isfinite(translation)):
            raise ValueError(f'CameraModel: translation: expected 3 finite numbers, got {self.translation!r}')
        object.__setattr__(self, 'K', K)
        object.__setattr__(self, 'D', D)
        object.__setattr__(self, 'rotation', rotation)
        object.__setattr__(self, 'translation', translation)

    @classmethod
    def from_pinhole(
        cls,
        camera: PinholeCamera,
        sample_offset: tuple[float, float] = (0.0, 0.0),
        distortion: tuple[float, ...] = (),
    ) -> CameraModel:
        """The model of the images ``camera`` renders (see :func:`intrinsics_of` for
        ``sample_offset``), seen through a lens with ``distortion``."""
        rotation, translation = optical_pose_of(camera)
        return cls(
            K=intrinsics_of(camera, sample_offset),
            D=tuple(distortion),
            width=camera.width,
            height=camera.height,
            rotation=rotation,
            translation=translation,
        )

    @property
    def eye(self) -> tuple[float, float, float]:
        """The optical centre in ``map``."""
        x, y, z = (float(c) for c in self.translation)
        return x, y, z

    @property
    def distorted(self) -> bool:
        """Whether the lens distorts (any non-zero coefficient)."""
        return any(self.D)

    def with_pose(self, rotation: np.ndarray, translation: np.ndarray) -> CameraModel:
        """The same camera with its optical frame at (``rotation``, ``translation``) in ``map``."""
        return replace(self, rotation=rotation, translation=translation)

    # -- lens ----------------------------------------------------------------------------------
    def _distort(self, normalized: np.ndarray, jacobian: bool = False):
        """Normalized image coordinates (N, 2) -> OpenCV pixel coordinates (N, 2), and with
        ``jacobian`` their derivatives (N, 2, 2): [d(u, v) / d(x, y)].

        OpenCV's model (``cv2.projectPoints``; the tests hold the two together), in numpy:
        some thirty times faster, which the many pixels of a :class:`drvs.sim.lens.Lens` need.
        """
        k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = (*self.D, *(0.0,) * (12 - len(self.D)))
        x, y = normalized[:, 0], normalized[:, 1]
        with np.errstate(all='ignore'):
            r2 = x * x + y * y
            numerator = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            denominator = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
            radial = numerator / denominator
            xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) + r2 * (s1 + s2 * r2)
            yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y + r2 * (s3 + s4 * r2)
            fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
            pixels = np.c_[fx * xd + cx, fy * yd + cy]
            if not jacobian:
                return pixels
            d_numerator = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
            d_denominator = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
            d_radial = 2.0 * (d_numerator * denominator - numerator * d_denominator) / denominator**2
            prism_x = 2.0 * (s1 + 2.0 * s2 * r2)
            prism_y = 2.0 * (s3 + 2.0 * s4 * r2)
            derivatives = np.empty((len(x), 2, 2))
            derivatives[:, 0, 0] = fx * (
                radial + x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x + prism_x * x
            )
            derivatives[:, 0, 1] = fx * (x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y + prism_x * y)
            derivatives[:, 1, 0] = fy * (x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y + prism_y * x)
            derivatives[:, 1, 1] = fy * (
                radial + y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x + prism_y * y
            )
        return pixels, derivatives

    def _newton(self, targets: np.ndarray, start: np.ndarray) -> np.ndarray:
        """Damped Newton on distort(x) = target from ``start`` (both (N, 2)); NaN where it fails."""
        x = start.copy()
        error = np.hypot(*(self._distort(x) - targets).T)
        alive = np.flatnonzero(np.isfinite(error) & (error > _NEWTON_GOAL))
        for _ in range(_NEWTON_ITERATIONS):
            if len(alive) == 0:
                break
            value, derivatives = self._distort(x[alive], jacobian=True)
            residual = value - targets[alive]
            (a, b), (c, d) = derivatives[:, 0].T, derivatives[:, 1].T
            with np.errstate(all='ignore'):  # a singular Jacobian gives a non-finite step: stuck
                determinant = a * d - b * c
                step = np.c_[d * residual[:, 0] - b * residual[:, 1], a * residual[:, 1] - c * residual[:, 0]]
                step /= determinant[:, None]
            trying = np.isfinite(step).all(axis=1)
            improved = np.zeros(len(alive), bool)
            scale = 1.0
            for _ in range(_NEWTON_HALVINGS):
                rows = np.flatnonzero(trying & ~improved)
                if len(rows) == 0:
                    break
                trial = x[alive[rows]] - scale * step[rows]
                trial_error = np.hypot(*(self._distort(trial) - targets[alive[rows]]).T)
                better = trial_error < error[alive[rows]]
                x[alive[rows[better]]] = trial[better]
                error[alive[rows[better]]] = trial_error[better]
                improved[rows[better]] = True
                scale /= 2.0
            alive = alive[improved & (error[alive] > _NEWTON_GOAL)]  # drop the converged and the stuck
        x[~(error <= UNDISTORT_TOLERANCE)] = np.nan
        return x

    def undistort(self, pixels: ArrayLike) -> np.ndarray:
        """Normalized image coordinates (x/z, y/z) in the optical frame of pixel position(s) (u, v).

        Shape (2,) for one pixel, (N, 2) for (N, 2). Each result distorts back to within
        1e-9 px of its pixel; NaN where none is found to :data:`UNDISTORT_TOLERANCE` (the lens
        model cannot be inverted there; see the module docstring).
        """
        pixels, single = _batch(pixels, 2, 'CameraModel: pixels')
        targets = pixels - OPENCV_OFFSET
        if len(targets) == 0:
            return np.empty((0, 2))
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        naive = np.c_[(targets[:, 0] - cx) / fx, (targets[:, 1] - cy) / fy]
        if not self.distorted:
            return naive[0] if single else naive
        import cv2  # here: world_sim and the server use this module's poses, not OpenCV (0.4 s to import)

        normalized = cv2.undistortPointsIter(
            targets.reshape(-1, 1, 2), self.K, np.asarray(self.D, float), None, None, _CV_CRITERIA
        ).reshape(-1, 2)
        error = np.hypot(*(self._distort(normalized) - targets).T)
        failed = np.flatnonzero(~(error <= _NEWTON_GOAL))
        if len(failed):
            # Start from the better of OpenCV's answer and the undistorted-as-is position.
            naive_error = np.hypot(*(self._distort(naive[failed]) - targets[failed]).T)
            start = np.where((naive_error < error[failed])[:, None], naive[failed], normalized[failed])
            normalized[failed] = self._newton(targets[failed], start)
        return normalized[0] if single else normalized

    # -- rays ----------------------------------------------------------------------------------
    def _directions(self, pixels: ArrayLike) -> tuple[np.ndarray, bool]:
        """Ray directions in ``map`` scaled so their component along the optical axis is 1."""
        normalized = self.undistort(pixels)
        single = normalized.ndim == 1
        normalized = np.atleast_2d(normalized)
        optical = np.c_[normalized, np.ones(len(normalized))]
        return optical @ self.rotation.T, single

    def project_pixel_to_3d_ray(self, pixels: ArrayLike) -> np.ndarray:
        """Unit direction(s) in ``map`` of the ray(s) from the optical centre through pixel(s) (u, v)."""
        directions, single = self._directions(pixels)
        directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
        return directions[0] if single else directions

    def pixel_to_point(self, pixels: ArrayLike, depth: ArrayLike) -> np.ndarray:
        """3D point(s) in ``map`` seen at pixel(s) (u, v) at ``depth`` metres along the optical z axis
        (a ROS depth image's value, REP-118)."""
        directions, single = self._directions(pixels)
        points = self.translation[None, :] + directions * np.reshape(np.asarray(depth, float), (-1, 1))
        return points[0] if single else points

    def pixel_to_floor(self, pixels: ArrayLike, z: float = 0.0) -> np.ndarray:
        """Where the ray(s) through (u, v) meet the horizontal plane at height ``z`` (NaN if never)."""
        directions, single = self._directions(pixels)
        with np.errstate(divide='ignore', invalid='ignore'):
            scale = (z - self.translation[2]) / directions[:, 2]
        scale[~(scale > 0) | ~np.isfinite(scale)] = np.nan
        points = self.translation[None, :] + directions * scale[:, None]
        return points[0] if single else points

    def project_3d_to_pixel(self, points: ArrayLike) -> np.ndarray:
        """(u, v) of 3D point(s) in ``map``, through the lens: shape (2,) for one point, (N, 2) for (N, 3).

        Points behind the camera (or in its optical centre's plane) have no image: NaN.
        """
        points, single = _batch(points, 3, 'CameraModel: points')
        optical = (points - self.translation[None, :]) @ self.rotation
        depth = optical[:, 2]
        in_front = depth > 0
        pixels = np.full((len(points), 2), np.nan)
        if in_front.any():
            normalized = optical[in_front, :2] / depth[in_front, None]
            pixels[in_front] = self._distort(normalized) + OPENCV_OFFSET
        return pixels[0] if single else pixels

    # -- field of view -------------------------------------------------------------------------
    def floor_footprint(
        self,
        max_range: float,
        floor_size: tuple[float, float] | None = None,
        samples_per_edge: int = 32,
    ) -> list[tuple[float, float]]:
        """The floor area (z = 0) the image sees within ``max_range`` metres of the optical
        centre, counter-clockwise; [] if it sees none of it.

        The image border is sampled (``samples_per_edge`` points per side) and undistorted, so
        a curved lens border is followed. Rays are kept where they point down steeply enough
        to meet the floor within :data:`FOOTPRINT_RANGE_FACTOR` x ``max_range`` (a straight
        line in the normalized image plane, whose map to the floor is a homography, so edges
        stay straight); the result is cut to the disc of floor points within ``max_range``
        (a 64-gon inscribed in the circle) and, with ``floor_size``, to the floor rectangle
        from (0, 0). Should the seen floor come apart in pieces (a strongly curved border cut
        by the horizon), their convex hull is returned.
        """
        from shapely.geometry import Polygon, box
        from shapely.geometry.polygon import orient
        from shapely.ops import unary_union

        if isinstance(max_range, bool) or not (math.isfinite(max_range) and max_range > 0):
            raise ValueError(
                f'CameraModel.floor_footprint: max_range: expected a positive finite number of metres, '
                f'got {max_range!r}'
            )
        height = float(self.translation[2])
        if height <= 0 or max_range <= height:
            return []
        per_edge = samples_per_edge if self.distorted else 1  # without distortion the edges are straight
        steps = np.arange(per_edge) / per_edge
        w, h = float(self.width), float(self.height)
        border = np.concatenate(
            [
                np.c_[steps * w, np.zeros_like(steps)],
                np.c_[np.full_like(steps, w), steps * h],
                np.c_[w - steps * w, np.full_like(steps, h)],
                np.c_[np.zeros_like(steps), h - steps * h],
            ]
        )
        normalized = self.undistort(border)
        normalized = normalized[np.isfinite(normalized).all(axis=1)]
        if len(normalized) < 3:
            return []
        image = Polygon(normalized).buffer(0)
        if image.is_empty:
            return []
        # The map z of the ray through normalized (x, y) is a*x + b*y + c (row 3 of the rotation).
        # Keep rays with z <= -limit: they meet the floor at most height * |ray| / limit away.
        a, b, c = self.rotation[2]
        limit = height / (FOOTPRINT_RANGE_FACTOR * max_range)
        down = _half_plane(image.bounds, a, b, c + limit)
        if down is None:
            return []
        seen = image.intersection(down)
        parts = [seen] if seen.geom_type == 'Polygon' else list(getattr(seen, 'geoms', []))
        floor_parts = []
        for part in parts:
            if part.geom_type != 'Polygon' or part.is_empty or part.area <= 0:
                continue
            vertices = np.asarray(part.exterior.coords)[:-1]
            rays = np.c_[vertices, np.ones(len(vertices))] @ self.rotation.T
            on_floor = self.translation[None, :2] + rays[:, :2] * (-height / rays[:, 2])[:, None]
            floor_parts.append(Polygon(on_floor).buffer(0))
        if not floor_parts:
            return []
        radius = math.sqrt(max_range**2 - height**2)
        angles = np.arange(FOOTPRINT_CIRCLE_SEGMENTS) * (2 * math.pi / FOOTPRINT_CIRCLE_SEGMENTS)
        disc = Polygon(self.translation[None, :2] + radius * np.c_[np.cos(angles), np.sin(angles)])
        shape = unary_union(floor_parts).intersection(disc)
        if floor_size is not None:
            shape = shape.intersection(box(0.0, 0.0, floor_size[0], floor_size[1]))
        if shape.is_empty or shape.area <= 0:
            return []
        if shape.geom_type != 'Polygon':
            shape = shape.convex_hull
        return [(float(x), float(y)) for x, y in orient(shape, sign=1.0).exterior.coords[:-1]]


def _half_plane(bounds: Sequence[float], a: float, b: float, c: float) -> Polygon | None:
    """The part of the rectangle ``bounds`` (grown a little) where a*x + b*y + c <= 0, or None."""
    from shapely.geometry import Polygon

    min_x, min_y, max_x, max_y = bounds
    margin = 1.0 + max(max_x - min_x, max_y - min_y)
    corners = [
        (min_x - margin, min_y - margin),
        (max_x + margin, min_y - margin),
        (max_x + margin, max_y + margin),
        (min_x - margin, max_y + margin),
    ]
    values = [a * x + b * y + c for x, y in corners]
    kept: list[tuple[float, ...]] = []
    for i, corner in enumerate(corners):
        j = (i + 1) % len(corners)
        if values[i] <= 0:
            kept.append(corner)
        if (values[i] <= 0) != (values[j] <= 0):
            t = values[i] / (values[i] - values[j])
            kept.append(tuple(np.add(corner, t * np.subtract(corners[j], corner))))
    if len(kept) < 3:
        return None
    shape = Polygon(kept)
    return shape if shape.area > 0 else None
