"""drvs_gateway on a live graph: drvs_server, a fake vision system that answers, and the gateway,
asked over HTTP as any client would (the standard library only)."""

import contextlib
import http.client
import json
import os
import random
import re
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request

import pytest

from drvs.gateway.tokens import add_token
from drvs.testing import free_port, read_json_lines, wait_for
from drvs.testing.doc_examples import commands, shell_blocks
from drvs.testing.footprint import MIB, established, rss
from drvs.testing.harness import REPO
from drvs.testing.hostile_bodies import random_body

pytestmark = pytest.mark.shared_master  # see test/conftest.py

COLOUR = 'colour:0,0,150,80,80,255'
BOX = [[1.0, 1.0], [1.4, 1.0], [1.4, 1.4], [1.0, 1.4]]
REGION = {'min_x': 0, 'min_y': 0, 'max_x': 4, 'max_y': 4}
FOV = [[0, 0], [4, 0], [4, 4], [0, 4]]


class Client:
    """HTTP with a token, answers as (status, headers, JSON body)."""

    def __init__(self, url, token=None):
        self.url, self.token = url, token

    def __call__(self, method, path, body=None, token=..., headers=None, data=None):
        token = self.token if token is ... else token
        headers = dict(headers or {})
        if token:
            headers['Authorization'] = f'Bearer {token}'
        if body is not None:
            data = json.dumps(body).encode()
        if data is not None:
            headers['Content-Type'] = 'application/json'
        request = urllib.request.Request(self.url + path, data=data, method=method, headers=headers)
        try:
            with urllib.request.urlopen(request, timeout=20) as response:
                return response.status, response.headers, json.loads(response.read() or b'null')
        except urllib.error.HTTPError as error:
            with error:
                return error.code, error.headers, json.loads(error.read() or b'null')


def events(url, path, token, count, last_event_id=None):
    """The next ``count`` events of an SSE stream as (id, event, data)."""
    host, port = url.removeprefix('http://').split(':')
    connection = http.client.HTTPConnection(host, int(port), timeout=20)
    headers = {'Authorization': f'Bearer {token}'}
    if last_event_id is not None:
        headers['Last-Event-ID'] = str(last_event_id)
    connection.request('GET', path, headers=headers)
    response = connection.getresponse()
    assert response.status == 200, response.read()
    found, fields = [], {}
    try:
        while len(found) < count:
            line = response.readline().decode().rstrip('\n')
            if not line:
                if 'event' in fields:
                    found.append((int(fields['id']), fields['event'], json.loads(fields['data'])))
                fields = {}
            elif not line.startswith(':'):
                key, _, value = line.partition(': ')
                fields[key] = value
    finally:
        connection.close()
    return found


@pytest.fixture(scope='module')
def site(module_ros, tmp_path_factory):
    """drvs_server, one fake camera that sees BOX, and the gateway with two tokens."""
    folder = tmp_path_factory.mktemp('gateway')
    tokens = folder / 'tokens.json'
    full = add_token(tokens, 'robot')
    viewer = add_token(tokens, 'viewer', ops=['read'])
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv('ROS_MASTER_URI', module_ros.master.uri)
        patch.setenv('ROS_HOSTNAME', '127.0.0.1')
        server = module_ros.start_node(
            'nodes/drvs_server',
            name='drvs',
            params={'fused_deadline': 1.0, 'max_pending': 1000, 'max_pending_per_vision_system': 1000},
        )
        module_ros.wait_for_service('/drvs/detect_object_boundary', node=server)
        module_ros.start_node(
            'test/nodes/fake_vision_system.py',
            name='cam1',
            params={
                'output': folder / 'cam1.jsonl',
                'field_of_view': FOV,
                'algorithms': ['colour'],
                'answer': True,
                'watch': True,
                'objects': [BOX],
                'renew': 3.0,
            },
        )
        url = f'http://127.0.0.1:{free_port()}'
        gateway = module_ros.start_node(
            'nodes/drvs_gateway',
            name='gateway',
            params={
                'bind': url.removeprefix('http://'),
                'rosbridge_bind': 'none',  # test_rosbridge.py tests it
                'tokens': tokens,
                'max_requests_per_s': 1000,
                'burst': 1000,
                'request_timeout': 5.0,
            },
        )
        client = Client(url, full)

        def ready():
            assert gateway.running(), gateway.describe()
            try:
                status, _, answer = client('GET', '/v1/vision_systems')
            except OSError:
                return False
            return status == 200 and answer['vision_systems']

        wait_for(ready, 30, 'the gateway and the camera in its registry', on_timeout=module_ros.describe)
        yield {
            'folder': folder,
            'url': url,
            'client': client,
            'full': full,
            'viewer': viewer,
            'gateway': gateway,
            'ros': module_ros,
        }


def test_detect_answers_with_the_callbacks_per_camera_and_fused(site):
    client = site['client']
    status, _, answer = client('POST', '/v1/detect', {'algorithm': COLOUR, 'region': REGION, 'wait': 5})
    assert status == 200, answer
    assert (answer['status'], answer['vision_systems'], len(answer['callbacks'])) == ('ACCEPTED', 1, 1)
    (callback,) = answer['callbacks']
    assert callback['vision_system'] == '/cam1/detect_object_boundary' and callback['algorithm'] == COLOUR
    (found,) = callback['objects']
    assert sum(found['boundary'], []) == pytest.approx(sum(BOX, []))
    assert found['bounding_box'] == pytest.approx({'min_x': 1.0, 'min_y': 1.0, 'max_x': 1.4, 'max_y': 1.4})
    status, _, fused = client(
        'POST', '/v1/detect', {'algorithm': COLOUR, 'region': REGION, 'wait': 5, 'fused': True}
    )
    assert status == 200, fused
    (callback,) = fused['callbacks']
    assert callback['fused'] and callback['status'] == 'OK' and callback['objects'][0]['track_id'] >= 1
    assert callback['answered'] == ['/cam1/detect_object_boundary']
    status, _, covered = client('GET', '/v1/coverage?min_x=3&min_y=3&max_x=9&max_y=9')
    assert (status, [entry['name'] for entry in covered['vision_systems']]) == (
        200,
        ['/cam1/detect_object_boundary'],
    )
    status, _, objects = client('GET', '/v1/objects')
    assert status == 200 and objects['objects'] and objects['algorithms'] == [COLOUR]


def test_a_watch_streams_callbacks_resumes_with_last_event_id_and_is_withdrawn(site):
    client, url, token = site['client'], site['url'], site['full']
    status, _, watch = client('POST', '/v1/watches', {'algorithm': COLOUR, 'region': REGION, 'period': 0.2})
    assert status == 201, watch
    first = events(url, watch['events'], token, 2)
    assert [kind for _, kind, _ in first] == ['callback', 'callback']
    assert first[0][2]['objects'] and first[1][0] > first[0][0]
    resumed = events(url, watch['events'], token, 1, last_event_id=first[0][0])
    assert resumed[0][0] == first[0][0] + 1  # nothing lost, nothing repeated
    status, _, _ = client('DELETE', f'/v1/watches/{watch["id"]}')
    assert status == 204
    assert client('GET', watch['events'])[0] == 404
    watches = site['folder'] / 'cam1.jsonl'
    wait_for(
        lambda: any(r['kind'] == 'watch' and r['duration'] == 0 for r in read_json_lines(watches)),
        15,
        'the DRVS watch withdrawn from the camera',
    )


@pytest.mark.parametrize(
    ('body', 'token', 'http', 'check'),
    [
        ({'algorithm': COLOUR, 'region': REGION}, None, 401, 'UNAUTHORIZED'),
        ({'algorithm': COLOUR, 'region': REGION}, 'drvs.0.nope', 401, 'UNAUTHORIZED'),
        ({'algorithm': COLOUR, 'region': REGION}, 'viewer', 403, 'FORBIDDEN'),
        ({'algorithm': COLOUR, 'region': {**REGION, 'min_x': 9}}, 'full', 400, 'region'),
        ({'algorithm': COLOUR, 'region': REGION, 'colour': 2}, 'full', 400, 'colour'),
        ({'algorithm': 'apriltag:tag36h11', 'region': REGION}, 'full', 422, 'UNSUPPORTED'),
    ],
)
def test_refusals(site, body, token, http, check):
    token = site.get(token, token)
    status, headers, answer = site['client']('POST', '/v1/detect', body, token=token)
    assert status == http, answer
    assert check in (answer['error'], answer.get('field'))
    if http == 422:
        assert answer['available_algorithms'] == ['colour']


def test_no_drvs_server_is_503_within_the_deadline(site):
    ros = site['ros']
    url = f'http://127.0.0.1:{free_port()}'
    lonely = ros.start_node(
        'nodes/drvs_gateway',
        name='lonely',
        params={
            'bind': url.removeprefix('http://'),
            'rosbridge_bind': 'none',
            'server': '/nowhere',
            'server_timeout': 1.0,
        },
    )
    client = Client(url)
    wait_for(lambda: _answers(client), 30, 'the second gateway', on_timeout=lonely.describe)
    started = time.monotonic()
    status, headers, answer = client('POST', '/v1/detect', {'algorithm': COLOUR, 'region': REGION})
    assert (status, answer['error'], headers['Retry-After']) == (503, 'NO_SERVER', '1')
    assert time.monotonic() - started < 3.0
    assert client('GET', '/v1/vision_systems')[0] == 503
    assert lonely.interrupt() == 0  # Ctrl-C: a clean exit


def _answers(client):
    try:
        return client('GET', '/v1/health')[0] == 200
    except OSError:
        return False


def test_without_tokens_it_refuses_to_listen_beyond_loopback(site):
    node = site['ros'].start_node(
        'nodes/drvs_gateway', name='open', params={'bind': f'0.0.0.0:{free_port()}', 'rosbridge_bind': 'none'}
    )
    wait_for(lambda: not node.running(), 30, 'the gateway to refuse', on_timeout=node.describe)
    assert node.process.returncode == 2
    assert 'is not a loopback address' in node.log()


def test_the_docs_examples_run_as_written(site, tmp_path):
    """docs/gateway.md's Python client and its first two curl commands, against this gateway."""
    page = (REPO / 'docs' / 'gateway.md').read_text()
    python = re.findall(r'^```python\n(.*?)^```', page, re.S | re.M)[0]  # the first; the next: roslibpy
    env = {**os.environ, 'DRVS_GATEWAY': site['url'], 'DRVS_TOKEN': site['full'], 'TOKEN': site['full']}
    script = tmp_path / 'client.py'
    script.write_text(python)
    done = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].startswith('/cam1/detect_object_boundary sees an object at {')
    assert lines[-3:] == ['watch: 1 object(s)'] * 3
    curl = [block for block in shell_blocks(REPO / 'docs' / 'gateway.md') if block.startswith('curl')][0]
    detect, coverage = (command for command, _ in commands(curl)[:2])
    for command in (detect, coverage):
        command = command.replace('http://127.0.0.1:8080', site['url'])
        done = subprocess.run(['bash', '-c', command], env=env, capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        assert 'error' not in json.loads(done.stdout), done.stdout


def test_random_bodies_get_clean_answers_and_the_gateway_keeps_serving(site):
    hostile(site, 2000)


@pytest.mark.slow
def test_ten_thousand_random_bodies(site):
    hostile(site, 10_000)


def hostile(site, count):
    """``count`` random bodies after a warm-up of a tenth as many: every answer a clean 2xx/4xx,
    and the gateway's memory and connections back near where the warm-up left them."""
    pid, port = site['gateway'].pid, int(site['url'].rpartition(':')[2])
    _random_bodies(site, count // 10, seed=count)
    before = rss(pid)
    _random_bodies(site, count, seed=27)
    wait_for(lambda: established(pid, port) == 0, 10, 'every connection of the run closed')
    assert rss(pid) - before < 20 * MIB, f'{(rss(pid) - before) / MIB:.1f} MiB more'


def _random_bodies(site, count, seed):
    rng = random.Random(seed)
    client = site['client']
    statuses = {}
    for _ in range(count):
        path = rng.choice(['/v1/detect', '/v1/watches'])
        status, _, answer = client('POST', path, data=random_body(rng, path, REGION))
        assert 200 <= status < 500, answer
        statuses[status] = statuses.get(status, 0) + 1
        if status == 201:
            assert client('DELETE', f'/v1/watches/{answer["id"]}')[0] == 204
    assert {200, 400} <= set(statuses), statuses
    status, _, health = client('GET', '/v1/health')
    assert status == 200 and health['gateway']['errors'] == 0 and health['gateway']['watches'] == 0
    assert site['gateway'].running()

    def no_drvs_watches():  # the server's own count, on /diagnostics once a second
        status, _, answer = client('GET', '/v1/health')
        if status == 429:  # the token's burst spent by the flood: asked again (a KeyError once)
            return False
        server = answer['server']
        return server is not None and int(server['values']['watches']) == 0

    wait_for(no_drvs_watches, 20, 'every DRVS watch withdrawn')


SLOW_SENDERS = 16


def test_slow_senders_and_a_reader_that_never_reads_delay_nobody(site):
    """A slowloris (a request's head one byte every 0.5 s on many connections) and an event stream
    nobody reads: a normal client's requests are answered while they are open, and the gateway cuts
    the slow senders off after ~request_timeout (5 s here)."""
    client, url, token = site['client'], site['url'], site['full']
    host, port = url.removeprefix('http://').split(':')
    pid = site['gateway'].pid
    status, _, watch = client('POST', '/v1/watches', {'algorithm': COLOUR, 'region': REGION, 'period': 0.1})
    assert status == 201, watch
    mute = socket.create_connection((host, int(port)), timeout=20)  # reads nothing, ever
    mute.sendall(
        f'GET {watch["events"]} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n\r\n'.encode()
    )
    head = b'POST /v1/detect HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n'
    slow = [socket.create_connection((host, int(port)), timeout=20) for _ in range(SLOW_SENDERS)]
    try:
        sent = 0

        def trickle():
            """One more byte on each slow connection; how many the gateway still holds (and the mute)."""
            nonlocal sent
            for each in slow:
                with contextlib.suppress(OSError):  # cut off
                    each.sendall(head[sent : sent + 1])
            sent += 1
            return established(pid, int(port))

        wait_for(lambda: trickle() == SLOW_SENDERS + 1, 10, 'the slow ones and the mute one connected')
        status, _, answer = client('POST', '/v1/detect', {'algorithm': COLOUR, 'region': REGION, 'wait': 5})
        assert (status, len(answer['callbacks'])) == (200, 1), answer
        assert client('GET', '/v1/health')[0] == 200
        assert established(pid, int(port)) == SLOW_SENDERS + 1, 'answered only once the slow ones were gone'

        def cut_off():
            time.sleep(0.5)  # the slowloris's pace, not a wait for the gateway
            return trickle() == 1  # the mute one is not cut off: it sent its request

        wait_for(cut_off, 30, 'the slow senders cut off')
        assert site['gateway'].running()
    finally:
        for each in [*slow, mute]:
            each.close()
        client('DELETE', f'/v1/watches/{watch["id"]}')
