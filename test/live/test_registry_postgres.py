"""drvs_server on a PostgreSQL registry (docs/registry.md): a database restart under a running
server, a bad DSN, and hostile text through all three services reaching SQL only as parameters."""

import os
import signal

import psycopg
import pytest

from drvs.common.status import ACCEPTED, INVALID, UNAVAILABLE
from drvs.msg import BoundingBox
from drvs.ros.conversions import points_to_polygon
from drvs.ros.service_client import ServiceClient
from drvs.srv import DetectObjectBoundary, RegisterVisionService, WatchObjectBoundary
from drvs.testing import read_json_lines, wait_for

pytestmark = pytest.mark.shared_master  # see test/conftest.py

SERVER = 'nodes/drvs_server'
FAKE = 'test/nodes/fake_vision_system.py'
RECORDER = 'test/nodes/callback_recorder.py'
COLOUR = 'colour:0,0,150,80,80,255'
CALLBACK = '/robot/callback_coordinates'


def square(x0, y0, x1, y1):
    return [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]


def records(path, kind):
    return [r for r in read_json_lines(path) if r['kind'] == kind]


@pytest.fixture
def server(ros, postgres, monkeypatch, tmp_path):
    """A drvs_server on the module's database (emptied), a callback recorder, clients to its services."""
    postgres.empty()
    monkeypatch.setenv('ROS_MASTER_URI', ros.master.uri)
    monkeypatch.setenv('ROS_HOSTNAME', '127.0.0.1')
    node = ros.start_node(
        SERVER, name='drvs', params={'registry': postgres.dsn, 'unavailable_retry_after': 0.5}
    )
    recorder = ros.start_node(RECORDER, name='robot', params={'output': tmp_path / 'callbacks.jsonl'})
    ros.wait_for_service('/drvs/detect_object_boundary', node=node)
    ros.wait_for_service(CALLBACK, node=recorder)
    clients = {
        'detect': ServiceClient('/drvs/detect_object_boundary', DetectObjectBoundary, 10.0),
        'register': ServiceClient('/drvs/register_vision_service', RegisterVisionService, 10.0),
        'watch': ServiceClient('/drvs/watch_object_boundary', WatchObjectBoundary, 10.0),
    }
    yield node, clients
    for client in clients.values():
        client.close()


def detect(clients, box, request_id='r1'):
    request = DetectObjectBoundary._request_class(
        algorithm=COLOUR,
        region_of_interest=BoundingBox(*box),
        callback_service=CALLBACK,
        request_id=request_id,
    )
    return clients['detect'].call(request)


def camera(ros, tmp_path, name, fov):
    output = tmp_path / f'{name}.jsonl'
    ros.start_node(FAKE, name=name, params={'output': output, 'field_of_view': fov, 'renew': 0.5})
    return output


def diagnostics(ros, condition):
    result = ros.run(f'timeout 30 rostopic echo -n 1 --filter "{condition}" /diagnostics', timeout=40)
    assert result.returncode == 0, result.stdout + result.stderr
    return result.stdout


def test_a_database_restart_serves_from_the_cache_refuses_registrations_and_catches_up(
    ros, postgres, server, tmp_path
):
    node, clients = server
    first = camera(ros, tmp_path, 'cam1', square(0, 0, 2, 2))
    wait_for(lambda: any(r['accepted'] for r in records(first, 'register')), 30, 'cam1 registered')
    assert detect(clients, (0.5, 0.5, 1.0, 1.0)).vision_systems == 1
    postgres.stop()
    try:
        second = camera(ros, tmp_path, 'cam2', square(5, 0, 7, 2))
        refused = wait_for(
            lambda: [r for r in records(second, 'register') if r['status'] == UNAVAILABLE], 30, 'cam2 refused'
        )
        assert (
            refused[0]['retry_after'] == 0.5 and 'registry database is unreachable' in refused[0]['message']
        )
        answer = detect(clients, (0.5, 0.5, 1.0, 1.0), 'r2')  # the cache still matches, cam1 still renews
        assert (answer.status, answer.vision_systems) == (ACCEPTED, 1)
        shown = diagnostics(ros, "'registry database unreachable' in m.status[0].message")
        assert 'level: 2' in shown
    finally:
        postgres.start()
    wait_for(
        lambda: records(second, 'register')[-1]['accepted'], 30, 'cam2 registered once the database is back'
    )
    assert detect(clients, (5.5, 0.5, 6.0, 1.0), 'r3').vision_systems == 1
    wait_for(
        lambda: detect(clients, (0.5, 0.5, 1.0, 1.0), 'r4').vision_systems == 1, 10, 'cam1 still matched'
    )
    with psycopg.connect(postgres.dsn) as connection:
        names = [
            row[0] for row in connection.execute('SELECT service_name FROM drvs_vision_systems ORDER BY 1')
        ]
    assert names == ['/cam1/detect_object_boundary', '/cam2/detect_object_boundary']
    assert node.running()


def test_a_wrong_password_is_one_line_and_exit_2(ros, postgres, monkeypatch):
    monkeypatch.setenv('ROS_MASTER_URI', ros.master.uri)
    wrong = postgres.dsn.replace('drvs:', 'drvs:wrong', 1)
    node = ros.start_node(SERVER, name='drvs_bad', params={'registry': wrong})
    code = node.process.wait(30)
    lines = [line.split(']: ', 1)[1] for line in node.log().splitlines() if line.startswith('[FATAL]')]
    assert code == 2, node.describe()
    assert lines == [
        f'drvs_server: ~registry: cannot use the registry database '
        f'postgresql://drvs@127.0.0.1:{postgres.dsn.rsplit(":", 1)[1].split("/")[0]}/drvs: '
        'password authentication failed for user "drvs"'
    ], node.describe()


HOSTILE = [
    "x'); DROP TABLE drvs_vision_systems; --",
    'x"; DELETE FROM drvs_watches; --',
    "%s %(now)s {0} \\' \\\\",
    '$$; SELECT pg_sleep(10); $$',
    'ünïcødé ☃ \u202e',
    'x' * 256,
    'nul \x00 byte',
]


def test_hostile_text_reaches_sql_only_as_parameters(ros, postgres, server, tmp_path):
    """Text in every field that reaches the database (service name, algorithms, request id) is refused
    by name or stored verbatim; the tables stay as they were (the fuzz run itself:
    test_hostile_input.py, against the in-memory registry)."""
    node, clients = server
    output = camera(ros, tmp_path, 'cam1', square(0, 0, 2, 2))
    wait_for(lambda: any(r['accepted'] for r in records(output, 'register')), 30, 'cam1 registered')
    for text in HOSTILE:
        register = RegisterVisionService._request_class(
            service_name=text, field_of_view=points_to_polygon(square(0, 0, 1, 1)), algorithms=[text]
        )
        answer = clients['register'].call(register)
        assert answer.status == INVALID, (text, answer.message)
        watch = WatchObjectBoundary._request_class(
            algorithm=COLOUR,
            region_of_interest=BoundingBox(0.5, 0.5, 1.0, 1.0),
            callback_service=CALLBACK,
            request_id=text,
            period=0.5,
            duration=30.0,
        )
        answer = clients['watch'].call(watch)
        assert answer.status == ACCEPTED, (text, answer.message)
        assert detect(clients, (0.5, 0.5, 1.0, 1.0), text).status == ACCEPTED
    expected = sorted(text.encode() for text in HOSTILE)  # the texts of a watch are kept as bytea
    with psycopg.connect(postgres.dsn) as connection:

        def stored():
            rows = connection.execute('SELECT request_id FROM drvs_watches').fetchall()
            return sorted(bytes(row[0]) for row in rows) == expected

        wait_for(stored, 10, 'every watch stored verbatim')
        names = connection.execute('SELECT service_name FROM drvs_vision_systems').fetchall()
        assert names == [('/cam1/detect_object_boundary',)]
    assert node.running()


def test_replicas_share_registrations_and_a_killed_one_loses_nothing_registered_nor_its_watches(
    ros, postgres, server, tmp_path
):
    """Two servers on one database: a camera registered through the first is matched through the
    second; kill -9 of the first: the second still forwards to it, and takes the first's watch over
    (a camera that comes later gets it)."""
    first, clients = server
    second = ros.start_node(
        SERVER, name='drvs_b', params={'registry': postgres.dsn, 'watch_takeover': 2.0, 'lease': 10.0}
    )
    ros.wait_for_service('/drvs_b/detect_object_boundary', node=second)
    output = tmp_path / 'cam1.jsonl'
    ros.start_node(
        FAKE,
        name='cam1',
        params={'output': output, 'field_of_view': square(0, 0, 2, 2), 'renew': 1.0, 'watch': True},
    )
    wait_for(lambda: any(r['accepted'] for r in records(output, 'register')), 30, 'cam1 registered')
    via_second = ServiceClient('/drvs_b/detect_object_boundary', DetectObjectBoundary, 10.0)
    try:

        def asked_second(request_id):
            request = DetectObjectBoundary._request_class(
                algorithm=COLOUR,
                region_of_interest=BoundingBox(0.5, 0.5, 1.0, 1.0),
                callback_service=CALLBACK,
                request_id=request_id,
            )
            return via_second.call(request).vision_systems

        wait_for(lambda: asked_second('b1') == 1, 10, 'the second replica matching cam1')
        watch = WatchObjectBoundary._request_class(
            algorithm=COLOUR,
            region_of_interest=BoundingBox(0.5, 0.5, 4.0, 1.0),
            callback_service=CALLBACK,
            request_id='w1',
            period=0.5,
            duration=60.0,
        )
        assert clients['watch'].call(watch).status == ACCEPTED
        wait_for(lambda: records(output, 'watch'), 10, 'the watch forwarded to cam1')
        os.killpg(first.pid, signal.SIGKILL)
        first.process.wait(10)
        # Requests keep flowing through the second, to the camera registered through the first;
        # drvs_ask given both moves on to the second.
        for n in range(5):
            assert asked_second(f'after{n}') == 1
        asked = ros.run(
            f"drvs_ask '{COLOUR}' --roi 0.5 0.5 1 1 --wait 0.1 --timeout 10 "
            '--server /drvs/detect_object_boundary /drvs_b/detect_object_boundary'
        )
        assert 'asking /drvs_b/detect_object_boundary' in asked.stderr, asked.stderr
        assert 'vision_systems: 1' in asked.stdout, asked.stdout + asked.stderr
        later = tmp_path / 'cam2.jsonl'
        ros.start_node(
            FAKE,
            name='cam2',
            params={
                'output': later,
                'field_of_view': square(3, 0, 5, 2),
                'renew': 1.0,
                'watch': True,
                'server': '/drvs_b/register_vision_service',
            },
        )
        got = wait_for(lambda: records(later, 'watch'), 30, 'the taken-over watch forwarded to cam2')
        assert got[0]['request_id'] == 'w1' and got[0]['callback_service'] == CALLBACK
    finally:
        via_second.close()
    with psycopg.connect(postgres.dsn) as connection:
        names = [
            row[0] for row in connection.execute('SELECT service_name FROM drvs_vision_systems ORDER BY 1')
        ]
    assert names == ['/cam1/detect_object_boundary', '/cam2/detect_object_boundary']
