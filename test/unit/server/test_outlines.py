"""Outlines as the fusion tracker handles them: checks, overlaps and fused outlines."""

import doctest

import pytest
from shapely.geometry import Polygon

import drvs.server.outlines
from drvs.server.outlines import clean, combine, overlap_area, union_outline

SQUARE = ((0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0))
ELL = ((0.0, 0.0), (2.0, 0.0), (2.0, 1.0), (1.0, 1.0), (1.0, 2.0), (0.0, 2.0))  # not convex


def moved(points, dx, dy=0.0):
    return tuple((x + dx, y + dy) for x, y in points)


def test_doctests():
    assert doctest.testmod(drvs.server.outlines).failed == 0


def test_a_clockwise_outline_gives_the_same_centroid_and_area():
    ccw, cw = clean(ELL), clean(ELL[::-1])
    assert (*cw.centroid, cw.area) == pytest.approx((*ccw.centroid, ccw.area))
    assert (ccw.convex, clean(SQUARE).convex) == (False, True)


def test_overlap_of_a_moved_outline():
    a, b = clean(SQUARE), clean(moved(SQUARE, -0.5))
    assert overlap_area(a, b) == pytest.approx(0.5)
    assert overlap_area(a, b, (0.5, 0.0)) == pytest.approx(1.0)  # b moved on by half a metre
    assert overlap_area(a, clean(moved(SQUARE, 3.0))) == 0.0


def test_the_union_of_convex_outlines_is_their_hull_and_of_others_their_union():
    hull = union_outline([(clean(SQUARE), (0.0, 0.0)), (clean(SQUARE), (0.5, 0.5))])
    assert Polygon(hull).area == pytest.approx(1.75 + 0.25)  # the union, and the two slivers between
    ell = union_outline([(clean(ELL), (0.0, 0.0)), (clean(SQUARE), (0.5, 0.0))])
    assert Polygon(ell).area == pytest.approx(3.0)  # the notch stays
    assert Polygon(ell).exterior.is_ccw


def test_pieces_combine_into_one_outline_with_their_area_weighted_centroid():
    left, right = clean(SQUARE), clean(((1.1, 0.0), (3.1, 0.0), (3.1, 1.0), (1.1, 1.0)))
    both = combine([left, right])
    assert both.centroid == pytest.approx(((0.5 * 1 + 2.1 * 2) / 3, 0.5))
    assert both.bounds == pytest.approx((0.0, 0.0, 3.1, 1.0))  # the hull over the gap
