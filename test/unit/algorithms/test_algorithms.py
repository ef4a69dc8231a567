"""The shared algorithm definitions: parsing, refusals, colour segmentation on drawn images."""

import math

import cv2
import numpy as np
import pytest

from drvs.algorithms import MAX_LENGTH, AlgorithmError, ColourModel, PixelObject, parse_algorithm


def test_colour_parses_and_formats_back():
    parsed = parse_algorithm('colour:0,0,150,80,80,255')
    assert (parsed.name, parsed.params) == ('colour', ColourModel((0, 0, 150), (80, 80, 255)))
    assert parse_algorithm(parsed.params.format()).params == parsed.params


@pytest.mark.parametrize(
    'text, message',
    [
        ('', 'algorithm: empty; expected NAME:PARAMS, e.g. colour:0,0,150,80,80,255'),
        ('colour:' + '1,' * 300, f'algorithm: 607 characters, longer than the limit of {MAX_LENGTH}'),
        (
            'colour',
            'algorithm: colour PARAMS must be 6 comma-separated integers RMIN,GMIN,BMIN,RMAX,GMAX,BMAX, '
            "got 1 value(s) in ''",
        ),
        (
            ':1,2',
            'algorithm: expected NAME[:PARAMS] with NAME a letter then letters, digits or _, '
            "e.g. colour:0,0,150,80,80,255, got ':1,2'",
        ),
        (
            '9lives:1',
            'algorithm: expected NAME[:PARAMS] with NAME a letter then letters, digits or _, '
            "e.g. colour:0,0,150,80,80,255, got '9lives:1'",
        ),
        ('sift:1', "algorithm: unknown NAME 'sift'; known: apriltag, colour, elevation, foreground, motion"),
        (
            'colour:1,2,3',
            'algorithm: colour PARAMS must be 6 comma-separated integers RMIN,GMIN,BMIN,RMAX,GMAX,BMAX, '
            "got 3 value(s) in '1,2,3'",
        ),
        ('colour:1,2,3,4,5,x', "algorithm: colour BMAX must be an integer 0-255, got 'x'"),
        ('colour:1,2,3,4,5,1.5', "algorithm: colour BMAX must be an integer 0-255, got '1.5'"),
        ('colour:0,0,0,256,0,0', 'algorithm: colour RMAX must be in 0-255, got 256'),
        ('colour:0,-1,0,0,0,0', 'algorithm: colour GMIN must be in 0-255, got -1'),
        ('colour:0,0,200,0,0,100', 'algorithm: colour BMIN 200 is greater than BMAX 100'),
    ],
)
def test_bad_algorithms_are_refused_with_a_message(text, message):
    with pytest.raises(AlgorithmError) as error:
        parse_algorithm(text)
    assert str(error.value) == message


def test_colour_finds_each_region_with_edge_exact_outlines():
    image = np.full((120, 160, 3), 255, np.uint8)
    image[10:30, 20:60] = (0, 0, 200)  # 40 x 20 blue rectangle
    cv2.circle(image, (120, 80), 15, (0, 0, 200), -1)
    image[100:110, 10:20] = (0, 200, 0)  # green: another model
    image[60:62, 5:7] = (0, 0, 200)  # 4 pixels: below the minimum area
    objects = ColourModel.parse('0,0,150,80,80,255').detect(image, min_area=20)
    assert len(objects) == 2
    rectangle = min(objects, key=lambda o: o.outline[:, 0].min())
    assert sorted(map(tuple, rectangle.outline)) == [(20, 10), (20, 30), (60, 10), (60, 30)]
    assert rectangle.area == pytest.approx(800)
    circle = max(objects, key=lambda o: o.outline[:, 0].min())
    pixels = int((np.all(image == (0, 0, 200), axis=2)[:, 90:]).sum())
    assert circle.area == pytest.approx(pixels, rel=0.03)
    assert circle.outline.mean(axis=0) == pytest.approx((120.5, 80.5), abs=0.5)


def test_colour_finds_nothing_in_an_empty_image():
    assert ColourModel.parse('0,0,150,80,80,255').detect(np.full((50, 50, 3), 255, np.uint8)) == []


def test_a_pixel_objects_confidence_defaults_to_unknown_and_must_lie_in_0_to_1():
    outline = np.array([(0.0, 0.0), (1.0, 0.0), (1.0, 1.0)])
    assert PixelObject(outline, 0.5).confidence == 0.0
    assert PixelObject(outline, 0.5, confidence=np.float32(0.25)).confidence == 0.25
    for bad, problem in (
        (1.5, 'must be in 0-1, got 1.5'),
        (-0.1, 'must be in 0-1, got -0.1'),
        (math.nan, 'must be in 0-1, got nan'),
        ('high', "must be a number 0-1, got 'high'"),
        (True, 'must be a number 0-1, got True'),
    ):
        with pytest.raises(ValueError) as error:
            PixelObject(outline, 0.5, confidence=bad)
        assert str(error.value) == f'PixelObject: confidence {problem}'
