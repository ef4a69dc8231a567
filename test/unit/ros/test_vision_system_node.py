"""The vision_system node's wiring, without a master: the server's answers to its registrations
reach the health report and ``~stats``, a bug in a handler is answered with a status, and the
callbacks carry the algorithm's confidence.

When to register is :mod:`drvs.vision.registration`'s (test/unit/vision/test_registration.py).
"""

import numpy as np
import pytest

from drvs.common.health import ERROR, OK, WARN
from drvs.common.status import ACCEPTED, BUSY, INVALID, UNAVAILABLE
from drvs.ros.service_client import ServiceCallError
from drvs.ros.vision_system import VisionSystemNode
from drvs.srv import (
    CallbackCoordinatesRequest,
    DetectObjectBoundaryRequest,
    RegisterVisionServiceResponse,
    WatchObjectBoundaryRequest,
)
from drvs.testing import ManualClock
from drvs.vision.camera import PinholeCamera
from drvs.vision.detections import Job
from drvs.vision.frame import Frame
from drvs.vision.params import VisionSystemParams
from drvs.vision.registration import Registration
from drvs.vision.watch_runner import parse_watch

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


def vision_system(clock, *answers, footprint=FLOOR, **params):
    """A topic vision system, not started: its publishers and the server are fakes."""
    node = VisionSystemNode(VisionSystemParams(camera='cam1', source='topic', **params))
    node.stats_pub, node.debug_pub = Publisher(), Publisher()
    node._register_client = RegisterService(*answers)  # the test's handle on the first server's
    node._register_clients = {node.servers.current: node._register_client}
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


def test_no_answer_or_unavailable_moves_to_the_next_server_which_registers_it(clock):
    """~servers: registered through /drvs, which stops answering; renewed through /drvs_b, then back."""
    node = vision_system(clock, answer(), ServiceCallError('connection refused'), servers='/drvs,/drvs_b')
    second = RegisterService(answer(), answer(UNAVAILABLE, 'the registry database is unreachable'))
    node._register_clients['/drvs_b/register_vision_service'] = second
    node._registration_tick()
    clock.now += 5.0  # half the lease: renewed, but /drvs does not answer
    node._registration_tick()
    assert node.servers.current == '/drvs_b/register_vision_service'
    clock.now += 0.2  # the retry, at once through /drvs_b (every call carries the registration)
    node._registration_tick()
    assert [r.service_name for r in second.requests] == ['/cam1/detect_object_boundary']
    assert node.registration.report().registered
    values = dict(node.health().values)
    assert (values['DRVS server'], values['server moves']) == ('/drvs_b/register_vision_service', '1')
    clock.now += 5.0
    node._registration_tick()  # UNAVAILABLE: the next one again
    assert (node.servers.current, node.servers.moves) == ('/drvs/register_vision_service', 2)


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


class CallbackClients:
    """The sender's connections to the robots' callback services: one client for all that keeps
    each request as the robot would receive it (deserialised from the bytes sent)."""

    def __init__(self):
        self.requests = []

    def get(self, service):
        return self

    def call(self, request, serialized):
        self.requests.append(CallbackCoordinatesRequest().deserialize(serialized))

    def expire(self):
        pass


BLUE = 'colour:0,0,150,80,80,255'


def square_with_a_hole(hole):
    """A frame straight down on a blue 40 x 40 pixel square with a white ``hole`` x ``hole`` one in it."""
    rgb = np.full((300, 400, 3), 255, np.uint8)
    rgb[130:170, 180:220] = (0, 0, 200)
    rgb[150 - hole // 2 : 150 + (hole + 1) // 2, 200 - hole // 2 : 200 + (hole + 1) // 2] = 255
    camera = PinholeCamera(eye=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0), fov_deg=60, width=400, height=300)
    return Frame(rgb=rgb, depth=None, camera=camera, stamp=100.0)


def test_callbacks_carry_the_algorithms_confidence_and_changes_only_ignores_it(clock):
    node = vision_system(clock)
    clients = CallbackClients()
    node.callbacks._clients, node.callbacks.markers_pub = clients, Publisher()
    frames = [square_with_a_hole(20)]  # colour's confidence: 1200 of the 1600 pixels blue
    node.source.frame = lambda arrival: (frames[-1], False)
    job = Job(node.algorithms.parse(BLUE), (-5.0, -5.0, 5.0, 5.0), '/robot/callback', 'once', clock())
    node._process(job)
    (request,) = clients.requests
    assert [o.confidence for o in request.objects] == [0.75]

    terms = parse_watch(BLUE, (-5, -5, 5, 5), '/robot/callback', 'watch', 0.5, 10.0, True, node.algorithms)
    node.watches.stand(terms, 10.0, clock())
    node._evaluate_watches(node.watches.due(clock()), clock())
    assert [o.confidence for o in clients.requests[-1].objects] == [0.75]
    frames.append(square_with_a_hole(10))  # the same outline, more solidly filled
    clock.now += 0.5
    node._evaluate_watches(node.watches.due(clock()), clock())
    assert len(clients.requests) == 2  # changes_only: the outline stood still; no callback
    frames.append(square_with_a_hole(0))
    node.watches.callback_failed(terms)  # the robot may hold anything: the next evaluation reports
    clock.now += 0.5
    node._evaluate_watches(node.watches.due(clock()), clock())
    assert [o.confidence for o in clients.requests[-1].objects] == [1.0]


def test_elevation_without_usable_depth_is_refused_saying_why_and_reported_until_depth_works(clock):
    from dataclasses import replace

    from drvs.msg import BoundingBox
    from drvs.testing.depth import Box, depth_frame

    node = vision_system(clock, depth=True)
    assert 'elevation' in node.algorithms  # a topic camera with ~depth registers it; without, not:
    assert 'elevation' not in vision_system(clock).algorithms
    clients = CallbackClients()
    node.callbacks._clients, node.callbacks.markers_pub = clients, Publisher()
    camera = PinholeCamera(eye=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0), fov_deg=60, width=160, height=120)
    good = depth_frame(camera, [Box((0.0, 0.0), (0.4, 0.4, 0.5))], stamp=100.0)
    holes = replace(good, depth=np.zeros((120, 160), np.float32))
    frames = [holes]
    node.source.latest = lambda: frames[-1]
    node.source.frame = lambda arrival: (frames[-1], False)
    node.source.unavailable = lambda: None  # frames flow
    problem = 'elevation: the depth image has no valid pixel (every one 0, NaN or infinite)'

    def ask(request_id):
        region = BoundingBox(-1.0, -1.0, 1.0, 1.0)
        request = DetectObjectBoundaryRequest('elevation', region, '/robot/callback', request_id, False, '')
        return node._handle_detect(request)

    response = ask('r1')
    assert (response.accepted, response.status, response.message) == (False, UNAVAILABLE, problem)
    # A request accepted before the problem showed: no callback, the problem on the health report.
    node._process(
        Job(node.algorithms.parse('elevation'), (-1.0, -1.0, 1.0, 1.0), '/robot/callback', 'r0', clock())
    )
    assert clients.requests == [] and problem in node.health().message
    frames.append(good)  # the newest frame works: the problem met before is over
    assert ask('r2').accepted
    node._process(
        Job(node.algorithms.parse('elevation'), (-1.0, -1.0, 1.0, 1.0), '/robot/callback', 'r2', clock())
    )
    (request,) = clients.requests
    assert [round(o.height, 2) for o in request.objects] == [0.5]
    assert 'elevation' not in node.health().message


def test_a_colour_request_does_not_look_at_a_frame_before_it_is_queued(clock):
    """Only algorithms that can refuse a frame (elevation, foreground) have one decoded at once."""
    from drvs.msg import BoundingBox

    node = vision_system(clock)
    node.source.unavailable = lambda: None
    looked = []
    node.source.latest = lambda: looked.append(1)
    request = DetectObjectBoundaryRequest(
        BLUE, BoundingBox(0.0, 0.0, 1.0, 1.0), '/robot/callback', 'c1', False, ''
    )
    assert node._handle_detect(request).accepted
    assert looked == []
    request.algorithm = 'foreground'
    node._handle_detect(request)
    assert looked == [1]


def test_a_callback_uri_is_checked_and_the_callback_goes_to_that_address(clock):
    from drvs.msg import BoundingBox

    node = vision_system(clock)
    node.source.unavailable = lambda: None
    node.source.latest = lambda: None
    region = BoundingBox(0.0, 0.0, 1.0, 1.0)
    bad = DetectObjectBoundaryRequest(BLUE, region, '/robot/callback', 'c1', False, 'robot-a:4100')
    refused = node._handle_detect(bad)
    assert (refused.accepted, refused.status, refused.message) == (
        False,
        INVALID,
        "callback_uri: 'robot-a:4100' is not a rosrpc://HOST:PORT address",
    )
    good = DetectObjectBoundaryRequest(BLUE, region, '/robot/callback', 'c2', True, 'rosrpc://robot-a:4100')
    assert node._handle_detect(good).accepted
    asked = []
    clients = CallbackClients()
    clients.get = lambda key: asked.append(key) or clients
    node.callbacks._clients, node.callbacks.markers_pub = clients, Publisher()
    node.callbacks.send(node._jobs.get_nowait(), node.service_name, 1.0, [])
    assert asked == [('/robot/callback', 'rosrpc://robot-a:4100')] and len(clients.requests) == 1
