"""The vision_system node's wiring, without a master: the server's answers to its registrations
reach the health report and ``~stats``, and a bug in a handler is answered with a status.

When to register is :mod:`drvs.vision.registration`'s (test/unit/vision/test_registration.py).
"""

import pytest

from drvs.common.health import ERROR, OK, WARN
from drvs.common.status import ACCEPTED, BUSY, INVALID, UNAVAILABLE
from drvs.ros.service_client import ServiceCallError
from drvs.ros.vision_system import VisionSystemNode
from drvs.srv import (
    DetectObjectBoundaryRequest,
    RegisterVisionServiceResponse,
    WatchObjectBoundaryRequest,
)
from drvs.testing import ManualClock
from drvs.vision.params import VisionSystemParams
from drvs.vision.registration import Registration

FLOOR = [(0.0, 0.0), (2.0, 0.0), (2.0, 1.0), (0.0, 1.0)]


class Publisher:
    def __init__(self):
        self.messages = []

    def publish(self, message):
        self.messages.append(message)

    def get_num_connections(self):
        return 0


class RegisterService:
    """The server's RegisterVisionService as the node's client sees it: one scripted answer a call."""

    def __init__(self, *answers):
        self.answers = list(answers)
        self.requests = []

    def call(self, request):
        self.requests.append(request)
        answer = self.answers.pop(0)
        if isinstance(answer, Exception):
            raise answer
        return answer


def answer(status=ACCEPTED, message='', lease=10.0, retry_after=0.0):
    return RegisterVisionServiceResponse(
        accepted=status == ACCEPTED, status=status, message=message, retry_after=retry_after, lease=lease
    )


@pytest.fixture
def clock(monkeypatch):
    clock = ManualClock(100.0)
    monkeypatch.setattr('rospy.get_time', clock)  # no master: ROS time is the test's
    monkeypatch.setattr('rospy.logwarn_throttle', lambda period, text, *args: None)  # it reads ROS time
    return clock


def vision_system(clock, *answers, footprint=FLOOR):
    """A topic vision system, not started: its publishers and the server are fakes."""
    node = VisionSystemNode(VisionSystemParams(camera='cam1', source='topic'))
    node.stats_pub, node.debug_pub = Publisher(), Publisher()
    node._register_client = RegisterService(*answers)
    node.service_name = '/cam1/detect_object_boundary'
    node.registration = Registration(0.01, 1.0, clock=clock, rng=lambda: 0.0)
    node.source.footprint = lambda: footprint
    node.source.frame_age = lambda: 0.05  # frames flow
    return node


def test_an_accepted_registration_sends_the_field_of_view_and_the_algorithms_and_is_counted(clock):
    node = vision_system(clock, answer(lease=8.0))
    node._registration_tick()
    (request,) = node._register_client.requests
    assert request.service_name == '/cam1/detect_object_boundary'
    assert [(p.x, p.y) for p in request.field_of_view.points] == FLOOR
    assert request.algorithms == node.algorithms.names() and 'colour' in request.algorithms
    assert node.node.counters['registrations'] == 1
    node._publish_stats()  # (the tick published ~stats just before: this count came too soon)
    assert node.stats_pub.messages[-1].registrations == 1
    assert (node.health().level, node.registration.lease) == (OK, 8.0)
    node._registration_tick()  # not due again before half the lease
    assert len(node._register_client.requests) == 1


@pytest.mark.parametrize(
    'reply, level, message',
    [
        (ServiceCallError('no service /drvs/register_vision_service'), WARN,
         'not registered: no service /drvs/register_vision_service'),
        (answer(BUSY, 'busy: try later', retry_after=0.5), WARN,
         'not registered: refused BUSY: busy: try later'),
        (answer(INVALID, 'field_of_view: too few points'), ERROR,
         'registration refused INVALID: field_of_view: too few points'),
    ],
)  # fmt: skip
def test_a_failed_registration_is_in_the_health_report(clock, reply, level, message):
    node = vision_system(clock, reply)
    node._registration_tick()
    health = node.health()
    assert (health.level, health.message) == (level, message)
    assert node.node.counters['registrations'] == 0


def test_a_clean_stop_unregisters(clock):
    node = vision_system(clock, answer(), answer())
    node._registration_tick()
    node.node.stop()
    farewell = node.registration.farewell()
    node._register(farewell)
    assert node._register_client.requests[-1].field_of_view.points == []
    assert node.node.counters['registrations'] == 2 and not node.registration.report().registered


@pytest.mark.parametrize(
    'handler, request_class, refused',
    [('_handle_detect', DetectObjectBoundaryRequest, 1), ('_handle_watch', WatchObjectBoundaryRequest, 0)],
)
def test_a_bug_in_a_handler_is_answered_unavailable_naming_the_error(
    clock, monkeypatch, handler, request_class, refused
):
    node = vision_system(clock)

    def broken(request):
        raise RuntimeError('boom')

    monkeypatch.setattr(node, handler.replace('_handle', ''), broken)
    response = getattr(node, handler)(request_class(request_id='r1'))
    assert (response.accepted, response.status, response.retry_after) == (False, UNAVAILABLE, 1.0)
    assert response.message == (
        'internal error in vision system /unnamed (RuntimeError: boom); it is logged there; retry later'
    )
    assert node.node.counters['refused'] == refused


def test_stats_count_accepted_requests_per_algorithm_string_up_to_a_bound(clock):
    node = vision_system(clock)
    node._publish_stats()
    for index in range(70):
        node._count_algorithm(f'colour:{index}')
    node._count_algorithm('colour:0')
    node._publish_stats()  # the algorithm counts alone changed ~stats
    message = node.stats_pub.messages[-1]
    counts = dict(zip(message.algorithms, message.algorithm_requests, strict=True))
    assert len(counts) == 65 and counts['colour:0'] == 2 and counts['other'] == 6
    node._publish_stats()
    assert len(node.stats_pub.messages) == 2  # nothing changed since
