"""Matching (the paper's Algorithm 1) against brute-force polygon intersection on random inputs."""

import math
import random

import pytest
from shapely.geometry import Polygon

from drvs.registry import Registry
from drvs.spatial_index import FieldOfViewIndex, interiors_intersect
from drvs.validation import region_geometry


def random_polygon(rng: random.Random, kind: str):
    """A valid polygon of one of three kinds: convex-ish quad, non-convex star, very thin sliver."""
    cx, cy = rng.uniform(0, 50), rng.uniform(0, 50)
    if kind == 'quad':
        w, h, a = rng.uniform(0.5, 6), rng.uniform(0.5, 6), rng.uniform(0, math.pi)
        corners = [(-w, -h), (w, -h), (w * rng.uniform(0.5, 1.5), h), (-w, h)]
        return [
            (cx + x * math.cos(a) - y * math.sin(a), cy + x * math.sin(a) + y * math.cos(a))
            for x, y in corners
        ]
    if kind == 'star':  # non-convex: radii alternate, angles increase, so it never crosses itself
        n = rng.randint(5, 12)
        return [
            (cx + r * math.cos(2 * math.pi * i / n), cy + r * math.sin(2 * math.pi * i / n))
            for i, r in ((i, rng.uniform(0.3, 1.0) * (4 if i % 2 else 1.5)) for i in range(n))
        ]
    length, a = rng.uniform(2, 30), rng.uniform(0, math.pi)  # sliver: a long triangle 1e-3 wide
    dx, dy = math.cos(a), math.sin(a)
    return [
        (cx, cy),
        (cx + length * dx, cy + length * dy),
        (cx + length * dx - 1e-3 * dy, cy + length * dy + 1e-3 * dx),
    ]


def brute_force(fields, box):
    """Names whose polygon overlaps the region by a positive area (no index, no shared predicate)."""
    region = Polygon([(box[0], box[1]), (box[2], box[1]), (box[2], box[3]), (box[0], box[3])])
    return sorted(name for name, points in fields.items() if Polygon(points).intersection(region).area > 0)


@pytest.mark.parametrize('seed', range(3))
def test_matching_equals_brute_force(seed):
    rng = random.Random(seed)
    index = FieldOfViewIndex(background=False, min_rebuild=32, max_rebuild=32)
    registry = Registry(lease=1e9, index=index)
    fields = {}
    for n in range(400):
        name = f'/vs{n}/detect_object_boundary'
        fields[name] = random_polygon(rng, ('quad', 'star', 'sliver')[n % 3])
        registry.register(name, fields[name])
    for step in range(120):
        if step % 3 == 0:  # move or remove some, so the tree and the delta are both exercised
            name = rng.choice(sorted(fields))
            if rng.random() < 0.3:
                registry.register(name, [])
                del fields[name]
            else:
                fields[name] = random_polygon(rng, 'star')
                registry.register(name, fields[name])
        x, y = rng.uniform(-5, 55), rng.uniform(-5, 55)
        box = (x, y, x + rng.uniform(0.01, 8), y + rng.uniform(0.01, 8))
        assert registry.match(box) == brute_force(fields, box)
    assert index.rebuilds >= 2


UNIT = [(0, 0), (1, 0), (1, 1), (0, 1)]


@pytest.mark.parametrize(
    'box, matches',
    [
        ((0.2, 0.2, 0.8, 0.8), True),  # inside
        ((-1, -1, 2, 2), True),  # contains the field of view
        ((0.9, 0.2, 3, 0.4), True),  # overlaps a strip
        ((1, 0, 2, 1), False),  # shares the right edge only
        ((1, 1, 2, 2), False),  # shares a corner only
        ((-1, -1, 0, 0), False),  # corner only, other side
        ((1.0001, 0, 2, 1), False),  # just apart
        ((0.9999, 0, 2, 1), True),  # just overlapping
        ((0.5, 0.5, 0.5, 0.5), True),  # a point inside
        ((1, 0.5, 1, 0.5), False),  # a point on the edge
        ((0.5, -1, 0.5, 2), True),  # a segment crossing the interior
        ((1, -1, 1, 2), False),  # a segment along the edge
    ],
)
def test_touching_edges_do_not_match(box, matches):
    registry = Registry(index=FieldOfViewIndex(background=False))
    registry.register('/a', UNIT)
    assert registry.match(box) == (['/a'] if matches else [])


def test_true_intersection_not_bounding_box():
    """An L-shaped field of view whose bounding box covers the region, but not the polygon."""
    registry = Registry(index=FieldOfViewIndex(background=False))
    registry.register('/l', [(0, 0), (4, 0), (4, 1), (1, 1), (1, 4), (0, 4)])
    assert registry.match((2, 2, 3, 3)) == []
    assert registry.match((0.5, 2, 3, 3)) == ['/l']


def test_interiors_intersect_is_the_documented_rule():
    square = Polygon(UNIT)
    assert interiors_intersect(square, region_geometry((0.5, 0.5, 2, 2)))
    assert not interiors_intersect(square, region_geometry((1, 0, 2, 1)))


@pytest.mark.slow
def test_matching_with_200000_cameras_equals_brute_force():
    rng = random.Random(7)
    index = FieldOfViewIndex(background=True, min_rebuild=10**6)  # bulk load, one build
    registry = Registry(lease=1e9, index=index)
    fields = {}
    for n in range(200_000):
        x, y = rng.uniform(0, 600), rng.uniform(0, 600)
        fields[f'/vs{n}'] = [(x, y), (x + 2, y + 0.3), (x + 1.8, y + 1.5), (x + 0.1, y + 1.2)]
        registry.register(f'/vs{n}', fields[f'/vs{n}'])
    index.rebuild_now()
    index.min_rebuild = 256
    for n in range(0, 200_000, 97):  # moves after the build: served from the delta and rebuilds
        x, y = rng.uniform(0, 600), rng.uniform(0, 600)
        fields[f'/vs{n}'] = [(x, y), (x + 1, y), (x, y + 1)]
        registry.register(f'/vs{n}', fields[f'/vs{n}'])
    for _ in range(30):
        x, y = rng.uniform(0, 600), rng.uniform(0, 600)
        box = (x, y, x + 5, y + 5)
        near = {k: v for k, v in fields.items() if x - 3 <= v[0][0] <= x + 5 and y - 2 <= v[0][1] <= y + 5}
        assert registry.match(box) == brute_force(near, box)
