"""The generated drvs types: importable, faithful to docs/design.md, and round-trip serialisable."""

import pytest
from geometry_msgs.msg import Point32, Polygon

from drvs.msg import BoundingBox, DetectedObject
from drvs.srv import (
    CallbackCoordinates,
    CallbackCoordinatesRequest,
    DetectObjectBoundary,
    DetectObjectBoundaryRequest,
    DetectObjectBoundaryResponse,
    RegisterVisionService,
    RegisterVisionServiceRequest,
    RegisterVisionServiceResponse,
)
from drvs.testing.messages import round_trip


def square(x, y, side=0.5):
    return Polygon(
        points=[
            Point32(x, y, 0),
            Point32(x + side, y, 0),
            Point32(x + side, y + side, 0),
            Point32(x, y + side, 0),
        ]
    )


@pytest.mark.parametrize(
    'cls, slots, types',
    [
        (BoundingBox, ['min_x', 'min_y', 'max_x', 'max_y'], ['float64'] * 4),
        (
            DetectedObject,
            [
                'boundary',
                'bounding_box',
                'label',
                'height',
                'clearance',
                'track_id',
                'confidence',
                'velocity',
                'stationary',
                'seen_by',
            ],
            [
                'geometry_msgs/Polygon',
                'drvs/BoundingBox',
                'string',
                'float32',
                'float32',
                'uint32',
                'float32',
                'geometry_msgs/Vector3',
                'bool',
                'string[]',
            ],
        ),
        (
            DetectObjectBoundaryRequest,
            ['algorithm', 'region_of_interest', 'callback_service', 'request_id', 'fused', 'callback_uri'],
            ['string', 'drvs/BoundingBox', 'string', 'string', 'bool', 'string'],
        ),
        (
            DetectObjectBoundaryResponse,
            ['accepted', 'status', 'message', 'vision_systems', 'retry_after'],
            ['bool', 'uint8', 'string', 'uint32', 'float32'],
        ),
        (
            CallbackCoordinatesRequest,
            [
                'algorithm',
                'request_id',
                'vision_system',
                'stamp',
                'objects',
                'fused',
                'status',
                'message',
                'answered',
                'refused',
                'missing',
                'gone',
            ],
            [
                'string',
                'string',
                'string',
                'time',
                'drvs/DetectedObject[]',
                'bool',
                'uint8',
                'string',
                'string[]',
                'string[]',
                'string[]',
                'uint32[]',
            ],
        ),
        (
            RegisterVisionServiceRequest,
            ['service_name', 'field_of_view', 'algorithms'],
            ['string', 'geometry_msgs/Polygon', 'string[]'],
        ),
        (
            RegisterVisionServiceResponse,
            ['accepted', 'status', 'message', 'lease', 'retry_after'],
            ['bool', 'uint8', 'string', 'float32', 'float32'],
        ),
    ],
)
def test_fields_match_the_contract(cls, slots, types):
    assert cls.__slots__ == slots
    assert cls._slot_types == types


def test_service_types_are_named_in_the_drvs_package():
    assert DetectObjectBoundary._type == 'drvs/DetectObjectBoundary'
    assert CallbackCoordinates._type == 'drvs/CallbackCoordinates'
    assert RegisterVisionService._type == 'drvs/RegisterVisionService'


def test_detect_object_boundary_round_trips():
    request = DetectObjectBoundaryRequest(
        algorithm='colour:0,0,150,80,80,255',
        region_of_interest=BoundingBox(0.5, -1.25, 7.0, 5.5),
        callback_service='/robot/callback_coordinates',
        request_id='station-7',
    )
    assert round_trip(request) == request
    response = DetectObjectBoundaryResponse(accepted=True, message='', vision_systems=2)
    assert round_trip(response) == response
    refused = DetectObjectBoundaryResponse(
        accepted=False, status=DetectObjectBoundaryResponse.BUSY, message='busy', retry_after=0.5
    )
    assert round_trip(refused) == refused


def test_callback_coordinates_round_trips_with_objects():
    import genpy

    objects = [
        DetectedObject(boundary=square(1.0, 2.0), bounding_box=BoundingBox(1.0, 2.0, 1.5, 2.5)),
        DetectedObject(boundary=square(4.0, 0.0, 0.25), bounding_box=BoundingBox(4.0, 0.0, 4.25, 0.25)),
    ]
    request = CallbackCoordinatesRequest(
        algorithm='colour:0,150,0,80,255,80',
        request_id='self-1',
        vision_system='/vs2/detect_object_boundary',
        stamp=genpy.Time(12, 345),
        objects=objects,
    )
    copy = round_trip(request)
    assert copy == request
    assert copy.objects[1].boundary.points[2].x == pytest.approx(4.25)


def test_register_vision_service_round_trips():
    request = RegisterVisionServiceRequest(
        service_name='/vs1/detect_object_boundary', field_of_view=square(0.0, 0.0, 3.0)
    )
    assert round_trip(request) == request
    response = RegisterVisionServiceResponse(
        accepted=False, status=RegisterVisionServiceResponse.INVALID, message='polygon has 2 vertices'
    )
    assert round_trip(response) == response
    granted = RegisterVisionServiceResponse(accepted=True, lease=10.0)
    assert round_trip(granted).lease == 10.0


@pytest.mark.parametrize('response_class', [DetectObjectBoundaryResponse, RegisterVisionServiceResponse])
def test_status_constants_match_drvs_status(response_class):
    """Code without ROS (drvs.common.status) and the .srv constants that `rossrv show` lists agree."""
    from drvs.common import status

    for code, name in status.NAMES.items():
        assert getattr(response_class, name) == code
    assert response_class().status == status.ACCEPTED


def test_a_detected_object_carries_its_measured_height_and_defaults_to_unknown():
    from drvs.ros.conversions import points_to_detected_object

    outline = [(1.0, 2.0), (1.5, 2.0), (1.5, 2.5)]
    assert round_trip(points_to_detected_object(outline, 'x', 0.5, 0.75)).height == pytest.approx(0.75)
    assert round_trip(points_to_detected_object(outline, clearance=0.4)).clearance == pytest.approx(0.4)
    assert round_trip(points_to_detected_object(outline)).height == 0.0


def test_the_fusion_stage_passes_heights_through_its_tracker():
    from drvs.ros.conversions import points_to_detected_object
    from drvs.ros.server_fusion import detected_object, observations
    from drvs.server.tracker import Tracker

    outline = [(1.0, 2.0), (1.5, 2.0), (1.5, 2.5), (1.0, 2.5)]
    (seen,) = observations([points_to_detected_object(outline, height=0.75, clearance=0.4)])
    assert (seen.height, seen.clearance) == pytest.approx((0.75, 0.4))
    tracker = Tracker()
    tracker.frame('/vs1', 0.0, [seen])
    (track,) = tracker.tracks(0.0)
    sent = round_trip(detected_object(track))
    assert (sent.height, sent.clearance) == pytest.approx((0.75, 0.4))


def test_the_gateway_gives_every_field_of_a_detected_object():
    from drvs.gateway.routes import SCHEMAS
    from drvs.ros.conversions import points_to_detected_object
    from drvs.ros.gateway import object_to_dict

    detected = points_to_detected_object([(1.0, 2.0), (1.5, 2.0), (1.5, 2.5)], height=0.75, clearance=0.4)
    data = object_to_dict(detected)
    assert list(data) == list(DetectedObject.__slots__) == list(SCHEMAS['Object']['properties'])
    assert (data['height'], data['clearance']) == pytest.approx((0.75, 0.4))
