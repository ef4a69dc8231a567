"""Colour segmentation on images drawn with cv2: regions, areas, outlines on pixel edges."""

from collections import namedtuple

import cv2
import numpy as np
import pytest
from shapely.geometry import Polygon

from drvs.algorithms import ColourModel, outlines_of_mask, parse_algorithm

BLUE = (0, 0, 200)
MODEL = parse_algorithm('colour:0,0,150,80,80,255').params

Setup = namedtuple('Setup', 'name corners iou_min')
SHAPES = [
    Setup('axis_aligned', [(20, 10), (60, 10), (60, 40), (20, 40)], 0.999),
    Setup('rotated', [(60, 20), (100, 45), (85, 70), (45, 45)], 0.95),
    Setup('concave_l', [(10, 10), (70, 10), (70, 25), (25, 25), (25, 70), (10, 70)], 0.98),
]


def draw(corners, size=(120, 160)):
    image = np.full((*size, 3), 255, np.uint8)
    cv2.fillPoly(image, [np.array(corners, np.int32)], BLUE)
    return image


@pytest.mark.parametrize('setup', SHAPES, ids=lambda s: s.name)
def test_an_outline_matches_the_drawn_region(setup):
    image = draw(setup.corners)
    (found,) = MODEL.detect(image, min_area=20, epsilon=1.0)
    pixels = int(MODEL.mask(image).astype(bool).sum())
    assert found.area == pytest.approx(pixels, rel=0.02)
    # cv2 fills the pixels whose centres (u + 0.5, v + 0.5) lie in the polygon, edges included
    truth = Polygon(np.asarray(setup.corners, float) + 0.5).buffer(0.5, join_style=2)
    outline = Polygon(found.outline)
    assert outline.intersection(truth).area / outline.union(truth).area >= setup.iou_min


@pytest.mark.parametrize('epsilon, most_vertices', [(0.0, 400), (1.0, 40), (3.0, 20)])
def test_epsilon_simplifies_a_circle(epsilon, most_vertices):
    image = np.full((120, 120, 3), 255, np.uint8)
    cv2.circle(image, (60, 60), 40, BLUE, -1)
    (found,) = MODEL.detect(image, min_area=20, epsilon=epsilon)
    assert 4 < len(found.outline) <= most_vertices
    assert Polygon(found.outline).area == pytest.approx(found.area, rel=0.03)


def test_separate_regions_are_separate_objects_and_small_ones_are_dropped():
    image = np.full((100, 100, 3), 255, np.uint8)
    image[10:20, 10:20] = BLUE
    image[20:30, 20:30] = BLUE  # touches the first only at a corner: another object
    image[50:60, 50:90] = BLUE
    image[90:93, 5:8] = BLUE  # 9 pixels
    found = MODEL.detect(image, min_area=20)
    assert sorted(round(o.area) for o in found) == [100, 100, 400]
    assert len(MODEL.detect(image, min_area=5)) == 4


def test_a_region_on_the_image_border_ends_at_the_border():
    image = np.full((50, 80, 3), 255, np.uint8)
    image[0:20, 70:80] = BLUE
    (found,) = MODEL.detect(image)
    assert Polygon(found.outline).bounds == (70, 0, 80, 20)


def test_a_hole_is_inside_the_object():
    image = np.full((80, 80, 3), 255, np.uint8)
    image[10:70, 10:70] = BLUE
    image[30:50, 30:50] = 255
    (found,) = MODEL.detect(image)
    assert Polygon(found.outline).bounds == (10, 10, 70, 70)


@pytest.mark.parametrize(
    'colour, inside',
    [((0, 0, 150), True), ((80, 80, 255), True), ((81, 0, 200), False), ((0, 0, 149), False)],
)
def test_thresholds_are_inclusive(colour, inside):
    image = np.full((10, 10, 3), colour, np.uint8)
    assert bool(ColourModel((0, 0, 150), (80, 80, 255)).mask(image).all()) is inside


def test_an_empty_mask_has_no_outlines():
    assert outlines_of_mask(np.zeros((10, 10), np.uint8), 1, 1.0) == []


# -- confidence: how solidly a region is filled --------------------------------------------------


def speckled(share, seed=0):
    """A 60 x 60 blue square whose pixels are each white with probability ``share``; its edge stays blue."""
    image = np.full((100, 100, 3), 255, np.uint8)
    image[20:80, 20:80] = BLUE
    holes = np.random.default_rng(seed).random((58, 58)) < share
    image[21:79, 21:79][holes] = 255
    return image


@pytest.mark.parametrize(
    'image, confidence',
    [
        (draw(SHAPES[1].corners), 1.0),  # a solid region, however it is turned
        (speckled(0.0), 1.0),
        (speckled(0.2), pytest.approx(1 - 0.2 * 58**2 / 60**2, abs=0.02)),
        (speckled(0.5), pytest.approx(1 - 0.5 * 58**2 / 60**2, abs=0.02)),
    ],
)
def test_confidence_is_the_share_of_the_outlines_pixels_that_match(image, confidence):
    (found,) = MODEL.detect(image, min_area=20)
    assert found.confidence == confidence


def test_a_hole_lowers_the_confidence_of_its_object():
    image = np.full((80, 80, 3), 255, np.uint8)
    image[10:70, 10:70] = BLUE
    image[30:50, 30:50] = 255
    image[35:45, 35:45] = BLUE  # an island in the hole: matching pixels inside the outline
    (found,) = MODEL.detect(image)
    assert found.confidence == pytest.approx((3600 - 400 + 100) / 3600)


def test_without_evidence_outlines_of_mask_leaves_the_confidence_unknown():
    mask = np.zeros((40, 40), np.uint8)
    mask[5:30, 5:30] = 1
    mask[10:20, 10:20] = 0
    (found,) = outlines_of_mask(mask, 1, 1.0)
    assert found.confidence == 0.0
    (found,) = outlines_of_mask(mask, 1, 1.0, evidence=mask)
    assert found.confidence == pytest.approx(525 / 625)
