"""The DRVS server node with a private roscore, fake vision systems and a callback recorder."""

import math

import pytest
from geometry_msgs.msg import Polygon

from drvs.common.status import INVALID, UNSUPPORTED
from drvs.msg import BoundingBox
from drvs.ros.conversions import points_to_polygon
from drvs.ros.service_client import ServiceCallError, ServiceClient
from drvs.srv import CallbackCoordinates, DetectObjectBoundary, RegisterVisionService
from drvs.testing import echo, points, read_json_lines, wait_for

pytestmark = pytest.mark.shared_master  # see test/conftest.py

SERVER = 'nodes/drvs_server'
FAKE = 'test/nodes/fake_vision_system.py'
RECORDER = 'test/nodes/callback_recorder.py'
COLOUR = 'colour:0,0,150,80,80,255'
CALLBACK = '/robot/callback_coordinates'


def square(x0, y0, x1, y1):
    return [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]


class Graph:
    """A server, a callback recorder and fake cameras on the test's private master."""

    def __init__(self, ros, monkeypatch, tmp_path, **params):
        self.ros, self.tmp_path = ros, tmp_path
        monkeypatch.setenv('ROS_MASTER_URI', ros.master.uri)
        monkeypatch.setenv('ROS_HOSTNAME', '127.0.0.1')
        self.server = ros.start_node(SERVER, name='drvs', params=params)
        recorder = ros.start_node(RECORDER, name='robot', params={'output': tmp_path / 'callbacks.jsonl'})
        ros.wait_for_service('/drvs/detect_object_boundary', node=self.server)
        ros.wait_for_service('/drvs/register_vision_service', node=self.server)
        ros.wait_for_service(CALLBACK, node=recorder)
        self.detect_client = ServiceClient('/drvs/detect_object_boundary', DetectObjectBoundary, 10.0)
        self.register_client = ServiceClient('/drvs/register_vision_service', RegisterVisionService, 10.0)

    def close(self):
        self.detect_client.close()
        self.register_client.close()

    def camera(self, name, fov, wait=True, **params):
        output = self.tmp_path / f'{name}.jsonl'
        node = self.ros.start_node(FAKE, name=name, params={'output': output, 'field_of_view': fov, **params})
        if wait:
            wait_for(
                lambda: self.registrations(name), 30, f'{name} registration', on_timeout=self.ros.describe
            )
            assert self.registrations(name)[-1]['accepted'], self.registrations(name)
        return node

    def records(self, name, kind):
        return [r for r in read_json_lines(self.tmp_path / f'{name}.jsonl') if r['kind'] == kind]

    def registrations(self, name):
        return self.records(name, 'register')

    def forwards(self, name):
        return self.records(name, 'forward')

    def detect(self, box, request_id='r1', algorithm=COLOUR, callback=CALLBACK):
        request = DetectObjectBoundary._request_class(
            algorithm=algorithm,
            region_of_interest=BoundingBox(*box),
            callback_service=callback,
            request_id=request_id,
        )
        return self.detect_client.call(request)

    def register(self, service_name, points):
        request = RegisterVisionService._request_class(service_name=service_name, field_of_view=points)
        return self.register_client.call(request)

    def registry_topic(self):
        """The latched /drvs/registry (drvs/Registry), each field_of_view as [[x, y], ...]."""
        registry = echo(self.ros, '/drvs/registry')
        for entry in registry['vision_systems']:
            entry['field_of_view'] = points(entry['field_of_view'])
        return registry


def forwarded_ids(graph, name):
    return [r['request_id'] for r in graph.forwards(name)]


def test_routes_to_overlapping_systems_unchanged_and_follows_moves(ros, make_graph):
    graph = make_graph()
    graph.camera('vs1', square(0, 0, 2, 2))
    graph.camera('vs2', square(2, 0, 4, 2))
    vs3 = graph.camera('vs3', square(10, 0, 12, 2))

    answer = graph.detect((1.0, 0.5, 3.0, 1.5), request_id='first')
    assert (answer.accepted, answer.vision_systems, answer.message) == (
        True,
        2,
        'forwarded to 2 vision systems',
    )
    for name in ('vs1', 'vs2'):
        wait_for(lambda name=name: graph.forwards(name), 10, f'forward to {name}', on_timeout=ros.describe)
        (record,) = graph.forwards(name)
        assert record == {
            'kind': 'forward',
            'algorithm': COLOUR,
            'region_of_interest': [1.0, 0.5, 3.0, 1.5],
            'callback_service': CALLBACK,
            'request_id': 'first',
            'caller': '/drvs',
        }
    # Touching only (vs2's edge at x = 4): not a match.
    assert graph.detect((4.0, 0.0, 5.0, 1.0), request_id='edge').vision_systems == 0

    # Move vs3 over the region: routing follows at once.
    ros.master.call('setParam', '/vs3/field_of_view', square(2.5, 1.0, 3.5, 3.0))
    wait_for(lambda: len(graph.registrations('vs3')) == 2, 10, 'vs3 moved', on_timeout=vs3.describe)
    answer = graph.detect((1.0, 0.5, 3.0, 1.5), request_id='second')
    assert answer.vision_systems == 3
    wait_for(lambda: forwarded_ids(graph, 'vs3') == ['second'], 10, 'forward to moved vs3')
    registry = graph.registry_topic()
    assert [(v['service_name'], v['provider'], v['field_of_view']) for v in registry['vision_systems']] == [
        ('/vs1/detect_object_boundary', '/vs1', square(0, 0, 2, 2)),
        ('/vs2/detect_object_boundary', '/vs2', square(2, 0, 4, 2)),
        ('/vs3/detect_object_boundary', '/vs3', square(2.5, 1.0, 3.5, 3.0)),
    ]
    assert 'moved /vs3/detect_object_boundary' in graph.server.log()

    # An empty field of view unregisters.
    ros.master.call('setParam', '/vs3/field_of_view', [])
    wait_for(lambda: len(graph.registrations('vs3')) == 3, 10, 'vs3 unregistered')
    assert graph.registrations('vs3')[-1]['message'] == 'unregistered /vs3/detect_object_boundary'
    assert graph.detect((2.6, 2.5, 3.0, 2.9), request_id='third').vision_systems == 0


def test_expired_lease_gets_nothing_more(ros, make_graph):
    graph = make_graph(lease=1.0)
    graph.camera('renewing', square(0, 0, 2, 2), renew=0.25)
    graph.camera('once', square(0, 0, 2, 2))  # registers once, never renews
    assert graph.detect((0.5, 0.5, 1.0, 1.0), request_id='a').vision_systems == 2
    wait_for(
        lambda: 'lease of /once/detect_object_boundary expired' in graph.server.log(),
        10,
        'the lease to expire',
        on_timeout=graph.server.describe,
    )
    answer = graph.detect((0.5, 0.5, 1.0, 1.0), request_id='b')
    assert answer.vision_systems == 1
    wait_for(lambda: forwarded_ids(graph, 'renewing') == ['a', 'b'], 10, 'forwards to the renewing camera')
    assert forwarded_ids(graph, 'once') == ['a']


def test_hung_camera_delays_neither_the_others_nor_the_robot(ros, make_graph):
    graph = make_graph(forward_timeout=3.0, max_failures=1)
    graph.camera('hung', square(0, 0, 2, 2), hang=3600)
    graph.camera('fast', square(0, 0, 2, 2))
    for index in range(3):
        assert graph.detect((0.5, 0.5, 1.0, 1.0), request_id=f'r{index}').vision_systems == 2
    # All three reach the fast camera while the hung one still holds the first.
    wait_for(lambda: forwarded_ids(graph, 'fast') == ['r0', 'r1', 'r2'], 10, 'forwards to the fast camera')
    assert forwarded_ids(graph, 'hung') == ['r0']
    # Its forward times out and, at max_failures 1, it is removed.
    wait_for(
        lambda: 'removed /hung/detect_object_boundary after 1 failed forwards in a row' in graph.server.log(),
        15,
        'the hung camera to be removed',
        on_timeout=graph.server.describe,
    )
    assert graph.detect((0.5, 0.5, 1.0, 1.0), request_id='after').vision_systems == 1
    wait_for(lambda: forwarded_ids(graph, 'fast')[-1] == 'after', 10, 'the next forward')


def test_a_full_pool_refuses_instead_of_queueing(ros, make_graph):
    graph = make_graph(forward_timeout=30.0, max_pending=2, workers=1)
    graph.camera('hung', square(0, 0, 2, 2), hang=3600)
    assert graph.detect((0, 0, 1, 1), request_id='r0').vision_systems == 1
    assert graph.detect((0, 0, 1, 1), request_id='r1').vision_systems == 1
    answer = graph.detect((0, 0, 1, 1), request_id='r2')
    assert (answer.accepted, answer.vision_systems, answer.message) == (
        False,
        0,
        'busy: 2 forwards pending, 1 more would pass the limit of 2; try again later',
    )


NAN = math.nan


@pytest.mark.parametrize('kind', ['detect', 'register'])
def test_invalid_inputs_are_refused_and_the_server_keeps_serving(ros, make_graph, kind):
    graph = make_graph()
    graph.camera('vs1', square(0, 0, 2, 2))
    if kind == 'detect':
        cases = [
            ({'algorithm': ''}, 'algorithm: empty; expected NAME:PARAMS, e.g. colour:0,0,150,80,80,255'),
            ({'algorithm': 'c' * 600}, 'algorithm: 600 characters, longer than the limit of 512'),
            (
                {'algorithm': '2d:round'},
                'algorithm: expected NAME[:PARAMS] with NAME a letter then letters, digits or _, '
                "e.g. colour:0,0,150,80,80,255, got '2d:round'",
            ),
            (
                {'algorithm': 'colour:1,2,3'},
                'algorithm: colour PARAMS must be 6 comma-separated integers '
                "RMIN,GMIN,BMIN,RMAX,GMAX,BMAX, got 3 value(s) in '1,2,3'",
            ),
            ({'box': (NAN, 0, 1, 1)}, 'region_of_interest: min_x is nan; coordinates must be finite'),
            ({'box': (0, 0, 1, math.inf)}, 'region_of_interest: max_y is inf; coordinates must be finite'),
            ({'box': (0, 2, 1, 1)}, 'region_of_interest: min_y 2 is greater than max_y 1'),
            ({'callback': 'robot cb'}, "callback_service: 'robot cb' is not a valid ROS name"),
            (
                {'callback': 'robot/cb'},
                "callback_service: 'robot/cb' is not a global ROS name (it must start with /)",
            ),
            ({'callback': '/nobody/cb'}, 'callback_service: /nobody/cb is not known to the ROS master'),
            (
                {'callback': '/vs1/detect_object_boundary'},
                'callback_service: /vs1/detect_object_boundary is of type drvs/DetectObjectBoundary, '
                'expected drvs/CallbackCoordinates',
            ),
        ]
        for fields, message in cases:
            answer = graph.detect(
                fields.get('box', (0, 0, 1, 1)),
                algorithm=fields.get('algorithm', COLOUR),
                callback=fields.get('callback', CALLBACK),
            )
            assert (answer.accepted, answer.status, answer.vision_systems, answer.message) == (
                False,
                INVALID,
                0,
                message,
            )
        # A NAME no registered vision system runs (vs1 registered none: the built-ins).
        answer = graph.detect((0, 0, 1, 1), algorithm='shape:round')
        assert (answer.accepted, answer.status, answer.message) == (
            False,
            UNSUPPORTED,
            "algorithm: no registered vision system runs 'shape'; available: apriltag, colour, motion",
        )
        # A caller of the wrong type is refused by the transport, and the server goes on.
        client = ServiceClient('/drvs/detect_object_boundary', CallbackCoordinates, 5.0)
        with pytest.raises(ServiceCallError, match='md5sums do not match'):
            client.call(CallbackCoordinates._request_class())
        client.close()
        answer = graph.detect((5, 5, 6, 6))
        assert (answer.accepted, answer.vision_systems, answer.message) == (
            True,
            0,
            'no vision system covers the region of interest',
        )
    else:
        own = '/vs1/detect_object_boundary'
        cases = [
            (
                own,
                [(0, 0), (1, 1)],
                'field_of_view: 2 vertices; a polygon needs at least 3 (service_name ' + own + ')',
            ),
            (
                own,
                [(0, 0), (1, NAN), (1, 1)],
                'field_of_view: vertex 1 is (1.0, nan); coordinates must be finite (service_name '
                + own
                + ')',
            ),
            (
                own,
                [(0, 0), (2, 2), (2, 0), (0, 2)],
                'field_of_view: the outline crosses itself at (1, 1) (service_name ' + own + ')',
            ),
            (
                own,
                [(0, 0), (1, 1), (2, 2)],
                'field_of_view: zero area (all vertices lie on one line) ' '(service_name ' + own + ')',
            ),
            ('/vs9/detect', square(0, 0, 1, 1), 'service_name: /vs9/detect is not known to the ROS master'),
            ('bad name', square(0, 0, 1, 1), "service_name: 'bad name' is not a valid ROS name"),
            (
                CALLBACK,
                square(0, 0, 1, 1),
                'service_name: /robot/callback_coordinates is of type drvs/CallbackCoordinates, '
                'expected drvs/DetectObjectBoundary',
            ),
            (
                own,
                square(5, 5, 6, 6),
                'service_name: /vs1/detect_object_boundary is provided by /vs1, not by the caller /unnamed; '
                'a node may register only its own service',
            ),
        ]
        for service_name, points, message in cases:
            answer = graph.register(service_name, points_to_polygon(points))
            assert (answer.accepted, answer.message) == (False, message)
        # Another node may not unregister vs1, and a camera may not claim vs1's service.
        answer = graph.register(own, Polygon())
        assert answer.message == f'service_name: {own} was registered by /vs1; /unnamed may not unregister it'
        graph.camera('thief', square(5, 5, 6, 6), wait=False, service_name=own)
        wait_for(lambda: graph.registrations('thief'), 30, 'the thief to try')
        assert graph.registrations('thief')[-1]['message'] == (
            f'service_name: {own} is provided by /vs1, not by the caller /thief; '
            'a node may register only its own service'
        )
        answer = graph.detect((0.5, 0.5, 1.0, 1.0))
        assert (answer.accepted, answer.vision_systems) == (True, 1)
        assert graph.detect((5.2, 5.2, 5.5, 5.5)).vision_systems == 0
        assert graph.registry_topic()['vision_systems'][0]['field_of_view'] == square(0, 0, 2, 2)
    assert graph.server.running()


def test_clean_exit_on_sigint(ros, make_graph):
    graph = make_graph()
    graph.camera('vs1', square(0, 0, 2, 2))
    assert graph.detect((0, 0, 1, 1)).vision_systems == 1
    assert graph.server.interrupt() == 0


def test_doctests():
    import doctest

    import drvs.common.log_throttle

    assert doctest.testmod(drvs.common.log_throttle).failed == 0  # the server's log throttle
