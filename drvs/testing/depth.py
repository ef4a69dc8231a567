"""Synthetic depth frames for tests and the bench: boxes standing on the floor, ray-cast exactly.

:func:`depth_frame` gives what an ideal depth camera registered to its colour image sees of a
few axis-aligned boxes (no renderer, no noise: add :mod:`drvs.sim.depth_noise` for that).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drvs.vision.camera import PinholeCamera
from drvs.vision.frame import Frame

__all__ = ['Box', 'depth_frame']

FLOOR_GREY = 200
BOX_GREY = 60


@dataclass(frozen=True)
class Box:
    """A box standing on the floor: its footprint's centre (x, y), size (x, y, z) in metres,
    and how its pixels show in the colour image (``grey``); optionally lifted off the floor by
    ``bottom`` metres (a shelf)."""

    centre: tuple[float, float]
    size: tuple[float, float, float]
    grey: int = BOX_GREY
    bottom: float = 0.0

    @property
    def top(self) -> float:
        return self.bottom + self.size[2]

    def footprint(self) -> list[tuple[float, float]]:
        (cx, cy), (sx, sy, _) = self.centre, self.size
        return [
            (cx - sx / 2, cy - sy / 2),
            (cx + sx / 2, cy - sy / 2),
            (cx + sx / 2, cy + sy / 2),
            (cx - sx / 2, cy + sy / 2),
        ]


def depth_frame(camera: PinholeCamera, boxes: Sequence[Box], stamp: float = 0.0) -> Frame:
    """The ideal view of ``boxes`` on a floor (z = 0) from ``camera``: grey RGB, depth along the
    optical axis in metres (0 where a ray meets nothing), at the pixel centres (no sample offset)."""
    rows, cols = np.mgrid[0 : camera.height, 0 : camera.width]
    pixels = np.c_[cols.ravel() + 0.5, rows.ravel() + 0.5]
    eye = np.asarray(camera.eye, float)
    rays = camera.pixel_to_point(pixels, np.ones(len(pixels))) - eye  # 1 along the optical axis
    with np.errstate(divide='ignore', invalid='ignore'):
        nearest = -eye[2] / rays[:, 2]
    nearest[~(nearest > 0)] = np.inf
    grey = np.full(len(pixels), FLOOR_GREY, np.uint8)
    for box in boxes:
        low = np.array([box.centre[0] - box.size[0] / 2, box.centre[1] - box.size[1] / 2, box.bottom])
        high = np.array([box.centre[0] + box.size[0] / 2, box.centre[1] + box.size[1] / 2, box.top])
        with np.errstate(divide='ignore', invalid='ignore'):
            t1 = (low[None, :] - eye[None, :]) / rays
            t2 = (high[None, :] - eye[None, :]) / rays
        t_near = np.nanmax(np.minimum(t1, t2), axis=1)
        t_far = np.nanmin(np.maximum(t1, t2), axis=1)
        hit = (t_near <= t_far) & (t_near > 0) & (t_near < nearest)
        nearest[hit] = t_near[hit]
        grey[hit] = box.grey
    depth = np.where(np.isfinite(nearest), nearest, 0.0).reshape(camera.height, camera.width)
    rgb = np.repeat(grey.reshape(camera.height, camera.width, 1), 3, axis=2)
    return Frame(rgb=rgb, depth=depth.astype(np.float32), camera=camera, stamp=stamp)
