"""The pinhole camera model of an overhead vision system: world point <-> pixel, and its floor footprint.

It is the model PyBullet renders with (``computeViewMatrix`` + ``computeProjectionMatrixFOV``,
OpenGL conventions), with names like image_geometry's ``PinholeCameraModel``.

Pixel coordinates are continuous (u, v) = (column, row) with the origin at the
top-left corner of the image: pixel (row r, column c) covers [c, c+1] x [r, r+1],
so its centre is (c + 0.5, r + 0.5). Depth is the distance along the optical axis
(what PyBullet's depth buffer holds once converted with :func:`metric_depth`).

>>> camera = PinholeCamera(eye=(2.0, 1.0, 3.0), target=(2.0, 1.0, 0.0), fov_deg=60, width=800, height=600)
>>> [round(c, 6) for c in camera.project_3d_to_pixel((2.0, 1.0, 0.0))]
[400.0, 300.0]
>>> [round(c, 6) for c in camera.pixel_to_floor((400.0, 300.0))]
[2.0, 1.0, 0.0]
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import cached_property
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

DEFAULT_NEAR = 0.05
DEFAULT_FAR = 100.0


class CameraConfig(Protocol):
    """What :meth:`PinholeCamera.from_config` reads of a camera's configuration (a world file's
    :class:`drvs.sim.world.Camera` has it)."""

    @property
    def position(self) -> Sequence[float]: ...

    @property
    def target(self) -> Sequence[float]: ...

    @property
    def up(self) -> Sequence[float]: ...

    @property
    def fov_deg(self) -> float: ...

    @property
    def resolution(self) -> tuple[int, int]: ...


def _vector3(values: Sequence[float]) -> tuple[float, float, float]:
    x, y, z = values
    return x, y, z


@dataclass(frozen=True)
class PinholeCamera:
    """A perspective camera at ``eye`` looking at ``target``; image rows run along ``up``.

    ``fov_deg`` is the vertical field of view; the aspect ratio is ``width / height``.
    """

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    fov_deg: float
    width: int
    height: int
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    near: float = DEFAULT_NEAR
    far: float = DEFAULT_FAR

    @classmethod
    def from_config(cls, camera: CameraConfig, resolution: tuple[int, int] | None = None) -> PinholeCamera:
        """The model of a world file's ``vision_systems`` entry (:class:`drvs.sim.world.Camera`)."""
        width, height = resolution or camera.resolution
        return cls(
            eye=_vector3(camera.position),
            target=_vector3(camera.target),
            fov_deg=camera.fov_deg,
            width=int(width),
            height=int(height),
            up=_vector3(camera.up),
        )

    def moved_to(self, x: float, y: float) -> PinholeCamera:
        """The same camera on a mount moved to (x, y): height, viewing direction and optics kept."""
        dx, dy = x - self.eye[0], y - self.eye[1]
        return replace(
            self,
            eye=(x, y, self.eye[2]),
            target=(self.target[0] + dx, self.target[1] + dy, self.target[2]),
        )

    # -- frame ---------------------------------------------------------------------------------
    @property
    def aspect(self) -> float:
        return self.width / self.height

    @property
    def tan_half_fov(self) -> float:
        return math.tan(math.radians(self.fov_deg) / 2.0)

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(right, image-up, forward) unit vectors in ``map``, as gluLookAt builds them (read-only)."""
        return self._axes

    @cached_property
    def _axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # Once per camera: every projection needs them, and np.cross costs more than the projection.
        eye, target = np.asarray(self.eye, float), np.asarray(self.target, float)
        forward = target - eye
        norm = np.linalg.norm(forward)
        if norm == 0:
            raise ValueError('camera: target equals eye; no viewing direction')
        forward /= norm
        right = np.cross(forward, np.asarray(self.up, float))
        norm = np.linalg.norm(right)
        if norm < 1e-9:
            raise ValueError('camera: up is parallel to the viewing direction')
        right /= norm
        axes = (right, np.cross(right, forward), forward)
        for axis in axes:
            axis.setflags(write=False)
        return axes

    # -- projections ---------------------------------------------------------------------------
    def project_3d_to_pixel(self, points: ArrayLike) -> np.ndarray:
        """(u, v) of 3D point(s) in ``map``: shape (2,) for one point, (N, 2) for (N, 3).

        Points behind the camera have no image: their (u, v) are NaN.
        """
        points = np.asarray(points, float)
        single = points.ndim == 1
        points = np.atleast_2d(points)
        right, up, forward = self.axes()
        relative = points - np.asarray(self.eye, float)
        depth = relative @ forward
        with np.errstate(divide='ignore', invalid='ignore'):
            x_ndc = (relative @ right) / (depth * self.tan_half_fov * self.aspect)
            y_ndc = (relative @ up) / (depth * self.tan_half_fov)
        pixels = np.stack([(x_ndc + 1.0) * self.width / 2.0, (1.0 - y_ndc) * self.height / 2.0], axis=1)
        pixels[depth <= 0] = np.nan
        return pixels[0] if single else pixels

    def _directions(self, pixels: ArrayLike) -> tuple[np.ndarray, bool]:
        """Ray directions scaled so their component along the optical axis is 1."""
        pixels = np.asarray(pixels, float)
        single = pixels.ndim == 1
        pixels = np.atleast_2d(pixels)
        right, up, forward = self.axes()
        x_ndc = 2.0 * pixels[:, 0] / self.width - 1.0
        y_ndc = 1.0 - 2.0 * pixels[:, 1] / self.height
        t = self.tan_half_fov
        directions = forward[None, :] + np.outer(x_ndc * t * self.aspect, right) + np.outer(y_ndc * t, up)
        return directions, single

    def project_pixel_to_3d_ray(self, pixels: ArrayLike) -> np.ndarray:
        """Unit direction(s) in ``map`` of the ray(s) from ``eye`` through pixel position(s) (u, v)."""
        directions, single = self._directions(pixels)
        directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
        return directions[0] if single else directions

    def pixel_to_point(self, pixels: ArrayLike, depth: ArrayLike) -> np.ndarray:
        """3D point(s) seen at pixel position(s) (u, v) at ``depth`` metres along the optical axis."""
        directions, single = self._directions(pixels)
        points = np.asarray(self.eye, float)[None, :] + directions * np.reshape(depth, (-1, 1))
        return points[0] if single else points

    def pixel_to_floor(self, pixels: ArrayLike, z: float = 0.0) -> np.ndarray:
        """Where the ray(s) through (u, v) meet the horizontal plane at height ``z`` (NaN if never)."""
        directions, single = self._directions(pixels)
        with np.errstate(divide='ignore', invalid='ignore'):
            scale = (z - self.eye[2]) / directions[:, 2]
        scale[~(scale > 0)] = np.nan
        points = np.asarray(self.eye, float)[None, :] + directions * scale[:, None]
        return points[0] if single else points

    def metric_depth(self, depth_buffer: np.ndarray) -> np.ndarray:
        """PyBullet/OpenGL depth-buffer values in [0, 1] -> metres along the optical axis."""
        buffer = np.asarray(depth_buffer, np.float64)
        return self.far * self.near / (self.far - (self.far - self.near) * buffer)

    # -- field of view -------------------------------------------------------------------------
    def floor_footprint(self, floor_size: tuple[float, float] | None = None) -> list[tuple[float, float]]:
        """The floor area (z = 0) the camera sees, counter-clockwise; [] if it sees none of it.

        Rays that would meet the floor beyond ``far`` (towards the horizon) are cut
        off there. With ``floor_size`` the area is clipped to the floor rectangle
        from (0, 0).
        """
        from shapely.geometry import Polygon, box
        from shapely.geometry.polygon import orient

        corners = [(0.0, 0.0), (self.width, 0.0), (self.width, self.height), (0.0, self.height)]
        height = self.eye[2]
        if height <= 0:
            return []
        directions, _ = self._directions(corners)
        # A ray meets the floor within `far` iff -direction_z >= height / far: a half-plane in
        # the image (direction is affine in (u, v)), so clip the image rectangle by it.
        limit = height / self.far
        values = [-d[2] - limit for d in directions]
        kept: list[tuple[float, ...]] = []
        for i, corner in enumerate(corners):
            j = (i + 1) % len(corners)
            a, b = values[i], values[j]
            if a >= 0:
                kept.append(corner)
            if (a >= 0) != (b >= 0):
                t = a / (a - b)
                kept.append(tuple(np.add(corner, t * np.subtract(corners[j], corner))))
        if len(kept) < 3:
            return []
        floor_points = self.pixel_to_floor(kept)[:, :2]
        if not np.all(np.isfinite(floor_points)):
            return []
        shape = Polygon(floor_points).buffer(0)
        if floor_size is not None:
            shape = shape.intersection(box(0.0, 0.0, floor_size[0], floor_size[1]))
        if shape.is_empty or shape.area <= 0 or shape.geom_type != 'Polygon':
            return []
        return [(float(x), float(y)) for x, y in orient(shape, sign=1.0).exterior.coords[:-1]]
