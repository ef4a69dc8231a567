"""The shared algorithm definitions: the ``NAME:PARAMS`` strings of DetectObjectBoundary.

The server parses them to refuse bad requests, the vision systems to run them
and the robots to build them (the paper's Discussion: these definitions are
part of the API). To add an algorithm, write a class with ``NAME``, ``parse``,
``format`` and ``detect`` and list it in :data:`ALGORITHMS`; nothing else changes.

>>> model = parse_algorithm('colour:0,0,150,80,80,255')
>>> model.lower, model.upper
((0, 0, 150), (80, 80, 255))
>>> model.format()
'colour:0,0,150,80,80,255'
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAX_LENGTH = 512


class AlgorithmError(ValueError):
    """An algorithm string that cannot be run; the message names the part and the problem."""


@dataclass(frozen=True)
class PixelObject:
    """One object found in an image: its outline in pixel coordinates and its area in pixels.

    ``outline`` is an (N, 2) float array of (u, v) = (column, row) positions on the
    boundary of the object's pixels (pixel edges, not centres)
    (orientation unspecified: callers orient it after projecting).
    """

    outline: np.ndarray
    area: float


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
        lower, upper = tuple(values[:3]), tuple(values[3:])
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

        Each outline is simplified with Douglas-Peucker at ``epsilon`` pixels.
        """
        return outlines_of_mask(self.mask(image_rgb), min_area, epsilon)

    def __str__(self) -> str:
        return self.format()


def outlines_of_mask(mask: np.ndarray, min_area: float, epsilon: float) -> list[PixelObject]:
    """Outer outlines of the connected regions of a binary mask, on the pixels' edges.

    Pixel (row v, column u) covers the square [u, u+1] x [v, v+1]. OpenCV traces
    contours through pixel centres (u + 0.5, v + 0.5); the traced polygon is
    grown by half a pixel with mitred corners so a region's outline runs along
    its outer pixel edges and its area matches its pixel count. Pixels that touch
    only at a corner, or through a one-pixel-wide neck, make separate objects.
    """
    import cv2
    from shapely.geometry import Polygon

    if not mask.any():
        return []
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    found = []
    for contour in contours:
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
                found.append(PixelObject(ring, float(part.area)))
    return found


ALGORITHMS: dict[str, type] = {ColourModel.NAME: ColourModel}
"""Every algorithm DRVS knows, by NAME."""


def parse_algorithm(text: str):
    """Parse ``NAME:PARAMS`` into the algorithm object that runs it.

    :raises AlgorithmError: naming the problem: empty, too long, not
        ``NAME:PARAMS``, unknown NAME, or PARAMS the algorithm refuses.
    """
    if not isinstance(text, str) or not text:
        raise AlgorithmError('algorithm: empty; expected NAME:PARAMS, e.g. colour:0,0,150,80,80,255')
    if len(text) > MAX_LENGTH:
        raise AlgorithmError(f'algorithm: {len(text)} characters, longer than the limit of {MAX_LENGTH}')
    name, separator, params = text.partition(':')
    if not separator or not name or not params:
        raise AlgorithmError(f'algorithm: expected NAME:PARAMS, e.g. colour:0,0,150,80,80,255, got {text!r}')
    cls = ALGORITHMS.get(name)
    if cls is None:
        raise AlgorithmError(f'algorithm: unknown NAME {name!r}; known: {", ".join(sorted(ALGORITHMS))}')
    return cls.parse(params)
