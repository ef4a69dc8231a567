"""``foreground[:MIN_AREA]``: whatever differs from a fixed camera's reference image of its empty floor.

For cameras without depth. The reference is given (a vision system's ``~reference`` file, which
``drvs_calibrate --reference`` writes; the simulation renders the empty floor), else learnt from
the camera's first frames (:data:`LEARN_FRAMES`). Each pixel is compared after the frame's global
change of light is divided out, by brightness and chromaticity, so that a soft shadow is floor;
each connected region of at least MIN_AREA pixels is one object, its footprint estimated from
the region's edge nearest the point below the camera. Method, error and limits: docs/design.md
("The built-in algorithms").

>>> Foreground().parse('400')
ForegroundParams(min_area=400.0)
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from drvs.algorithms.base import Algorithm, AlgorithmError, FrameProblem, PixelObject, outlines_of_mask

if TYPE_CHECKING:
    from drvs.vision.frame import Frame

log = logging.getLogger('rosout.' + __name__)

DEFAULT_MIN_AREA = 100.0
"""Smallest region reported, pixels, when ``MIN_AREA`` is not given."""
LEARN_FRAMES = 5
"""Without a reference image: the per-pixel median of the first this many frames observed is the
reference (the floor must be empty of what is to be found then)."""
BLUR = 5
"""Side (pixels) of the Gaussian blur of frame and reference before comparing (sensor noise)."""
SHADOW = 0.55
"""A pixel at least this bright relative to the reference (after the global change of light), of
the same chromaticity, is floor in a shadow; darker, it is an object."""
BRIGHT = 1.3
"""A pixel brighter than this relative to the reference is an object (a lit surface, a reflection)."""
CHROMA = 0.12
"""Largest chromaticity distortion (colour distance from the reference's line of brightness, over
the reference's brightness) of floor."""
DARK = 30.0
"""The reference's brightness (RGB norm, 0-441) under which chromaticity is measured against this
instead: in the dark, colour is noise."""
OPENING = 3
CLOSING = 5
"""Sizes (pixels) of the square kernels that clean the foreground mask."""
SAMPLE = 4
"""Every SAMPLE-th pixel in each direction estimates the global change of light."""


@dataclass(frozen=True)
class ForegroundParams:
    """``foreground[:MIN_AREA]`` parsed: the smallest region reported, in pixels."""

    min_area: float = DEFAULT_MIN_AREA

    def format(self) -> str:
        return f'foreground:{self.min_area:g}'


class Foreground(Algorithm):
    """The foreground algorithm for one camera: its reference image of the empty floor.

    :param reference: the empty floor, (H, W, 3) uint8 RGB; None: learnt from the first
        :data:`LEARN_FRAMES` frames observed.
    :param epsilon: Douglas-Peucker tolerance (pixels) of the outlines.
    """

    name = 'foreground'
    syntax = 'foreground[:MIN_AREA]'

    def __init__(self, reference: np.ndarray | None = None, epsilon: float = 1.0):
        self.epsilon = epsilon
        self._lock = threading.Lock()  # guards the reference and the frames being learnt
        self._learning: list[np.ndarray] = []
        self._reference: np.ndarray | None = None
        if reference is not None:
            self.set_reference(reference)

    @property
    def streaming(self) -> bool:  # type: ignore[override]
        """Whether it needs the camera's stream: only while it learns its reference. With one, what
        it finds depends on the frame alone, so requests sharing a frame share its objects."""
        return self._reference is None

    @property
    def reference(self) -> np.ndarray | None:
        """The blurred reference, float32 (H, W, 3); None while it is being learnt."""
        return self._reference

    def set_reference(self, image: np.ndarray) -> None:
        """Take ``image`` ((H, W, 3) uint8 RGB of the empty floor) as the reference."""
        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] < 3:
            raise ValueError(f'foreground: a reference image must be (H, W, 3) RGB, got shape {image.shape}')
        with self._lock:
            self._reference = _blurred(image)
            self._learning.clear()

    # -- parameters ----------------------------------------------------------------------------
    def parse(self, params: str) -> ForegroundParams:
        text = params.strip()
        if not text:
            return ForegroundParams()
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value > 0):
            raise AlgorithmError(
                f'algorithm: foreground MIN_AREA must be a positive number of pixels, got {text!r}'
            )
        return ForegroundParams(value)

    # -- the stream: learning the reference ----------------------------------------------------------
    def observe(self, frame: Frame) -> None:
        """While there is no reference, learn it from the frames (:data:`LEARN_FRAMES`)."""
        with self._lock:
            if self._reference is not None:
                return
            if self._learning and self._learning[-1].shape != frame.rgb.shape:
                self._learning.clear()
            if any(seen is frame.rgb for seen in self._learning):
                return
            self._learning.append(frame.rgb)
            if len(self._learning) >= LEARN_FRAMES:
                median = np.median(np.stack(self._learning), axis=0).astype(np.uint8)
                self._reference = _blurred(median)
                self._learning.clear()
                log.info('foreground: learnt the reference of the empty floor from %d frames', LEARN_FRAMES)

    # -- detection -----------------------------------------------------------------------------
    def frame_problem(self, frame: Frame) -> str | None:
        """Why ``frame`` cannot be judged now: no reference yet, or one of another size; or None."""
        with self._lock:
            reference, learnt = self._reference, len(self._learning)
        if reference is None:
            return (
                f'foreground: learning the reference of the empty floor ({learnt} of {LEARN_FRAMES} '
                'frames); give the vision system ~reference to start at once'
            )
        if reference.shape[:2] != frame.rgb.shape[:2]:
            height, width = reference.shape[:2]
            return (
                f'foreground: the reference image is {width}x{height} but the frames '
                f'{frame.rgb.shape[1]}x{frame.rgb.shape[0]}'
            )
        return None

    def detect(self, frame: Frame, params: ForegroundParams) -> list[PixelObject]:
        """The regions of ``frame`` unlike the reference, each with its estimated footprint.

        :raises FrameProblem: no reference yet, or one of another size than the frame.
        """
        reference = self._reference
        problem = self.frame_problem(frame)
        if problem or reference is None:
            raise FrameProblem(problem or 'foreground: no reference')
        changed = foreground_mask(frame.rgb, reference)
        found = []
        for region in outlines_of_mask(clean(changed), params.min_area, self.epsilon, evidence=changed):
            footprint = footprint_from_outline(frame, region.outline)
            found.append(
                PixelObject(region.outline, region.area, confidence=region.confidence, footprint=footprint)
            )
        return found


def read_reference(path: str) -> np.ndarray:
    """The RGB image (uint8) of the empty floor in file ``path`` (any format OpenCV reads).

    :raises ValueError: naming the file and what is wrong.
    """
    import cv2

    image = cv2.imread(path, cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError(f'{path}: cannot read it as an image (no such file, or not a format OpenCV reads)')
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def _blurred(image: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.GaussianBlur(np.asarray(image[..., :3], np.float32), (BLUR, BLUR), 0)


def foreground_mask(rgb: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """uint8 mask (255: unlike the floor) of ``rgb`` against the blurred ``reference`` (float32).

    The global change of light is the per-channel median ratio of frame to reference (objects
    must cover less than half the view); then each pixel's brightness relative to the reference
    (``alpha``, the projection on the reference colour's line) and its chromaticity distortion
    (distance from that line over the reference's brightness) decide: floor, or floor in a soft
    shadow, when ``SHADOW <= alpha <= BRIGHT`` and the distortion is below ``CHROMA``.
    """
    image = _blurred(rgb)
    sample_image = image[::SAMPLE, ::SAMPLE].reshape(-1, 3)
    sample_reference = reference[::SAMPLE, ::SAMPLE].reshape(-1, 3)
    lit = np.all(sample_reference > 10, axis=1)
    gain = np.ones(3, np.float32)
    if np.count_nonzero(lit) > 0:
        gain = np.median(sample_image[lit] / sample_reference[lit], axis=0).astype(np.float32)
    expected = reference * gain
    power = np.einsum('ijk,ijk->ij', expected, expected)
    alpha = np.einsum('ijk,ijk->ij', image, expected) / np.maximum(power, 1.0)
    distortion = np.linalg.norm(image - alpha[..., None] * expected, axis=2)
    chroma = distortion / np.maximum(np.sqrt(power), DARK)
    floor = (alpha >= SHADOW) & (alpha <= BRIGHT) & (chroma <= CHROMA)
    return np.where(floor, 0, 255).astype(np.uint8)


def clean(mask: np.ndarray) -> np.ndarray:
    """The mask without speckle and with close parts of one object joined."""
    import cv2

    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((OPENING, OPENING), np.uint8))
    return cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((CLOSING, CLOSING), np.uint8))


def footprint_from_outline(frame: Frame, outline: np.ndarray) -> np.ndarray | None:
    """Where an object whose image is ``outline`` (array pixels) stands, estimated on the floor.

    The outline met with the floor plane is the object's *shadow from the camera*: right along its
    edge nearest the point below the camera (its lowest edge in the image, where it meets the floor),
    stretched away from that point by its unknown height. The estimate keeps the part of it within
    its width (across the direction from the camera) of that nearest edge: a footprint as deep as
    it is wide. An object whose shadow holds the point below the camera shows no side: its shadow
    is all there is. None when the outline does not meet the floor.
    """
    from shapely.affinity import rotate, translate
    from shapely.geometry import Point, Polygon, box

    points = frame.camera.pixel_to_floor(frame.to_camera(np.asarray(outline, float)))
    points = points[np.all(np.isfinite(points), axis=1)]
    if len(points) < 3:
        return None
    shadow = Polygon(points[:, :2]).buffer(0)
    if shadow.is_empty or shadow.geom_type != 'Polygon' or shadow.area <= 0:
        return None
    eye = np.asarray(frame.camera.eye[:2], float)
    away = np.asarray(shadow.centroid.coords[0]) - eye
    if np.hypot(*away) < 1e-6 or shadow.contains(Point(eye)):  # right below the camera: no side shows
        return np.asarray(shadow.exterior.coords)[:-1]
    angle = math.degrees(math.atan2(away[1], away[0]))
    # In a frame turned so that "away from the camera" is +x, with the camera at the origin.
    turned = rotate(translate(shadow, -eye[0], -eye[1]), -angle, origin=(0, 0))
    near, low, far, high = turned.bounds
    kept = turned.intersection(box(near, low, near + (high - low), high))
    if kept.is_empty:
        return None
    if kept.geom_type != 'Polygon':
        kept = max(getattr(kept, 'geoms', []), key=lambda part: part.area, default=None)
        if kept is None or kept.geom_type != 'Polygon':
            return None
    placed = translate(rotate(kept, angle, origin=(0, 0)), eye[0], eye[1])
    return np.asarray(placed.exterior.coords)[:-1]
