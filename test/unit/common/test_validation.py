"""Validation of what callers send the server: every refusal names the field and the problem."""

import math

import pytest

from drvs.algorithms import AlgorithmError
from drvs.common.validation import (
    ValidationError,
    field_of_view_polygon,
    global_ros_name,
    region_geometry,
    region_of_interest,
    request_fields,
)

SQUARE = [(0, 0), (1, 0), (1, 1), (0, 1)]


@pytest.mark.parametrize(
    'points, message',
    [
        ([], 'field_of_view: 0 vertices; a polygon needs at least 3'),
        ([(0, 0), (1, 1)], 'field_of_view: 2 vertices; a polygon needs at least 3'),
        (
            [(0, 0), (1, math.nan), (1, 1)],
            'field_of_view: vertex 1 is (1.0, nan); coordinates must be finite',
        ),
        (
            [(0, 0), (1, 0), (math.inf, 1)],
            'field_of_view: vertex 2 is (inf, 1.0); coordinates must be finite',
        ),
        ([(0, 0), (1, 1), (2, 2)], 'field_of_view: zero area (all vertices lie on one line)'),
        ([(0, 0), (0, 0), (0, 0)], 'field_of_view: zero area (all vertices lie on one line)'),
        ([(0, 0), (2, 2), (2, 0), (0, 2)], 'field_of_view: the outline crosses itself at (1, 1)'),
        (
            [(0, 0), (4, 0), (4, 2), (2, 2), (2, -1), (0, 2)],
            'field_of_view: the outline crosses itself at (1.33333, 0)',
        ),
    ],
)
def test_bad_field_of_view(points, message):
    with pytest.raises(ValidationError) as caught:
        field_of_view_polygon(points)
    assert str(caught.value) == message


@pytest.mark.parametrize(
    'points',
    [
        SQUARE,
        SQUARE + [(0, 0)],  # closed ring
        list(reversed(SQUARE)),  # clockwise
        [(0, 0), (3, 0), (3, 3), (2, 3), (2, 1), (1, 1), (1, 3), (0, 3)],  # non-convex (a U)
        [(0, 0), (100, 0), (100, 1e-6)],  # very thin
    ],
)
def test_good_field_of_view(points):
    polygon = field_of_view_polygon(points)
    assert polygon.is_valid and polygon.area > 0


@pytest.mark.parametrize(
    'box, message',
    [
        ((math.nan, 0, 1, 1), 'region_of_interest: min_x is nan; coordinates must be finite'),
        ((0, -math.inf, 1, 1), 'region_of_interest: min_y is -inf; coordinates must be finite'),
        ((0, 0, math.inf, 1), 'region_of_interest: max_x is inf; coordinates must be finite'),
        ((0, 0, 1, math.nan), 'region_of_interest: max_y is nan; coordinates must be finite'),
        ((2, 0, 1, 1), 'region_of_interest: min_x 2 is greater than max_x 1'),
        ((0, 1.5, 1, 0.25), 'region_of_interest: min_y 1.5 is greater than max_y 0.25'),
    ],
)
def test_bad_region_of_interest(box, message):
    with pytest.raises(ValidationError) as caught:
        region_of_interest(box)
    assert str(caught.value) == message


@pytest.mark.parametrize(
    'box, kind',
    [
        ((0, 0, 1, 1), 'Polygon'),
        ((0, 0, 0, 1), 'LineString'),
        ((0, 1, 2, 1), 'LineString'),
        ((1, 1, 1, 1), 'Point'),
    ],
)
def test_region_geometry(box, kind):
    assert region_geometry(region_of_interest(box)).geom_type == kind


@pytest.mark.parametrize(
    'name, message',
    [
        ('', 'callback_service: empty; expected a ROS name such as /robot/callback_coordinates'),
        (
            'robot/callback',
            "callback_service: 'robot/callback' is not a global ROS name (it must start with /)",
        ),
        ('~callback', "callback_service: '~callback' is not a global ROS name (it must start with /)"),
        ('/robot//x', "callback_service: '/robot//x' is not a valid ROS name"),
        ('/robot/9x', "callback_service: '/robot/9x' is not a valid ROS name"),
        ('/robot/call back', "callback_service: '/robot/call back' is not a valid ROS name"),
        ('/' + 'a' * 300, 'callback_service: 301 characters, longer than the limit of 256'),
    ],
)
def test_bad_callback_service(name, message):
    with pytest.raises(ValidationError) as caught:
        global_ros_name('callback_service', name)
    assert str(caught.value) == message


@pytest.mark.parametrize(
    'algorithm, message',
    [
        ('', 'algorithm: empty; expected NAME:PARAMS, e.g. colour:0,0,150,80,80,255'),
        ('x' * 513, 'algorithm: 513 characters, longer than the limit of 512'),
        (
            'colour',
            'algorithm: colour PARAMS must be 6 comma-separated integers RMIN,GMIN,BMIN,RMAX,GMAX,BMAX, '
            "got 1 value(s) in ''",
        ),
        (
            'shape:round',
            "algorithm: unknown NAME 'shape'; known: apriltag, colour, elevation, foreground, motion",
        ),
        ('colour:0,0,0,300,0,0', 'algorithm: colour RMAX must be in 0-255, got 300'),
    ],
)
def test_request_fields_use_the_shared_algorithm_parser(algorithm, message):
    with pytest.raises(AlgorithmError) as caught:
        request_fields(algorithm, (0, 0, 1, 1), '/robot/callback_coordinates')
    assert str(caught.value) == message


def test_request_fields_accepts_a_good_request():
    model, region = request_fields('colour:0,0,150,80,80,255', (0, 0, 1, 2), '/robot/callback_coordinates')
    assert model.params.format() == 'colour:0,0,150,80,80,255'
    assert region == (0.0, 0.0, 1.0, 2.0)
