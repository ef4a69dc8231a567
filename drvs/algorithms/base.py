"""What an algorithm is: a name, a parser for its parameters, and a detector that finds objects in a frame.

:class:`Algorithm` is the plugin API the built-ins and third-party algorithms share
(``name``, ``syntax``, ``parse``, ``detect``, and ``observe`` with ``streaming`` for those
with memory), with :class:`PixelObject` and :class:`AlgorithmError`. The reference for
writing one: docs/tutorials/adding-an-algorithm.md; the algorithm string:
docs/interface.md ("Algorithms").
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from drvs.vision.frame import Frame

MAX_LENGTH = 512
NAME_PATTERN = re.compile(r'[A-Za-z][A-Za-z0-9_]*')


class AlgorithmError(ValueError):
    """An algorithm string that cannot be run; the message names the part and the problem."""


class FrameProblem(AlgorithmError):
    """A frame an algorithm cannot work on now (no depth, a depth image that does not fit, no
    reference yet); the message says what is wrong. The vision system refuses the algorithm's
    requests with it, and reports it on its diagnostics, until a frame works again."""


@dataclass(frozen=True)
class PixelObject:
    """One object found in an image: its outline in pixel coordinates and its area in pixels.

    ``outline`` is an (N, 2) float array of (u, v) = (column, row) positions on the
    boundary of the object's pixels (pixel edges, not centres), or any other points
    (a tag's corners) in the same coordinates; orientation unspecified unless the
    algorithm documents it. ``label`` says what it is when the algorithm knows
    (``tag36h11:3``). ``height``: the object lies flat at this height above the
    floor (metres), so its outline is met with that plane; None: lift it with depth,
    or meet it with the floor.
    """

    outline: np.ndarray
    area: float
    label: str = ''
    height: float | None = None
    keep_order: bool = False
    """True: the outline's vertex order means something (a tag's corner 0 first); keep it."""
    confidence: float = 0.0
    """How sure the algorithm is of the object, 0 to 1, in a sense each algorithm documents;
    0: unknown (the default, for algorithms that do not say). Sent in DetectedObject.confidence."""
    footprint: np.ndarray | None = None
    """Where the object stands on the floor, (N, 2) (x, y) in ``map``, metres, when the algorithm
    works it out itself (``elevation``): reported as it is instead of ``outline`` put on the floor."""
    top_height: float = 0.0
    """The object's top, metres above the floor, when the algorithm measures it; 0: unknown.
    Sent in DetectedObject.height."""
    clearance: float = 0.0
    """The free space under the object, metres above the floor of its underside, when the algorithm
    measured it (``elevation``, a camera that saw floor under it); 0: on the floor or unknown.
    Sent in DetectedObject.clearance."""

    def __post_init__(self) -> None:
        top = self.top_height
        if isinstance(top, bool) or not isinstance(top, int | float | np.floating) or not top >= 0.0:
            raise ValueError(f'PixelObject: top_height must be a number >= 0, got {top!r}')
        object.__setattr__(self, 'top_height', float(top))
        under = self.clearance
        if isinstance(under, bool) or not isinstance(under, int | float | np.floating) or not under >= 0.0:
            raise ValueError(f'PixelObject: clearance must be a number >= 0, got {under!r}')
        object.__setattr__(self, 'clearance', float(under))
        confidence = self.confidence
        if isinstance(confidence, bool) or not isinstance(confidence, int | float | np.floating):
            raise ValueError(f'PixelObject: confidence must be a number 0-1, got {confidence!r}')
        if not 0.0 <= confidence <= 1.0:  # NaN too
            raise ValueError(f'PixelObject: confidence must be in 0-1, got {confidence!r}')
        object.__setattr__(self, 'confidence', float(confidence))


class Algorithm:
    """Base class of the algorithms (plugins need not inherit from it; they need the same members)."""

    name = ''
    syntax = ''
    streaming = False

    def parse(self, params: str) -> Any:
        raise NotImplementedError

    def detect(self, frame: Frame, params: Any) -> list[PixelObject]:
        raise NotImplementedError

    def observe(self, frame: Frame) -> None:
        """Take one frame of the camera's stream (algorithms with memory)."""

    def frame_problem(self, frame: Frame) -> str | None:
        """Why ``frame`` cannot be worked on (no depth, no reference yet), naming the algorithm; None
        when it can. The vision system refuses requests with it before they queue; ``detect``
        raises :class:`FrameProblem` with it."""
        return None


def split_algorithm(text: object) -> tuple[str, str]:
    """``NAME[:PARAMS]`` -> (NAME, PARAMS) after checking the syntax only.

    :raises AlgorithmError: empty, too long, or not ``NAME[:PARAMS]``.
    """
    if not isinstance(text, str) or not text:
        raise AlgorithmError('algorithm: empty; expected NAME:PARAMS, e.g. colour:0,0,150,80,80,255')
    if len(text) > MAX_LENGTH:
        raise AlgorithmError(f'algorithm: {len(text)} characters, longer than the limit of {MAX_LENGTH}')
    name, _, params = text.partition(':')
    if not NAME_PATTERN.fullmatch(name):
        raise AlgorithmError(
            f'algorithm: expected NAME[:PARAMS] with NAME a letter then letters, digits or _, '
            f'e.g. colour:0,0,150,80,80,255, got {text!r}'
        )
    return name, params


def outlines_of_mask(
    mask: np.ndarray, min_area: float, epsilon: float, evidence: np.ndarray | None = None
) -> list[PixelObject]:
    """Outer outlines of the connected regions of a binary mask, on the pixels' edges.

    Pixel (row v, column u) covers the square [u, u+1] x [v, v+1]. OpenCV traces
    contours through pixel centres (u + 0.5, v + 0.5); the traced polygon is
    grown by half a pixel with mitred corners so a region's outline runs along
    its outer pixel edges and its area matches its pixel count. Pixels that touch
    only at a corner, or through a one-pixel-wide neck, make separate objects.

    ``evidence``: a mask of the same shape (non-zero: a pixel that speaks for an object;
    ``mask`` itself for how solidly each region is filled); each object's ``confidence`` is
    then :func:`fill_fraction`, the share of the pixels inside its traced outer outline
    (holes included) that are set in ``evidence``. None: confidence 0 (unknown).
    """
    import cv2
    from shapely.geometry import Polygon

    # countNonZero reads a uint8 mask several times faster than ndarray.any().
    if not (cv2.countNonZero(mask) if mask.dtype == np.uint8 and mask.ndim == 2 else mask.any()):
        return []
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    found = []
    for contour in contours:
        confidence = 0.0 if evidence is None else fill_fraction(contour, evidence)
        centres = contour.reshape(-1, 2).astype(np.float64) + 0.5
        if len(centres) < 3:
            shape = Polygon(
                [
                    (u + du, v + dv)
                    for u, v in centres
                    for du, dv in ((-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5))
                ]
            ).convex_hull
        else:
            shape = Polygon(centres).buffer(0).buffer(0.5, join_style=2, mitre_limit=2.0)
        # Parts joined only diagonally or by a one-pixel neck come apart here: each is an object.
        parts = shape.geoms if shape.geom_type == 'MultiPolygon' else [shape]
        for part in parts:
            if part.is_empty or part.area < min_area:
                continue
            simple = part.simplify(epsilon, preserve_topology=True)
            ring = np.asarray(simple.exterior.coords)[:-1]
            if len(ring) >= 3:
                found.append(PixelObject(ring, float(part.area), confidence=confidence))
    return found


def fill_fraction(contour: np.ndarray, evidence: np.ndarray) -> float:
    """The share (0-1) of the pixels inside ``contour`` (an OpenCV contour through pixel centres,
    its own pixels and any holes included) that are non-zero in ``evidence``."""
    import cv2

    left, top, width, height = cv2.boundingRect(contour)
    inside = np.zeros((height, width), np.uint8)
    cv2.drawContours(inside, [contour], 0, 255, thickness=cv2.FILLED, offset=(-left, -top))
    total = cv2.countNonZero(inside)
    if total == 0:
        return 0.0
    window = evidence[top : top + height, left : left + width]
    return float(np.count_nonzero(window[inside > 0])) / total
