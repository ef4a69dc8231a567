"""A captured view, the unit a vision system works on: colour, depth, camera model and stamp.

Any frame source makes these — the simulation's renderer (:mod:`drvs.sim.scene`), a camera
topic (:mod:`drvs.ros.frame_sources`) — and the pipeline (:mod:`drvs.vision.pipeline`) reads them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from drvs.vision.camera import PinholeCamera

if TYPE_CHECKING:
    from drvs.vision.optics import CameraModel


@dataclass(frozen=True)
class Frame:
    """One captured view: RGB (H, W, 3) uint8, depth along the optical axis (H, W) metres
    (None for a camera without depth), the camera model it was taken with
    (:class:`PinholeCamera` or :class:`drvs.vision.optics.CameraModel`), when (seconds: the
    moment it shows) and ``sample_offset``: add it to array-pixel coordinates to get
    the camera model's (u, v) of what they show."""

    rgb: np.ndarray
    depth: np.ndarray | None
    camera: PinholeCamera | CameraModel
    stamp: float
    sample_offset: tuple[float, float] = (0.0, 0.0)

    def to_camera(self, pixels: ArrayLike) -> np.ndarray:
        """Array-pixel (u, v) positions -> the camera model's (u, v)."""
        return np.asarray(pixels, float) + np.asarray(self.sample_offset)
