"""The depth a real structured-light or stereo sensor gives: error growing with the square of the
distance, and holes at depth edges and on dark or shiny surfaces.

:class:`DepthNoise` is a world file camera's ``depth_noise`` (worlds/README.md has the keys and
their defaults); :meth:`DepthNoise.apply` spoils a perfect depth image with a caller's seeded
random generator, so a run is repeatable. Pure numpy and OpenCV.

>>> import numpy as np
>>> noise = DepthNoise(error=0.0015)
>>> round(noise.sigma(3.0), 5)  # metres at 3 m
0.0135
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

__all__ = ['DepthNoise']


@dataclass(frozen=True)
class DepthNoise:
    """A depth sensor's imperfections.

    :param error: standard deviation of the depth at 1 m, metres; at distance d it is
        ``error * d**2`` (a structured-light or stereo sensor's error grows with the square of
        the distance: its disparity error is constant). 0.0015: a Kinect-class sensor.
    :param edge_jump: metres between neighbouring pixels' depths that make a depth edge.
    :param edge_width: pixels either side of a depth edge where the sensor may see nothing.
    :param edge_dropout: probability (0-1) that a pixel near a depth edge is a hole.
    :param dark_level: grey level (0-255) below which a surface is too dark to return the
        sensor's light.
    :param dark_dropout: probability that a pixel of a dark surface is a hole.
    :param shiny_dropout: probability that a pixel of a shiny surface (the caller's mask) is a hole.
    :param seed: seed of the random generator of a camera's frames (None: from its name).
    """

    error: float = 0.0015
    edge_jump: float = 0.05
    edge_width: int = 2
    edge_dropout: float = 0.8
    dark_level: int = 30
    dark_dropout: float = 0.9
    shiny_dropout: float = 0.9
    seed: int | None = None

    def generator(self, camera: str) -> np.random.Generator:
        """The random generator of camera ``camera``'s frames: seeded with :attr:`seed`, or from the
        camera's name, so that a run repeats and two cameras differ."""
        return np.random.default_rng(self.seed if self.seed is not None else zlib.crc32(camera.encode()))

    def sigma(self, distance: float | np.ndarray) -> float | np.ndarray:
        """The depth's standard deviation at ``distance`` metres."""
        return self.error * np.square(distance)

    def apply(
        self,
        depth: np.ndarray,
        rgb: np.ndarray | None,
        rng: np.random.Generator,
        shiny: np.ndarray | None = None,
    ) -> np.ndarray:
        """A noisy copy of ``depth`` ((H, W) metres along the optical axis; 0 or NaN: a hole):
        Gaussian error of :meth:`sigma`, and holes (0) at depth edges, on dark pixels of ``rgb``
        ((H, W, 3) uint8) and where ``shiny`` ((H, W) bool) is set."""
        import cv2

        depth = np.asarray(depth, np.float32)
        valid = np.isfinite(depth) & (depth > 0)
        clean = np.where(valid, depth, 0).astype(np.float32)
        sigma = np.float32(self.error) * clean * clean
        noisy = clean + rng.standard_normal(depth.shape, dtype=np.float32) * sigma
        holes = ~valid | (noisy <= 0)
        if self.edge_width > 0 and self.edge_dropout > 0:
            jump = np.zeros(depth.shape, bool)  # both pixels of each pair across an edge
            across = np.abs(np.diff(clean, axis=1)) > self.edge_jump
            jump[:, 1:] |= across
            jump[:, :-1] |= across
            across = np.abs(np.diff(clean, axis=0)) > self.edge_jump
            jump[1:, :] |= across
            jump[:-1, :] |= across
            side = 2 * self.edge_width - 1
            near_edge = cv2.dilate(jump.astype(np.uint8), np.ones((side, side), np.uint8)) > 0
            holes |= near_edge & (rng.random(depth.shape, dtype=np.float32) < self.edge_dropout)
        if rgb is not None and self.dark_dropout > 0:
            grey = np.asarray(rgb[..., :3], np.float32).mean(axis=2)
            holes |= (grey < self.dark_level) & (
                rng.random(depth.shape, dtype=np.float32) < self.dark_dropout
            )
        if shiny is not None and self.shiny_dropout > 0:
            holes |= shiny & (rng.random(depth.shape, dtype=np.float32) < self.shiny_dropout)
        noisy[holes] = 0.0
        return noisy
