"""``colour:RMIN,GMIN,BMIN,RMAX,GMAX,BMAX``: the paper's colour segmentation.

>>> model = ColourModel.parse('0,0,150,80,80,255')
>>> model.lower, model.upper
((0, 0, 150), (80, 80, 255))
>>> model.format()
'colour:0,0,150,80,80,255'
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from drvs.algorithms.base import Algorithm, AlgorithmError, PixelObject, outlines_of_mask

if TYPE_CHECKING:
    from drvs.vision.frame import Frame


@dataclass(frozen=True)
class ColourModel:
    """``colour:RMIN,GMIN,BMIN,RMAX,GMAX,BMAX`` — the paper's colour segmentation.

    Pixels whose RGB values lie inside the inclusive thresholds are grouped into
    connected regions; each region above a minimum area is one object.
    """

    NAME = 'colour'
    FIELDS = ('RMIN', 'GMIN', 'BMIN', 'RMAX', 'GMAX', 'BMAX')

    lower: tuple[int, int, int]
    upper: tuple[int, int, int]

    @classmethod
    def parse(cls, params: str) -> ColourModel:
        parts = params.split(',')
        if len(parts) != 6:
            raise AlgorithmError(
                f"algorithm: colour PARAMS must be 6 comma-separated integers "
                f"{','.join(cls.FIELDS)}, got {len(parts)} value(s) in {params!r}"
            )
        values = []
        for field, text in zip(cls.FIELDS, parts, strict=True):
            text = text.strip()
            try:
                value = int(text, 10)
            except ValueError:
                raise AlgorithmError(
                    f'algorithm: colour {field} must be an integer 0-255, got {text!r}'
                ) from None
            if not 0 <= value <= 255:
                raise AlgorithmError(f'algorithm: colour {field} must be in 0-255, got {value}')
            values.append(value)
        lower, upper = (values[0], values[1], values[2]), (values[3], values[4], values[5])
        for channel in range(3):
            if lower[channel] > upper[channel]:
                raise AlgorithmError(
                    f'algorithm: colour {cls.FIELDS[channel]} {lower[channel]} is greater than '
                    f'{cls.FIELDS[channel + 3]} {upper[channel]}'
                )
        return cls(lower, upper)

    def format(self) -> str:
        return f'{self.NAME}:' + ','.join(str(v) for v in (*self.lower, *self.upper))

    def mask(self, image_rgb: np.ndarray) -> np.ndarray:
        """A uint8 mask (255 inside the thresholds) of an (H, W, 3) RGB image."""
        import cv2

        return cv2.inRange(np.ascontiguousarray(image_rgb[..., :3]), self.lower, self.upper)

    def detect(
        self, image_rgb: np.ndarray, min_area: float = 20.0, epsilon: float = 1.0
    ) -> list[PixelObject]:
        """Objects in an RGB image: connected regions of at least ``min_area`` pixels.

        Each outline is simplified with Douglas-Peucker at ``epsilon`` pixels. Each object's
        confidence is how solidly it is filled: the share of the pixels inside its outer
        outline that match (1 for a region without holes; speckle and holes lower it).
        """
        mask = self.mask(image_rgb)
        return outlines_of_mask(mask, min_area, epsilon, evidence=mask)

    def __str__(self) -> str:
        return self.format()


class Colour(Algorithm):
    """The colour algorithm: :class:`ColourModel` thresholds, connected regions of at least
    ``min_area`` pixels, outlines simplified by ``epsilon`` pixels."""

    name = ColourModel.NAME
    syntax = 'colour:RMIN,GMIN,BMIN,RMAX,GMAX,BMAX'

    def __init__(self, min_area: float = 20.0, epsilon: float = 1.0):
        self.min_area = min_area
        self.epsilon = epsilon

    def parse(self, params: str) -> ColourModel:
        return ColourModel.parse(params)

    def detect(self, frame: Frame, params: ColourModel) -> list[PixelObject]:
        return params.detect(frame.rgb, self.min_area, self.epsilon)
