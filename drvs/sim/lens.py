"""Rendering through a lens: the simulation's frames as a camera with radial/tangential distortion takes them.

:class:`Lens` remaps one ideal PyBullet render of a larger canvas into the distorted image
of ``camera.width`` x ``camera.height``; :attr:`Lens.model` describes the output (the
camera's ``K``, the lens's ``D``), as the simulated camera publishes it in its CameraInfo.
How: docs/design.md ("Vision systems"); who uses it: docs/nodes/sim_camera.md.
"""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np

from drvs.sim.scene import TINY_RENDERER_SAMPLE
from drvs.vision.camera import PinholeCamera
from drvs.vision.frame import Frame
from drvs.vision.optics import OPENCV_OFFSET, CameraModel, optical_pose_of

MAX_CANVAS = 4096
"""Pixels per side: the largest canvas a lens asks the renderer for."""

MARGIN = 2
"""Pixels of canvas beyond the outermost undistorted position (bilinear sampling reads one more)."""

BORDER_SAMPLES = 64
"""Points per image edge undistorted to size the canvas before the full maps are computed."""


class Lens:
    """Renders what a PinholeCamera with distortion D sees: an ideal render on a padded canvas,
    remapped with cv2.

    :param camera: the camera whose images come out (size, pose, focal length).
    :param distortion: OpenCV coefficients (plumb_bob: k1, k2, p1, p2, k3); () or all zero: none.
    :param sample_offset: the renderer's (:data:`drvs.sim.scene.TINY_RENDERER_SAMPLE`); the canvas
        is rendered by the same renderer, so it applies there too.
    :param interpolation: how colours are sampled (``cv2.INTER_LINEAR``; ``cv2.INTER_NEAREST``
        keeps every colour a body's own).
    :raises ValueError: if the distortion cannot be undone over the image, or needs a canvas
        larger than :data:`MAX_CANVAS`.

    Attributes: ``canvas`` (the padded :class:`PinholeCamera` to render; ``camera`` itself
    without distortion), ``padding`` ((x, y) pixels added on each side), ``model`` (the
    :class:`CameraModel` of the output images).
    """

    def __init__(
        self,
        camera: PinholeCamera,
        distortion: tuple[float, ...] = (),
        sample_offset: tuple[float, float] = TINY_RENDERER_SAMPLE,
        interpolation: int = cv2.INTER_LINEAR,
    ):
        self.camera = camera
        self.sample_offset = (sample_offset[0], sample_offset[1])
        self.interpolation = interpolation
        self.model = CameraModel.from_pinhole(camera, self.sample_offset, tuple(distortion))
        self.canvas = camera
        self.padding = (0, 0)
        self._maps: tuple[np.ndarray, np.ndarray] | None = None
        if not self.model.distorted:
            return
        width, height = camera.width, camera.height
        # Size the canvas from the border first: an impossible lens fails fast, before the full maps.
        steps = np.linspace(0.0, 1.0, BORDER_SAMPLES + 1)
        border = np.concatenate(
            [
                np.c_[steps * width, np.zeros_like(steps)],
                np.c_[steps * width, np.full_like(steps, height)],
                np.c_[np.zeros_like(steps), steps * height],
                np.c_[np.full_like(steps, width), steps * height],
            ]
        )
        self._check_size(self._padding(self._ideal(border, 'border points')))
        rows, columns = np.mgrid[0:height, 0:width]
        centres = np.c_[columns.ravel(), rows.ravel()] + OPENCV_OFFSET  # DRVS coordinates
        ideal = self._ideal(centres, 'pixels')
        pad_x, pad_y = self.padding = self._padding(ideal)
        self._check_size(self.padding)
        canvas_height = height + 2 * pad_y
        fov = 2.0 * math.degrees(math.atan(camera.tan_half_fov * canvas_height / height))
        self.canvas = replace(camera, fov_deg=fov, width=width + 2 * pad_x, height=canvas_height)
        # The canvas's K is the camera's with the principal point moved by the padding (same
        # focal length, same sample offset), so a canvas OpenCV position is the ideal one + padding.
        map_x = (ideal[:, 0] + pad_x).reshape(height, width).astype(np.float32)
        map_y = (ideal[:, 1] + pad_y).reshape(height, width).astype(np.float32)
        self._maps = (map_x, map_y)

    def _ideal(self, pixels: np.ndarray, what: str) -> np.ndarray:
        """OpenCV positions in the undistorted image (the unpadded camera's K) of output ``pixels``."""
        normalized = self.model.undistort(pixels)
        failed = ~np.isfinite(normalized).all(axis=1)
        if failed.any():
            raise ValueError(
                f'Lens: distortion {list(self.model.D)} cannot be undone at {int(failed.sum())} of '
                f'{len(pixels)} {what} of the {self.camera.width}x{self.camera.height} image (first at '
                f'{tuple(float(round(c, 1)) for c in pixels[failed][0])}): the lens model folds over there'
            )
        K = self.model.K
        return np.c_[normalized[:, 0] * K[0, 0] + K[0, 2], normalized[:, 1] * K[1, 1] + K[1, 2]]

    def _padding(self, ideal: np.ndarray) -> tuple[int, int]:
        """Pixels to add on each side so every ``ideal`` position lies MARGIN inside the canvas."""
        low = -ideal.min(axis=0)
        high = ideal.max(axis=0) - (self.camera.width - 1, self.camera.height - 1)
        over = np.maximum(np.maximum(low, high), 0.0)
        return int(math.ceil(over[0])) + MARGIN, int(math.ceil(over[1])) + MARGIN

    def _check_size(self, padding: tuple[int, int]) -> None:
        width = self.camera.width + 2 * padding[0]
        height = self.camera.height + 2 * padding[1]
        if max(width, height) > MAX_CANVAS:
            raise ValueError(
                f'Lens: distortion {list(self.model.D)} needs a {width}x{height} canvas to render the '
                f'{self.camera.width}x{self.camera.height} image; the limit is {MAX_CANVAS} pixels per '
                'side (the distortion is too strong for this field of view and resolution)'
            )

    @property
    def identity(self) -> bool:
        """Whether the lens leaves frames as they are (no distortion)."""
        return self._maps is None

    def apply(self, frame: Frame) -> Frame:
        """The view through the lens of ``frame``, an ideal render of :attr:`canvas`.

        The canvas may have been moved since (``canvas.moved_to``, a moving mount): the
        maps depend on the optics only, and the result takes the pose of ``frame.camera``.

        Returns a :class:`Frame` whose ``camera`` and ``sample_offset`` describe its pixels,
        as every Frame's do: without distortion ``frame`` itself (its PinholeCamera and the
        renderer's sample offset); with distortion a ``camera.width`` x ``camera.height``
        frame whose ``camera`` is :attr:`model` at the frame's pose (a
        :class:`CameraModel`, which has the methods of :class:`PinholeCamera` that
        :mod:`drvs.vision.pipeline` uses) and whose ``sample_offset`` is (0, 0): ``model``'s ``K``
        already holds the renderer's. RGB is sampled with :attr:`interpolation`, depth
        (metres along the optical axis, the same for canvas and output) at the nearest pixel.

        :raises ValueError: if ``frame`` is not a render of the canvas's optics.
        """
        if self._maps is None:
            return frame
        camera = frame.camera
        expected = (self.canvas.width, self.canvas.height, self.canvas.fov_deg)
        got = (
            getattr(camera, 'width', None),
            getattr(camera, 'height', None),
            getattr(camera, 'fov_deg', None),
        )
        if (
            not isinstance(camera, PinholeCamera)
            or got != expected
            or frame.rgb.shape[:2] != (self.canvas.height, self.canvas.width)
        ):
            raise ValueError(
                f'Lens.apply: expected a frame rendered with the lens canvas ({self.canvas.width}x'
                f'{self.canvas.height}, fov {self.canvas.fov_deg:.6g} deg), got {frame.rgb.shape[1]}x'
                f'{frame.rgb.shape[0]} from {camera!r}'
            )
        map_x, map_y = self._maps
        rgb = cv2.remap(frame.rgb, map_x, map_y, self.interpolation, borderMode=cv2.BORDER_REPLICATE)
        depth = cv2.remap(frame.depth, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
        return Frame(
            rgb=rgb,
            depth=depth,
            camera=self.model.with_pose(*optical_pose_of(camera)),
            stamp=frame.stamp,
            sample_offset=(0.0, 0.0),
        )
