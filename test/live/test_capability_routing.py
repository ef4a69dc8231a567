"""Routing by capability: a request goes only to vision systems that cover its region and run its algorithm.

Live: the DRVS server, a callback recorder and fake vision systems
(``test/nodes/fake_vision_system.py``) that declare which algorithm names they
run, all with the same field of view, on a private master.
"""

import pytest

from drvs.algorithms import AlgorithmError, parse_algorithm
from drvs.common.status import ACCEPTED, INVALID, UNSUPPORTED
from drvs.ros.conversions import points_to_polygon
from drvs.ros.service_client import ServiceClient
from drvs.srv import RegisterVisionService
from drvs.testing import echo, read_json_lines, wait_for
from drvs.testing.detect import detect

pytestmark = pytest.mark.shared_master  # see test/conftest.py

SERVER = 'nodes/drvs_server'
FAKE = 'test/nodes/fake_vision_system.py'
RECORDER = 'test/nodes/callback_recorder.py'
DETECT = '/drvs/detect_object_boundary'
REGISTER = '/drvs/register_vision_service'
COLOUR = 'colour:0,0,150,80,80,255'
FIELD_OF_VIEW = [[0, 0], [2, 0], [2, 2], [0, 2]]
REGION = (0.5, 0.5, 1.0, 1.0)  # inside FIELD_OF_VIEW
ELSEWHERE = [[10, 0], [12, 0], [12, 2], [10, 2]]
ELSEWHERE_REGION = (10.5, 0.5, 11.0, 1.0)


def service(name):
    return f'/{name}/detect_object_boundary'


class Cameras:
    """The server, a callback recorder, and fake vision systems started by name."""

    def __init__(self, ros, tmp_path):
        self.ros, self.tmp_path = ros, tmp_path
        self.server = ros.start_node(SERVER, name='drvs')
        ros.wait_for_service(DETECT, node=self.server)
        ros.wait_for_service(REGISTER, node=self.server)
        recorder = ros.start_node(RECORDER, name='robot', params={'output': tmp_path / 'callbacks.jsonl'})
        ros.wait_for_service('/robot/callback_coordinates', node=recorder)

    def start(self, name, algorithms, field_of_view=FIELD_OF_VIEW):
        params = {'output': self.tmp_path / f'{name}.jsonl', 'field_of_view': field_of_view}
        node = self.ros.start_node(FAKE, name=name, params={**params, 'algorithms': algorithms})
        self.wait_registrations(name, 1)
        return node

    def records(self, name, kind):
        return [r for r in read_json_lines(self.tmp_path / f'{name}.jsonl') if r['kind'] == kind]

    def wait_registrations(self, name, count):
        wait_for(
            lambda: len(self.records(name, 'register')) >= count,
            30,
            f'registration {count} of {name}',
            on_timeout=self.ros.describe,
        )
        return self.records(name, 'register')[count - 1]

    def forwarded(self, name):
        return [(r['algorithm'], r['request_id']) for r in self.records(name, 'forward')]

    def registry(self, condition=lambda registry: True):
        """The latest ``/drvs/registry`` message that meets ``condition`` (it may lag a registration)."""
        return wait_for(lambda: r if condition(r := self._registry()) else None, 30, 'the registry')

    def _registry(self):
        return echo(self.ros, '/drvs/registry')


@pytest.fixture
def cameras(graph, tmp_path):
    return Cameras(graph, tmp_path)


def outcome(answer):
    return answer.accepted, answer.status, answer.vision_systems, answer.message


def invalid_params_message(algorithm):
    """What the shared parser says about ``algorithm`` (the server must say the same)."""
    with pytest.raises(AlgorithmError) as caught:
        parse_algorithm(algorithm)
    return str(caught.value)


def test_requests_reach_only_the_vision_systems_that_run_their_algorithm(cameras):
    cameras.start('plain', ['colour'])
    cameras.start('tags', ['colour', 'apriltag'])
    cameras.start('plugin', ['sift'])
    cameras.start('builtin', [], field_of_view=ELSEWHERE)  # [] = the built-in set

    assert outcome(detect(DETECT, COLOUR, REGION, 'c1')) == (
        True,
        ACCEPTED,
        2,
        'forwarded to 2 vision systems',
    )
    # The server does not know sift: it checks the syntax only and forwards the PARAMS unchanged.
    assert outcome(detect(DETECT, 'sift:whatever', REGION, 's1')) == (
        True,
        ACCEPTED,
        1,
        'forwarded to 1 vision system',
    )
    wait_for(
        lambda: [cameras.forwarded(name) for name in ('plain', 'tags', 'plugin')]
        == [[(COLOUR, 'c1')], [(COLOUR, 'c1')], [('sift:whatever', 's1')]],
        10,
        'the forwards',
        on_timeout=cameras.ros.describe,
    )

    # Nobody runs surf: final, with what is available (the built-in camera adds motion).
    assert outcome(detect(DETECT, 'surf:1', REGION, 'u1')) == (
        False,
        UNSUPPORTED,
        0,
        "algorithm: no registered vision system runs 'surf'; available: apriltag, colour, motion, sift",
    )
    # ... but a wrong field comes first.
    assert outcome(detect(DETECT, 'surf:1', (2, 0, 1, 1), 'u2')) == (
        False,
        INVALID,
        0,
        'region_of_interest: min_x 2 is greater than max_x 1',
    )
    assert outcome(detect(DETECT, 'surf:1', REGION, 'u3', callback='/nobody/callback')) == (
        False,
        INVALID,
        0,
        'callback_service: /nobody/callback is not known to the ROS master',
    )
    assert outcome(detect(DETECT, '2d:x', REGION, 'u4')) == (
        False,
        INVALID,
        0,
        'algorithm: expected NAME[:PARAMS] with NAME a letter then letters, digits or _, '
        "e.g. colour:0,0,150,80,80,255, got '2d:x'",
    )
    # The server knows colour: it checks its PARAMS.
    answer = detect(DETECT, 'colour:1,2', REGION, 'i1')
    assert outcome(answer) == (False, INVALID, 0, invalid_params_message('colour:1,2'))
    assert answer.message.startswith('algorithm: colour PARAMS')

    # The camera that registered [] runs the built-ins.
    assert outcome(detect(DETECT, COLOUR, ELSEWHERE_REGION, 'b1')) == (
        True,
        ACCEPTED,
        1,
        'forwarded to 1 vision system',
    )
    wait_for(lambda: cameras.forwarded('builtin') == [(COLOUR, 'b1')], 10, 'the forward to builtin')
    # Someone runs sift, but not there; and nobody at all looks at (5, 5).
    assert outcome(detect(DETECT, 'sift:x', ELSEWHERE_REGION, 's2')) == (
        True,
        ACCEPTED,
        0,
        "no vision system that runs 'sift' covers the region of interest",
    )
    assert outcome(detect(DETECT, 'sift:x', (5, 5, 6, 6), 's3')) == (
        True,
        ACCEPTED,
        0,
        'no vision system covers the region of interest',
    )

    registry = cameras.registry(lambda registry: len(registry['vision_systems']) == 4)
    assert [(v['service_name'], v['algorithms']) for v in registry['vision_systems']] == [
        (service('builtin'), ['apriltag', 'colour', 'motion']),
        (service('plain'), ['colour']),
        (service('plugin'), ['sift']),
        (service('tags'), ['apriltag', 'colour']),
    ]
    # RViz: one field-of-view outline and one name per registered camera, after a DELETEALL.
    markers = wait_for(
        lambda: m if len((m := echo(cameras.ros, '/drvs/markers'))['markers']) == 1 + 2 * 4 else None,
        30,
        'one field-of-view marker and one name per camera on /drvs/markers',
    )['markers']
    assert markers[0]['action'] == 3  # DELETEALL: cameras that left disappear
    assert sorted(m['text'] for m in markers if m['ns'] == 'names') == ['builtin', 'plain', 'plugin', 'tags']
    assert all(m['header']['frame_id'] == 'map' for m in markers if m['ns'] == 'fields_of_view')
    assert f'registered {service("tags")} by /tags: field of view' in cameras.server.log()
    assert 'algorithms apriltag, colour' in cameras.server.log()

    # Requests for a built-in algorithm other than colour go only to the cameras that run it.
    assert outcome(detect(DETECT, 'apriltag:tag36h11', REGION, 'a1')) == (
        True,
        ACCEPTED,
        1,
        'forwarded to 1 vision system',
    )
    wait_for(
        lambda: cameras.forwarded('tags')[-1:] == [('apriltag:tag36h11', 'a1')], 10, 'the forward to tags'
    )
    assert cameras.forwarded('plain') == [(COLOUR, 'c1')]
    assert cameras.server.running()


def test_a_new_algorithm_list_changes_routing(cameras):
    cameras.start('vs', ['colour'])
    assert outcome(detect(DETECT, 'sift:1', REGION, 'r1')) == (
        False,
        UNSUPPORTED,
        0,
        "algorithm: no registered vision system runs 'sift'; available: colour",
    )

    cameras.ros.master.call('setParam', '/vs/algorithms', ['sift'])
    answer = cameras.wait_registrations('vs', 2)
    assert (answer['status'], answer['message']) == (
        ACCEPTED,
        'changed /vs/detect_object_boundary; lease 10 s',
    )
    assert 'changed /vs/detect_object_boundary: algorithms sift' in cameras.server.log()
    assert outcome(detect(DETECT, 'sift:1', REGION, 'r2')) == (
        True,
        ACCEPTED,
        1,
        'forwarded to 1 vision system',
    )
    assert outcome(detect(DETECT, COLOUR, REGION, 'r3')) == (
        False,
        UNSUPPORTED,
        0,
        "algorithm: no registered vision system runs 'colour'; available: sift",
    )
    assert cameras.registry(lambda registry: registry['vision_systems'][0]['algorithms'] == ['sift'])

    cameras.ros.master.call('setParam', '/vs/algorithms', [])  # back to the built-ins
    assert cameras.wait_registrations('vs', 3)['message'] == 'changed /vs/detect_object_boundary; lease 10 s'
    assert outcome(detect(DETECT, COLOUR, REGION, 'r4')) == (
        True,
        ACCEPTED,
        1,
        'forwarded to 1 vision system',
    )
    wait_for(
        lambda: cameras.forwarded('vs') == [('sift:1', 'r2'), (COLOUR, 'r4')],
        10,
        'the forwards',
        on_timeout=cameras.ros.describe,
    )


OWN = service('vs1')
NAME_RULE = '(a letter, then letters, digits or _, without :PARAMS)'


def test_a_registration_with_bad_algorithm_names_is_refused(cameras):
    cases = [
        (['colour', 'sift:1'], f"algorithms[1]: 'sift:1' is not an algorithm NAME {NAME_RULE}"),
        ([''], f"algorithms[0]: '' is not an algorithm NAME {NAME_RULE}"),
        (['colour', 'two words'], f"algorithms[1]: 'two words' is not an algorithm NAME {NAME_RULE}"),
        (['a' * 65], 'algorithms[0]: 65 characters, longer than the limit of 64'),
        ([f'a{n}' for n in range(65)], 'algorithms: 65 names, more than the limit of 64'),
    ]
    client = ServiceClient(REGISTER, RegisterVisionService, 10.0)
    try:
        for algorithms, message in cases:
            request = RegisterVisionService._request_class(OWN, points_to_polygon(FIELD_OF_VIEW), algorithms)
            answer = client.call(request)
            assert (answer.accepted, answer.status, answer.message) == (
                False,
                INVALID,
                f'{message} (service_name {OWN})',
            )
    finally:
        client.close()
    # A vision system that declares a bad name is not registered; the server goes on.
    cameras.ros.start_node(
        FAKE,
        name='vs1',
        params={
            'output': cameras.tmp_path / 'vs1.jsonl',
            'field_of_view': FIELD_OF_VIEW,
            'algorithms': ['x-ray'],
        },
    )
    answer = cameras.wait_registrations('vs1', 1)
    assert (answer['status'], answer['message']) == (
        INVALID,
        f"algorithms[0]: 'x-ray' is not an algorithm NAME {NAME_RULE} (service_name {OWN})",
    )
    assert cameras.registry()['vision_systems'] == []
    cameras.start('vs2', ['colour'])
    assert outcome(detect(DETECT, COLOUR, REGION, 'r1')) == (
        True,
        ACCEPTED,
        1,
        'forwarded to 1 vision system',
    )


def test_fake_cameras_declare_algorithms_per_camera(cameras):
    """``fake_cameras.py`` (the load tests' fakes) takes a plain field of view or one with algorithms."""
    output = cameras.tmp_path / 'many.jsonl'
    layout = {'sifter': {'fov': FIELD_OF_VIEW, 'algorithms': ['sift']}, 'plain': FIELD_OF_VIEW}
    cameras.ros.start_node(
        'test/nodes/fake_cameras.py', name='many', params={'output': output, 'cameras': layout}
    )

    def registered():
        return {
            r['camera']
            for r in read_json_lines(output)
            if r['kind'] == 'register' and r['status'] == ACCEPTED
        }

    wait_for(
        lambda: len(registered()) == 2, 30, 'both fake cameras to register', on_timeout=cameras.ros.describe
    )
    assert outcome(detect(DETECT, 'sift:1', REGION, 's1')) == (
        True,
        ACCEPTED,
        1,
        'forwarded to 1 vision system',
    )
    assert outcome(detect(DETECT, COLOUR, REGION, 'c1')) == (
        True,
        ACCEPTED,
        1,
        'forwarded to 1 vision system',
    )
    wait_for(
        lambda: sorted(
            (r['camera'], r['request_id']) for r in read_json_lines(output) if r['kind'] == 'forward'
        )
        == [('/many/plain/detect_object_boundary', 'c1'), ('/many/sifter/detect_object_boundary', 's1')],
        10,
        'the forwards',
        on_timeout=cameras.ros.describe,
    )
