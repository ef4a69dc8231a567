"""Matching (the paper's Algorithm 1) against brute-force polygon intersection on random inputs.

The index answers most candidates in plain Python (bounding boxes, the separating-axis
test on convex polygons) and the rest with GEOS; both paths are checked against GEOS's
relate, on random polygons and on exact touching (integer coordinates, float32 values).
"""

import math
import random
import struct
import threading

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from shapely.errors import ShapelyError
from shapely.geometry import Polygon

import drvs.server.spatial_index
from drvs.common.validation import ValidationError, field_of_view_polygon, region_geometry, region_of_interest
from drvs.server.registry import Registry
from drvs.server.spatial_index import FieldOfViewIndex, interiors_intersect, separating_axes


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
    index = FieldOfViewIndex()
    registry = Registry(lease=1e9, index=index)
    fields = {}
    for n in range(400):
        name = f'/vs{n}/detect_object_boundary'
        fields[name] = random_polygon(rng, ('quad', 'star', 'sliver')[n % 3])
        registry.register(name, fields[name])
    for step in range(120):
        if step % 3 == 0:  # move or remove some
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
    assert len(index) == len(fields)


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
    registry = Registry()
    registry.register('/a', UNIT)
    assert registry.match(box) == (['/a'] if matches else [])


def test_true_intersection_not_bounding_box():
    """An L-shaped field of view whose bounding box covers the region, but not the polygon."""
    registry = Registry()
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
    registry = Registry(lease=1e9)
    fields = {}
    for n in range(200_000):
        x, y = rng.uniform(0, 600), rng.uniform(0, 600)
        fields[f'/vs{n}'] = [(x, y), (x + 2, y + 0.3), (x + 1.8, y + 1.5), (x + 0.1, y + 1.2)]
        registry.register(f'/vs{n}', fields[f'/vs{n}'])
    for n in range(0, 200_000, 97):  # moves
        x, y = rng.uniform(0, 600), rng.uniform(0, 600)
        fields[f'/vs{n}'] = [(x, y), (x + 1, y), (x, y + 1)]
        registry.register(f'/vs{n}', fields[f'/vs{n}'])
    for _ in range(30):
        x, y = rng.uniform(0, 600), rng.uniform(0, 600)
        box = (x, y, x + 5, y + 5)
        near = {k: v for k, v in fields.items() if x - 3 <= v[0][0] <= x + 5 and y - 2 <= v[0][1] <= y + 5}
        assert registry.match(box) == brute_force(near, box)


# -- the index's two paths: plain Python where it is sure, GEOS where it is not -------------------

PROPERTY = settings(
    max_examples=120,
    deadline=None,
    database=None,  # nothing written into the working tree
    derandomize=True,  # the same examples in every run
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)


def float32(value: float) -> float:
    return struct.unpack('<f', struct.pack('<f', value))[0]


def relate(points, box) -> bool | None:
    """GEOS's answer for the rule (interiors share a point); None if GEOS cannot tell."""
    try:
        return Polygon(points).relate_pattern(region_geometry(box), 'T********')
    except ShapelyError:  # GEOS cannot tell (as for some subnormal coordinates): no reference answer
        return None


def assert_matches_like_geos(points, box):
    try:
        field_of_view_polygon(points)
        region_of_interest(box)
    except ValidationError:
        return
    expected = relate(points, box)
    if expected is None:
        return
    registry = Registry()
    registry.register('/p', points)
    assert registry.match(box) == (['/p'] if expected else []), (points, box)


def hull(points) -> list[tuple[float, float]]:
    """The convex hull's outline (counter-clockwise, no repeated last vertex), or [] if it is flat."""
    shape = Polygon(points).convex_hull if len(set(points)) >= 3 else None
    if shape is None or shape.geom_type != 'Polygon':
        return []
    return [(float(x), float(y)) for x, y in shape.exterior.coords[:-1]]


@st.composite
def convex_cases(draw, values):
    """A convex outline of ``values`` (any first vertex, either way round, maybe a straight vertex), a box."""
    outline = hull(draw(st.lists(st.tuples(values, values), min_size=3, max_size=7)))
    if not outline:
        outline = [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)]
    shift = draw(st.integers(0, len(outline) - 1))
    outline = outline[shift:] + outline[:shift]
    if draw(st.booleans()):
        outline.reverse()
    if draw(st.integers(0, 4)) == 0:  # a vertex halfway along an edge: convex, not strictly
        (x1, y1), (x2, y2) = outline[0], outline[1]
        outline.insert(1, ((x1 + x2) / 2, (y1 + y2) / 2))
    (min_x, max_x), (min_y, max_y) = sorted(draw(values) for _ in 'ab'), sorted(draw(values) for _ in 'ab')
    return outline, (min_x, min_y, max_x, max_y)


GRID = st.integers(-3, 6).map(float)
"""Small integers: exact arithmetic, so regions touch edges (also slanted ones) and corners exactly."""
SCALED = st.builds(
    lambda base, scale, sign: float32(sign * base * scale),
    st.sampled_from([0.0, 0.1, 0.3, 0.427, 1 / 3, 1.7, 2.0]),
    st.sampled_from([1e-3, 1.0, 1e3, 1e5, 1e6]),
    st.sampled_from([1, -1]),
)
"""A few float32 values at several scales, as fields of view come over the wire: near-coincidences."""
ANY = st.floats(-50, 50, allow_nan=False)


@PROPERTY
@given(convex_cases(GRID))
def test_convex_fields_of_view_match_like_geos_on_a_grid(case):
    assert_matches_like_geos(*case)


@PROPERTY
@given(convex_cases(SCALED))
def test_convex_fields_of_view_match_like_geos_at_every_scale(case):
    assert_matches_like_geos(*case)


@PROPERTY
@given(convex_cases(ANY))
def test_convex_fields_of_view_match_like_geos_anywhere(case):
    assert_matches_like_geos(*case)


@PROPERTY
@given(st.lists(st.tuples(GRID, GRID), min_size=3, max_size=7), st.lists(GRID, min_size=4, max_size=4))
def test_any_field_of_view_matches_like_geos(points, values):
    """Non-convex and self-crossing outlines too (those the validation lets through)."""
    (min_x, max_x), (min_y, max_y) = sorted(values[:2]), sorted(values[2:])
    assert_matches_like_geos(points, (min_x, min_y, max_x, max_y))


def test_separating_axes_only_for_surely_convex_outlines():
    assert separating_axes([(0, 0), (2, 0), (2, 1), (0, 1)]) is not None
    assert separating_axes([(0, 0), (0, 1), (2, 1), (2, 0)]) is not None  # clockwise
    assert separating_axes([(0, 0), (1, 0), (2, 0), (2, 1), (0, 1)]) is None  # a straight vertex
    assert separating_axes([(0, 0), (4, 0), (4, 1), (1, 1), (1, 4), (0, 4)]) is None  # an L
    star = [(math.cos(4 * math.pi * i / 5), math.sin(4 * math.pi * i / 5)) for i in range(5)]
    assert separating_axes(star) is None  # turns one way, but twice round
    assert separating_axes([(0, 0), (1, 0), (1, 0), (0, 1)]) is None  # a repeated vertex
    # Each edge: outward unit normal, its absolute components, how far the polygon reaches along it.
    counter_clockwise = list(separating_axes([(0, 0), (2, 0), (2, 1), (0, 1)]))
    assert counter_clockwise == [0, -1, 0, 1, 0, 1, 0, 1, 0, 2, 0, 1, 0, 1, 1, -1, 0, 1, 0, 0]
    clockwise = list(separating_axes([(0, 1), (2, 1), (2, 0), (0, 0)]))
    assert clockwise == [0, 1, 0, 1, 1, 1, 0, 1, 0, 2, 0, -1, 0, 1, 0, -1, 0, 1, 0, 0]


@pytest.fixture
def geos_calls(monkeypatch):
    """The candidates the index hands to GEOS."""
    calls = []
    real = drvs.server.spatial_index.interiors_intersect

    def counted(field_of_view, region):
        calls.append(region.geom_type)
        return real(field_of_view, region)

    monkeypatch.setattr(drvs.server.spatial_index, 'interiors_intersect', counted)
    return calls


def test_only_close_calls_go_to_geos(geos_calls):
    index = FieldOfViewIndex()
    diamond = [(1, 0), (2, 1), (1, 2), (0, 1)]  # a square turned 45°: slanted edges
    index.insert('/d', Polygon(diamond), diamond)
    assert index.query_box((0.9, 0.9, 1.1, 1.1)) == ['/d']  # overlap on every axis
    assert index.query_box((1.6, 1.6, 3, 3)) == []  # beyond the edge x + y = 3
    assert index.query_box((-1, -1, 3, 3)) == ['/d']  # the whole diamond within the region: vertices
    assert index.query_box((2, 0, 3, 3)) == []  # touches the right corner: bounding boxes only touch
    assert index.query_box((1.5, 0.5, 3, 1.5)) == ['/d']  # the right corner inside the region
    assert geos_calls == []
    assert index.query_box((1.5, 1.5, 3, 3)) == []  # its corner on the edge x + y = 3: too close to call
    assert index.query_box((1, 1, 1, 1)) == ['/d']  # a point: GEOS
    assert index.query_box((0.5, 1, 1.5, 1)) == ['/d']  # a segment: GEOS
    assert geos_calls == ['Polygon', 'Point', 'LineString']


def test_non_convex_fields_of_view_go_to_geos_unless_a_vertex_is_inside(geos_calls):
    index = FieldOfViewIndex()
    ell = [(0, 0), (4, 0), (4, 1), (1, 1), (1, 4), (0, 4)]
    index.insert('/l', Polygon(ell))  # outline read from the polygon
    assert index.query_box((-1, -1, 5, 5)) == ['/l']
    assert index.query_box((0.5, 0.5, 1.5, 1.5)) == ['/l']  # the inner corner inside the region
    assert geos_calls == []
    assert index.query_box((2, 2, 3, 3)) == []
    assert geos_calls == ['Polygon']


def test_values_near_zero_are_left_to_geos(geos_calls):
    """GEOS counts this as a match though the bounding boxes only touch (5e-324): the index agrees."""
    points = [(0.0, 0.0), (0.0, 0.5), (0.0, 1.0), (1.0, 9.357972885482116e-08)]
    box = (-1.0, -1.0, 5e-324, 0.0)
    assert relate(points, box)
    index = FieldOfViewIndex()
    index.insert('/p', Polygon(points), points)
    assert index.query_box(box) == ['/p']
    assert geos_calls == ['Polygon']


def test_small_and_huge_fields_of_view_share_the_index():
    index = FieldOfViewIndex()
    fields = {
        '/tiny': [(5, 5), (5.001, 5), (5.001, 5.001)],  # below the finest cells
        '/room': [(0, 0), (8, 0), (8, 6), (0, 6)],
        '/huge': [(-1e5, -1e5), (1e5, -1e5), (0, 1e5)],
    }
    for key, points in fields.items():
        index.insert(key, Polygon(points), points)
    assert sorted(index.query_box((4.9, 4.9, 5.1, 5.1))) == ['/huge', '/room', '/tiny']
    assert index.query_box((-5e4, -9e4, -4e4, -8e4)) == ['/huge']
    # A region far bigger than the finest cells: their occupied cells are visited, not all of them.
    assert sorted(index.query_box((-1e6, -1e6, 1e6, 1e6))) == ['/huge', '/room', '/tiny']
    assert sorted(index.candidates((5, 5, 5, 5))) == ['/huge', '/room', '/tiny']
    index.insert('/tiny', Polygon([(50, 50), (51, 50), (50, 51)]))  # a move
    assert sorted(index.query_box((4.9, 4.9, 5.1, 5.1))) == ['/huge', '/room']
    assert index.query(Polygon([(50.1, 50.1), (50.2, 50.1), (50.1, 50.2)])) == ['/huge', '/tiny']
    assert len(index) == 3 and '/tiny' in index and index.get('/room').area == 48
    for key in fields:
        assert index.remove(key)
    assert not index.remove('/room')
    assert len(index) == 0 and index.query_box((-1e6, -1e6, 1e6, 1e6)) == []
    assert index._levels == {}  # no empty cells left behind


def test_queries_answer_the_values_given():
    index = FieldOfViewIndex()
    index.insert('/a', Polygon(UNIT), UNIT, value=('/a', 1))
    index.insert('/b', Polygon(UNIT))  # no value: the key
    assert sorted(index.query_box((0.2, 0.2, 0.8, 0.8)), key=str) == [('/a', 1), '/b']
    assert index.set_value('/a', ('/a', 2)) and not index.set_value('/c', 3)
    assert sorted(index.candidates((0, 0, 1, 1)), key=str) == [('/a', 2), '/b']
    assert sorted(index.query(Polygon(UNIT)), key=str) == [('/a', 2), '/b']
    index.insert('/a', Polygon(UNIT), UNIT)  # a new polygon: a new value (here the key)
    assert sorted(index.query_box((0.2, 0.2, 0.8, 0.8))) == ['/a', '/b']


def test_concurrent_moves_and_matches():
    registry = Registry(lease=1e9)

    def move(seed):
        rng = random.Random(seed)
        for _ in range(400):
            name, x, y = f'/c{seed}_{rng.randrange(40)}', rng.uniform(0, 30), rng.uniform(0, 30)
            registry.register(name, [(x, y), (x + 2, y), (x + 1, y + 1.5)] if rng.random() < 0.9 else [])

    def match(seed):
        rng = random.Random(seed)
        for _ in range(400):
            x, y = rng.uniform(0, 30), rng.uniform(0, 30)
            registry.match((x, y, x + 3, y + 3))

    threads = [threading.Thread(target=move, args=(seed,)) for seed in range(3)]
    threads += [threading.Thread(target=match, args=(seed,)) for seed in range(3, 5)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    fields = {entry.service_name: entry.field_of_view for entry in registry.entries()}
    rng = random.Random(5)
    for _ in range(100):
        x, y = rng.uniform(-2, 32), rng.uniform(-2, 32)
        box = (x, y, x + rng.uniform(0, 5), y + rng.uniform(0.01, 5))
        assert registry.match(box) == brute_force(fields, box)
