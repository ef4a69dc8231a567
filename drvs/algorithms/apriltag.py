"""``apriltag:FAMILY[:ID,ID,...][:h=HEIGHT]``: AprilTags found with OpenCV's aruco module.

Each tag found is one :class:`PixelObject` labelled ``FAMILY:ID``, lying flat at its
height, its four corners in a fixed order (corner 0 the printed top-left, then
counter-clockwise seen from above), its confidence how clearly its cells read
(:func:`decision_margin`); :func:`tag_pose` gives a tag's centre and heading from
its outline on the floor. The syntax: docs/interface.md ("Algorithms"); corner order and
refinement: docs/design.md ("The built-in algorithms").

>>> from drvs.algorithms import AlgorithmSet, parse_algorithm
>>> parsed = parse_algorithm('apriltag:tag36h11:3,7:h=0.2', AlgorithmSet([AprilTag()]))
>>> parsed.params
TagQuery(family='tag36h11', ids=(3, 7), height=0.2)
>>> parsed.params.format()
'apriltag:tag36h11:3,7:h=0.2'
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from drvs.algorithms.base import Algorithm, AlgorithmError, PixelObject
from drvs.algorithms.tag_images import FAMILIES, FAMILY_NAMES, cells, dictionary

if TYPE_CHECKING:
    from drvs.vision.calibration import Intrinsics
    from drvs.vision.frame import Frame

SYNTAX = 'apriltag:FAMILY[:ID,ID,...][:h=HEIGHT]'
MAX_FIELDS = 3
ARUCO_TO_OUTLINE = (0, 3, 2, 1)
"""aruco's corners (top-left, top-right, bottom-right, bottom-left) in the outline's order."""
OPENCV_OFFSET = 0.5
"""DRVS corner coordinates minus this are OpenCV pixel coordinates (as in :mod:`drvs.vision.optics`)."""
MARGIN_CELL_PIXELS = 8
"""Samples across one tag cell when :func:`decision_margin` reads the cells."""
_ID = re.compile(r'[0-9]+')


@dataclass(frozen=True)
class TagQuery:
    """What ``apriltag:...`` asks for: the tags of ``family``, only ``ids`` (all when empty), lying
    at ``height`` metres (None: the height the algorithm instance knows for each tag)."""

    family: str
    ids: tuple[int, ...] = ()
    height: float | None = None

    @classmethod
    def parse(cls, params: str) -> TagQuery:
        """``FAMILY[:ID,ID,...][:h=HEIGHT]`` -> a query.

        :raises AlgorithmError: naming the field and the problem.
        """
        if not params.strip():
            raise AlgorithmError(f'algorithm: apriltag needs a FAMILY: {SYNTAX}, e.g. apriltag:tag36h11')
        fields = params.split(':')
        if len(fields) > MAX_FIELDS:
            raise AlgorithmError(
                f'algorithm: apriltag takes at most {MAX_FIELDS} fields FAMILY:ID,ID,...:h=HEIGHT, '
                f'got {len(fields)} in {params!r}'
            )
        family = fields[0].strip()
        if family not in FAMILIES:
            raise AlgorithmError(
                f'algorithm: apriltag FAMILY must be one of {", ".join(FAMILY_NAMES)}, got {family!r}'
            )
        ids: tuple[int, ...] = ()
        height = None
        rest = [text.strip() for text in fields[1:]]
        if rest and _is_height(rest[-1]):
            height = _height(rest.pop().partition('=')[2].strip())
        if len(rest) > 1 or any(_is_height(text) for text in rest):
            raise AlgorithmError(
                f'algorithm: apriltag PARAMS must be FAMILY[:ID,ID,...][:h=HEIGHT] in that order, '
                f'got {params!r}'
            )
        if rest:
            ids = _ids(rest[0], family)
        return cls(family, ids, height)

    def format(self) -> str:
        text = f'apriltag:{self.family}'
        if self.ids:
            text += ':' + ','.join(map(str, self.ids))
        if self.height is not None:
            text += f':h={self.height:g}'
        return text

    def __str__(self) -> str:
        return self.format()


def _is_height(field: str) -> bool:
    key, equals, _ = field.partition('=')
    return bool(equals) and key.strip() == 'h'


def _ids(text: str, family: str) -> tuple[int, ...]:
    count = FAMILIES[family].ids
    ids = []
    for part in text.split(','):
        part = part.strip()
        if not _ID.fullmatch(part) or int(part) >= count:
            raise AlgorithmError(
                f'algorithm: apriltag ID must be an integer 0-{count - 1} (an id of {family}), got {part!r}'
            )
        value = int(part)
        if value in ids:
            raise AlgorithmError(f'algorithm: apriltag ID {value} is given twice')
        ids.append(value)
    return tuple(ids)


def _height(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0) or '_' in text:
        raise AlgorithmError(f'algorithm: apriltag h must be a finite number >= 0 (metres), got {text!r}')
    return value + 0.0  # -0.0 -> 0.0


class AprilTag(Algorithm):
    """The apriltag algorithm.

    :param default_height: the plane (metres) of a tag whose height neither the request
        (``h=``) nor ``heights`` gives; 0: on the floor.
    :param heights: {label: height} of the tags the vision system knows, e.g. from the
        world file: ``{'tag36h11:3': 0.2}`` for a tag on top of a 0.2 m robot.

    :meth:`detect` keeps no state between calls: two threads may run it at once.
    """

    name = 'apriltag'
    syntax = SYNTAX

    def __init__(self, default_height: float = 0.0, heights: Mapping[str, float] | None = None):
        self.default_height = _checked_height(default_height, 'default_height')
        self.heights = MappingProxyType(
            {str(label): _checked_height(h, f'heights[{label!r}]') for label, h in (heights or {}).items()}
        )

    def parse(self, params: str) -> TagQuery:
        return TagQuery.parse(params)

    def height_of(self, label: str, query: TagQuery) -> float:
        """The plane tag ``label`` lies on: the request's ``h=``, else ``heights``, else the default."""
        if query.height is not None:
            return query.height
        return self.heights.get(label, self.default_height)

    def detect(self, frame: Frame, params: TagQuery) -> list[PixelObject]:
        """The tags of ``params`` in ``frame``: corners in the order of the module docstring."""
        import cv2

        rgb = frame.rgb
        gray = rgb if rgb.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(rgb[..., :3]), cv2.COLOR_RGB2GRAY)
        found = []
        for tag_id, corners in find_tags(gray, params.family, _intrinsics(frame)):
            if params.ids and tag_id not in params.ids:
                continue
            label = f'{params.family}:{tag_id}'
            outline = corners[list(ARUCO_TO_OUTLINE)] + OPENCV_OFFSET
            found.append(
                PixelObject(
                    outline=outline,
                    area=_area(outline),
                    label=label,
                    height=self.height_of(label, params),
                    keep_order=True,
                    confidence=decision_margin(gray, corners, params.family, tag_id),
                )
            )
        return found


def _checked_height(value: object, what: str) -> float:
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not (math.isfinite(value) and value >= 0)
    ):
        raise ValueError(f'AprilTag: {what}: expected a finite number of metres >= 0, got {value!r}')
    return float(value)


def _intrinsics(frame: Frame) -> Intrinsics:
    """The lens model of the frame's array pixels (OpenCV coordinates) for corner refinement."""
    from drvs.vision.calibration import Intrinsics
    from drvs.vision.optics import CameraModel

    camera = frame.camera
    model = camera if isinstance(camera, CameraModel) else CameraModel.from_pinhole(camera)
    K = np.array(model.K, float)
    # Array pixel (u, v) shows the model's (u, v) + sample_offset.
    K[0, 2] -= frame.sample_offset[0]
    K[1, 2] -= frame.sample_offset[1]
    return Intrinsics(K, tuple(model.D), model.width, model.height)


def find_tags(
    gray: np.ndarray, family: str, intrinsics: Intrinsics | None = None
) -> list[tuple[int, np.ndarray]]:
    """(id, corners) of each ``family`` tag in a grey uint8 image: corners (4, 2) in OpenCV pixel
    coordinates, in aruco's order (top-left, top-right, bottom-right, bottom-left as printed).

    aruco's corners (``CORNER_REFINE_CONTOUR``: lines fitted to the marker's own
    contour) are refined with :func:`drvs.vision.calibration.refine_tag_corners` through the
    lens of ``intrinsics`` (:class:`drvs.vision.calibration.Intrinsics`; None: an ideal lens).
    Not ``CORNER_REFINE_SUBPIX``: ``cv2.cornerSubPix`` moves to any corner near by, such
    as where a quiet zone ends against a coloured body, and the edge fit then refuses
    the moved corners.
    """
    import cv2

    from drvs.vision.calibration import Intrinsics, refine_tag_corners

    if intrinsics is None:
        intrinsics = Intrinsics(np.eye(3))  # without distortion the refinement does not use K
    parameters = cv2.aruco.DetectorParameters_create()
    parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_CONTOUR
    corners, ids, _ = cv2.aruco.detectMarkers(gray, dictionary(family), parameters=parameters)
    found = []
    for quad, tag_id in zip(corners, [] if ids is None else ids.ravel(), strict=True):
        refined = refine_tag_corners(gray, np.asarray(quad, float).reshape(4, 2), intrinsics)
        found.append((int(tag_id), np.asarray(refined, float)))
    return found


def decision_margin(gray: np.ndarray, corners: np.ndarray, family: str, tag_id: int) -> float:
    """How clearly a found tag's weakest cell reads as its code: the algorithm's confidence, 0-1.

    The tag's black square (``corners`` as :func:`find_tags` gives them) is sampled
    cell by cell (the middle half of each cell, through the homography of its corners);
    the threshold lies midway between the mean grey of the cells that should be black
    (the border and the 0 bits) and of those that should be white. A cell's margin is its
    distance from the threshold towards the colour the code expects, as a share of half
    that contrast (1: as clear as the tag's mean; 0: on the threshold; -1: the wrong
    colour). The confidence is (1 + the smallest margin) / 2: 1 for a sharp, evenly lit
    tag; down towards 0.5 as blur, too few pixels, glare, a shadow's edge or noise pull a
    cell towards the threshold; below 0.5 only for a cell that reads wrong here (aruco
    corrects no bit of the AprilTag families, so it read every bit of a tag it reports).
    After AprilTag 3's ``decision_margin`` (OpenCV 4.6's aruco reports none).
    """
    import cv2

    expected = _code(family, tag_id)
    n = len(expected)
    side = n * MARGIN_CELL_PIXELS
    # The black square's corners to the edges of a side x side image (OpenCV pixel centres).
    square = np.array([[0, 0], [side, 0], [side, side], [0, side]], np.float32) - 0.5
    homography = cv2.getPerspectiveTransform(np.asarray(corners, np.float32), square)
    warped = cv2.warpPerspective(
        gray, homography, (side, side), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    quarter = MARGIN_CELL_PIXELS // 4
    grid = warped.reshape(n, MARGIN_CELL_PIXELS, n, MARGIN_CELL_PIXELS)
    values = grid[:, quarter:-quarter, :, quarter:-quarter].mean(axis=(1, 3))
    black, white = values[~expected].mean(), values[expected].mean()
    contrast = white - black
    if not contrast > 0:
        return 0.0
    margins = (values - (black + white) / 2.0) * np.where(expected, 1.0, -1.0) / (contrast / 2.0)
    return float(np.clip((1.0 + margins.min()) / 2.0, 0.0, 1.0))


@functools.lru_cache(maxsize=64)
def _code(family: str, tag_id: int) -> np.ndarray:
    """The tag's cells as printed, border included: (cells, cells) bool, True for white."""
    import cv2

    marker = cv2.aruco.drawMarker(dictionary(family), tag_id, cells(family))
    code = marker > 127
    code.flags.writeable = False
    return code


def _area(outline: np.ndarray) -> float:
    x, y = outline[:, 0], outline[:, 1]
    return float(abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) / 2.0)


def tag_pose(outline: ArrayLike) -> tuple[float, float, float]:
    """(x, y, yaw) of a tag from its 4 corners on the floor, in this module's order.

    The centre is where the diagonals (corner 0 to 2, 1 to 3) cross; the yaw is the
    direction of the printed right: corner 0 -> 3 averaged with corner 1 -> 2. Takes
    (4, 2) or (4, 3) points in ``map`` (as :func:`drvs.vision.pipeline.locate_labelled` reports
    them); in image coordinates (v down) the angle's sign flips.

    >>> x, y, yaw = tag_pose([(1.0, 3.0), (1.0, 1.0), (3.0, 1.0), (3.0, 3.0)])
    >>> round(x, 9), round(y, 9), round(yaw, 9)
    (2.0, 2.0, 0.0)
    """
    points = np.asarray(outline, float)
    if points.ndim != 2 or points.shape[0] != 4 or points.shape[1] not in (2, 3):
        raise ValueError(f'tag_pose: expected 4 corners (x, y), got shape {points.shape}')
    c0, c1, c2, c3 = points[:, :2]
    # c0 + t (c2 - c0) = c1 + s (c3 - c1)
    matrix = np.column_stack([c2 - c0, c1 - c3])
    if abs(np.linalg.det(matrix)) > 1e-12:
        t, _ = np.linalg.solve(matrix, c1 - c0)
        centre = c0 + t * (c2 - c0)
    else:  # degenerate (a quad seen edge-on): the mean of the corners
        centre = points[:, :2].mean(axis=0)
    heading = (c3 - c0) + (c2 - c1)
    return float(centre[0]), float(centre[1]), math.atan2(heading[1], heading[0])
