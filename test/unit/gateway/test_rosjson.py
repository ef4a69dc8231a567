"""Messages <-> JSON as rosbridge converts them: field names, time as {secs, nsecs}, bytes as base64,
NaN as null; from JSON, defaults kept and every bad value refused naming its path."""

import math

import pytest
from sensor_msgs.msg import Image

from drvs.gateway.rosjson import FieldError, from_json, to_json
from drvs.ros.conversions import points_to_detected_object
from drvs.ros.gateway_rosbridge import resolve
from drvs.srv import CallbackCoordinates, DetectObjectBoundary

Request = CallbackCoordinates._request_class
BOX = [(1.0, 1.0), (1.4, 1.0), (1.4, 1.4), (1.0, 1.4)]


def callback():
    request = Request(
        vision_system='/cam1/detect_object_boundary', request_id='r1', algorithm='colour', fused=True
    )
    request.stamp.secs, request.stamp.nsecs = 12, 500
    request.objects = [points_to_detected_object(BOX)]
    request.answered = ['/cam1/detect_object_boundary']
    request.gone = [3, 4]
    return request


def test_a_callback_becomes_rosbridge_json_and_back():
    data = to_json(callback())
    assert data['stamp'] == {'secs': 12, 'nsecs': 500}
    assert data['objects'][0]['boundary']['points'][1] == pytest.approx({'x': 1.4, 'y': 1.0, 'z': 0.0})
    assert data['objects'][0]['velocity'] == {'x': 0.0, 'y': 0.0, 'z': 0.0}
    assert (data['gone'], data['fused'], data['status']) == ([3, 4], True, 0)
    again = from_json(data, Request, resolve)
    assert again == callback()


def test_missing_fields_keep_their_defaults():
    request = from_json(
        {'algorithm': 'colour', 'region_of_interest': {'max_x': 4, 'max_y': 4.5}},
        DetectObjectBoundary._request_class,
        resolve,
    )
    assert (request.algorithm, request.region_of_interest.max_y, request.callback_service, request.fused) == (
        'colour',
        4.5,
        '',
        False,
    )


def test_not_finite_numbers_become_null():
    request = callback()
    request.objects[0].confidence = math.nan
    assert to_json(request)['objects'][0]['confidence'] is None


def test_bytes_are_base64_both_ways():
    image = Image(height=1, width=3, encoding='mono8', step=3, data=b'\x00\x7f\xff')
    data = to_json(image)
    assert data['data'] == 'AH//'
    assert from_json(data, Image, resolve).data == b'\x00\x7f\xff'
    assert from_json({'data': [1, 2]}, Image, resolve).data == b'\x01\x02'


@pytest.mark.parametrize(
    ('data', 'field'),
    [
        ({'colour': 1}, 'colour'),
        ({'algorithm': 5}, 'algorithm'),
        ({'fused': 1}, 'fused'),
        ({'status': 256}, 'status'),
        ({'status': -1}, 'status'),
        ({'gone': [1, 'a']}, 'gone[1]'),
        ({'gone': 'abc'}, 'gone'),
        ({'stamp': 12.5}, 'stamp'),
        ({'stamp': {'secs': 1, 'sec': 2}}, 'stamp'),
        ({'stamp': {'secs': 2**40}}, 'stamp.secs'),
        ({'objects': [{'boundary': {'points': [{'x': 'left'}]}}]}, 'objects[0].boundary.points[0].x'),
        ({'objects': [{'label': True}]}, 'objects[0].label'),
        ({'objects': {}}, 'objects'),
        ({'objects': [7]}, 'objects[0]'),
        ({'objects': [{'velocity': {'x': True}}]}, 'objects[0].velocity.x'),
    ],
)
def test_bad_values_are_refused_naming_their_path(data, field):
    with pytest.raises(FieldError) as refused:
        from_json(data, Request, resolve)
    assert refused.value.field == field


def test_only_an_object_fills_a_message():
    with pytest.raises(FieldError) as refused:
        from_json([1], Request, resolve)
    assert refused.value.field == 'args'
