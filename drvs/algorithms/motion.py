"""``motion[:MIN_AREA]``: the things that move in a fixed camera's view, by background subtraction.

Each connected region of at least MIN_AREA pixels (default :data:`DEFAULT_MIN_AREA`) that
differs from a model of the camera's background, learnt by OpenCV's MOG2 from the
camera's own frame stream (``streaming``: the vision system calls :meth:`Motion.observe`
with its frames). The stream contract, ghosts and limits: docs/design.md ("The built-in
algorithms").

>>> Motion().parse('250')
MotionParams(min_area=250.0)
>>> Motion().parse('').min_area == DEFAULT_MIN_AREA
True
"""

from __future__ import annotations

import logging
import math
import threading
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from drvs.algorithms.base import Algorithm, AlgorithmError, PixelObject, outlines_of_mask

if TYPE_CHECKING:
    from drvs.vision.frame import Frame

log = logging.getLogger('rosout.' + __name__)

DEFAULT_MIN_AREA = 100.0
"""Smallest moving region reported, pixels, when ``MIN_AREA`` is not given."""
STREAM_RATE = 5.0
"""Frames per second the stream is expected at (what the ghost times in seconds assume)."""
HISTORY = 20
"""Frames the background model remembers (its learning rate is 1 / HISTORY once warmed up)."""
BACKGROUND_RATIO = 0.5
"""A pixel's colour is background once the colours weightier than it in the model hold less
than this share of its weight.

MOG2's default (0.9) absorbs a thing within 3 frames of it covering a pixel, which
punches holes in a slowly walking human (its tall side covers the same pixels for
many frames); 0.5 keeps a pixel moving for ~14 frames, and makes a ghost last as long."""
VARIANCE_THRESHOLD = 16.0
"""Squared Mahalanobis distance beyond which a pixel differs from the model (MOG2's default)."""
WARM_UP = 3
"""Frames observed before :meth:`Motion.detect` reports anything."""
REMEMBERED = 4
"""Masks of the most recently observed frames kept for ``detect``."""
OPENING = 3
CLOSING = 5
"""Sizes (pixels) of the square kernels that clean the foreground mask."""
RING = 4
"""Width (pixels) of the band around a region that says what colour its surroundings are."""
FLOOR_TOLERANCE = 16
"""Largest difference per channel (0-255) between colours taken as the same floor colour."""
UNIFORM_SHARE = 0.9
"""Share of the band around a region within FLOOR_TOLERANCE of its median: a uniform floor."""


@dataclass(frozen=True)
class MotionParams:
    """``motion[:MIN_AREA]`` parsed: the smallest moving region reported, in pixels."""

    min_area: float = DEFAULT_MIN_AREA

    def format(self) -> str:
        return f'motion:{self.min_area:g}'


@dataclass(frozen=True)
class _Observed:
    stamp: float
    rgb: np.ndarray
    mask: np.ndarray


class Motion(Algorithm):
    """The motion algorithm for one camera: a background model learnt from its frame stream.

    :param epsilon: Douglas-Peucker tolerance (pixels) of the outlines.
    :param history: frames the model remembers (:data:`HISTORY`).
    :param warm_up: frames observed before anything is reported (:data:`WARM_UP`).
    """

    name = 'motion'
    syntax = 'motion[:MIN_AREA]'
    streaming = True

    def __init__(self, epsilon: float = 1.0, history: int = HISTORY, warm_up: int = WARM_UP):
        self.epsilon = epsilon
        self.history = history
        self.warm_up = warm_up
        self._lock = threading.Lock()  # guards the subtractor, the frame count and the masks
        self._subtractor: Any = None  # a cv2.BackgroundSubtractorMOG2 once a frame is seen
        self._shape: tuple[int, ...] | None = None
        self._frames = 0
        self._observed: deque[_Observed] = deque(maxlen=REMEMBERED)

    # -- parameters ----------------------------------------------------------------------------
    def parse(self, params: str) -> MotionParams:
        text = params.strip()
        if not text:
            return MotionParams()
        if ':' in text or ',' in text:
            raise AlgorithmError(f'algorithm: motion takes one optional field MIN_AREA, got {params!r}')
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value > 0):
            raise AlgorithmError(
                f'algorithm: motion MIN_AREA must be a positive number of pixels, got {text!r}'
            )
        return MotionParams(value)

    # -- the stream ----------------------------------------------------------------------------
    def observe(self, frame: Frame) -> None:
        """Learn one frame of the camera's stream; a frame already observed is not learnt again."""
        with self._lock:
            if self._find(frame) is not None:
                return
            image = self._image(frame, reset=True)
            mask = self._subtractor.apply(image, learningRate=-1)
            self._frames += 1
            self._observed.append(_Observed(frame.stamp, frame.rgb, mask))

    def reset(self) -> None:
        """Forget the background (the camera was moved): the next frames warm a new model up."""
        with self._lock:
            self._subtractor = None
            self._shape = None
            self._frames = 0
            self._observed.clear()

    @property
    def frames_observed(self) -> int:
        """Frames the current model has learnt."""
        return self._frames

    # -- detection -----------------------------------------------------------------------------
    def detect(self, frame: Frame, params: MotionParams) -> list[PixelObject]:
        """The moving regions of ``frame``: [] until the model has seen :data:`WARM_UP` frames."""
        with self._lock:
            if self._frames < self.warm_up:
                return []
            observed = self._find(frame)
            if observed is not None:
                mask = observed.mask
            else:
                image = self._image(frame, reset=False)
                if image is None:
                    return []
                mask = self._subtractor.apply(image, learningRate=0)
        # confidence: the share of a cleaned region's pixels that the model itself found changed.
        return outlines_of_mask(self.clean(frame.rgb, mask), params.min_area, self.epsilon, evidence=mask)

    def clean(self, rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """The foreground mask without speckle, holes between close parts, and ghosts on plain floors."""
        import cv2

        mask = np.where(mask > 0, 255, 0).astype(np.uint8)
        mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((OPENING, OPENING), np.uint8))
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((CLOSING, CLOSING), np.uint8))
        if without_ghosts(rgb, mask):
            mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((OPENING, OPENING), np.uint8))
        return mask

    # -- internals (called with the lock held) -----------------------------------------------------
    def _find(self, frame: Frame) -> _Observed | None:
        for observed in self._observed:
            if observed.rgb is frame.rgb and observed.stamp == frame.stamp:
                return observed
        return None

    def _image(self, frame: Frame, reset: bool) -> np.ndarray | None:
        """The frame as the subtractor takes it; a new model for a new image size when ``reset``."""
        import cv2

        image = np.ascontiguousarray(frame.rgb[..., :3], dtype=np.uint8)
        if self._shape != image.shape:
            if not reset:
                return None
            if self._shape is not None:
                log.warning(
                    'motion: frames changed size from %s to %s; learning the background anew',
                    self._shape,
                    image.shape,
                )
            self._subtractor = cv2.createBackgroundSubtractorMOG2(
                history=self.history, varThreshold=VARIANCE_THRESHOLD, detectShadows=False
            )
            self._subtractor.setBackgroundRatio(BACKGROUND_RATIO)
            self._shape = image.shape
            self._frames = 0
            self._observed.clear()
        return image


def without_ghosts(rgb: np.ndarray, mask: np.ndarray) -> bool:
    """Drop, in place, the pixels of each region of ``mask`` that show the colour of its plain surroundings.

    A region whose surrounding band (:data:`RING` pixels wide, outside every region)
    is one colour (:data:`UNIFORM_SHARE` of it within :data:`FLOOR_TOLERANCE` of its
    median) lies on a plain floor; its pixels of that colour differ only from an
    out-of-date background model: they are a ghost. Returns whether any pixel was dropped.
    """
    import cv2

    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    height, width = mask.shape
    foreground = mask > 0
    kernel = np.ones((2 * RING + 1, 2 * RING + 1), np.uint8)
    dropped = False
    for label in range(1, count):
        x, y, w, h = (int(v) for v in stats[label, :4])
        top, left = max(y - RING, 0), max(x - RING, 0)
        bottom, right = min(y + h + RING, height), min(x + w + RING, width)
        region = labels[top:bottom, left:right] == label
        band = cv2.dilate(region.astype(np.uint8), kernel).astype(bool) & ~foreground[top:bottom, left:right]
        surroundings = rgb[top:bottom, left:right][band].astype(np.int16)
        if len(surroundings) < RING * 4:
            continue
        floor = np.median(surroundings, axis=0)
        if np.mean(np.all(np.abs(surroundings - floor) <= FLOOR_TOLERANCE, axis=1)) < UNIFORM_SHARE:
            continue
        pixels = rgb[top:bottom, left:right].astype(np.int16)
        ghost = region & np.all(np.abs(pixels - floor) <= FLOOR_TOLERANCE, axis=2)
        if ghost.any():
            mask[top:bottom, left:right][ghost] = 0
            dropped = True
    return dropped
