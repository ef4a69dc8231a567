"""AprilTag families as OpenCV 4.6's aruco module knows them, and the images a renderer textures with them.

A tag's image is the marker as ``cv2.aruco.drawMarker`` draws it (a black border one
cell wide around the family's bits: 8 x 8 cells for tag36h11) inside a white quiet
zone one cell wide; a tag's ``size`` is the side of the black square. Seen from
above, a textured :data:`QUAD_OBJ` quad at yaw 0 shows the printed top of the tag
towards +y of ``map`` and its left edge towards -x.

PyBullet puts a texture on any shape with ``loadTexture`` + ``changeVisualShape``,
but only a mesh with UV coordinates shows it as drawn: a ``GEOM_BOX`` maps a part of
the texture to each face. So a tag is an OBJ quad (:func:`write_quad`) scaled to
:func:`quad_side`.

>>> FAMILIES['tag36h11'].ids, cells('tag36h11')
(587, 8)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Family:
    """An AprilTag family: aruco's dictionary constant, the bits across its data grid, how many ids."""

    name: str
    aruco: str
    bits: int
    ids: int


FAMILIES = {
    family.name: family
    for family in (
        Family('tag16h5', 'DICT_APRILTAG_16h5', 4, 30),
        Family('tag25h9', 'DICT_APRILTAG_25h9', 5, 35),
        Family('tag36h10', 'DICT_APRILTAG_36h10', 6, 2320),
        Family('tag36h11', 'DICT_APRILTAG_36h11', 6, 587),
    )
}
"""The AprilTag families of OpenCV 4.6's aruco, by name; ids run from 0 to ``ids - 1``."""

FAMILY_NAMES = tuple(FAMILIES)

CELL_PIXELS = 32
"""Texture pixels per cell of a tag image."""

QUAD_OBJ = """\
# A 1 x 1 quad at z = 0 facing up, the whole texture on it, upright as seen from above.
v -0.5 -0.5 0.0
v 0.5 -0.5 0.0
v 0.5 0.5 0.0
v -0.5 0.5 0.0
vt 0.0 0.0
vt 1.0 0.0
vt 1.0 1.0
vt 0.0 1.0
vn 0.0 0.0 1.0
f 1/1/1 2/2/1 3/3/1
f 1/1/1 3/3/1 4/4/1
"""


def dictionary(family: str) -> Any:  # a cv2.aruco.Dictionary
    """aruco's dictionary of ``family`` (a fresh object: safe to use from any thread)."""
    import cv2

    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, FAMILIES[family].aruco))


def cells(family: str) -> int:
    """Cells across the black square of a ``family`` marker: its bits and the border on both sides."""
    return FAMILIES[family].bits + 2


def quad_side(family: str, size: float) -> float:
    """The side of the textured quad (quiet zone included) of a tag whose black square is ``size``."""
    return size * (cells(family) + 2) / cells(family)


def tag_image(family: str, tag_id: int, cell_pixels: int = CELL_PIXELS) -> np.ndarray:
    """The marker with a one-cell white quiet zone: (cells + 2) * cell_pixels square, grey uint8."""
    import cv2

    marker = cv2.aruco.drawMarker(dictionary(family), tag_id, cells(family) * cell_pixels)
    border = cell_pixels
    return cv2.copyMakeBorder(marker, border, border, border, border, cv2.BORDER_CONSTANT, value=255)


def write_quad(folder: str | Path) -> Path:
    """Write :data:`QUAD_OBJ` into ``folder`` (created if needed); its path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    quad = folder / 'tag_quad.obj'
    quad.write_text(QUAD_OBJ)
    return quad


def write_tag_image(folder: str | Path, family: str, tag_id: int) -> Path:
    """Write the PNG of :func:`tag_image` into ``folder``; its path."""
    import cv2

    texture = Path(folder) / f'{family}_{tag_id}.png'
    if not cv2.imwrite(str(texture), tag_image(family, tag_id)):
        raise OSError(f'cannot write the tag texture {texture}')
    return texture
