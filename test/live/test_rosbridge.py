"""drvs_gateway's rosbridge endpoint on a live graph: drvs_server, a fake vision system that answers,
and the clients people use — roslibpy and roslibjs (Node) — running docs/gateway.md's examples as
written: host the callback, ask, receive the outlines; then hostile clients: garbage frames, one
that never answers DRVS's call to its callback, thousands of random frames."""

import asyncio
import json
import os
import random
import shutil
import subprocess
import sys
import time

import aiohttp
import pytest

from drvs.gateway.tokens import add_token
from drvs.testing import free_port, wait_for
from drvs.testing.footprint import MIB, established, rss
from drvs.testing.harness import REPO
from drvs.testing.hostile_frames import random_frame

pytestmark = pytest.mark.shared_master  # see test/conftest.py

BOX = [[1.0, 1.0], [1.4, 1.0], [1.4, 1.4], [1.0, 1.4]]
FOV = [[0, 0], [4, 0], [4, 4], [0, 4]]
COLOUR = 'colour:0,0,150,80,80,255'
EXAMPLES = REPO / 'examples'
SEES = '/cam1/detect_object_boundary sees an object at '


@pytest.fixture(scope='module')
def site(module_ros, tmp_path_factory):
    """drvs_server, one fake camera that sees BOX, and the gateway with its rosbridge endpoint."""
    folder = tmp_path_factory.mktemp('rosbridge')
    tokens = folder / 'tokens.json'
    full = add_token(tokens, 'robot')
    viewer = add_token(tokens, 'viewer', ops=['read'])
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv('ROS_MASTER_URI', module_ros.master.uri)
        patch.setenv('ROS_HOSTNAME', '127.0.0.1')
        server = module_ros.start_node('nodes/drvs_server', name='drvs')
        module_ros.wait_for_service('/drvs/detect_object_boundary', node=server)
        module_ros.start_node(
            'test/nodes/fake_vision_system.py',
            name='cam1',
            params={
                'output': folder / 'cam1.jsonl',
                'field_of_view': FOV,
                'algorithms': ['colour'],
                'answer': True,
                'objects': [BOX],
                'renew': 3.0,
            },
        )
        address = f'127.0.0.1:{free_port()}'
        gateway = module_ros.start_node(
            'nodes/drvs_gateway',
            name='gateway',
            params={
                'bind': f'127.0.0.1:{free_port()}',
                'rosbridge_bind': address,
                'tokens': tokens,
                'max_requests_per_s': 1000,
                'burst': 1000,
            },
        )
        url = f'ws://{address}'

        async def registry_heard():
            async with connect(url, full) as socket:
                await socket.send_json({'op': 'subscribe', 'topic': '/drvs/registry'})
                message = await receive(socket, 3)
                return message['op'] == 'publish' and message['msg']['vision_systems']

        def ready():
            assert gateway.running(), gateway.describe()
            try:
                return asyncio.run(registry_heard())
            except (OSError, TimeoutError, aiohttp.ClientError):
                return False

        wait_for(
            ready,
            30,
            'the rosbridge endpoint and the camera in /drvs/registry',
            on_timeout=module_ros.describe,
        )
        yield {
            'url': url,
            'address': address,
            'full': full,
            'viewer': viewer,
            'ros': module_ros,
            'gateway': gateway,
        }


def connect(url, token):
    session = aiohttp.ClientSession()
    return _Connection(session, url, token)


class _Connection:
    def __init__(self, session, url, token):
        self.session, self.url, self.token = session, url, token

    async def __aenter__(self):
        try:
            return await self.session.ws_connect(self.url, headers={'Authorization': f'Bearer {self.token}'})
        except BaseException:
            await self.session.close()
            raise

    async def __aexit__(self, *exc):
        await self.session.close()


async def receive(socket, seconds=10.0):
    message = await asyncio.wait_for(socket.receive(), seconds)
    assert message.type == aiohttp.WSMsgType.TEXT, message
    return json.loads(message.data)


def run_example(command, site, cwd=REPO):
    env = {**os.environ, 'DRVS_ROSBRIDGE': site['address'], 'DRVS_TOKEN': site['full']}
    env['DRVS_ROSBRIDGE'] = site['address'] if command[0] != 'node' else site['url']
    done = subprocess.run(command, env=env, cwd=cwd, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    return done.stdout.splitlines()


def test_the_roslibpy_example_asks_hosts_its_callback_and_gets_the_outlines(site):
    pytest.importorskip('roslibpy', reason='roslibpy is installed by make setup')
    lines = run_example([sys.executable, str(EXAMPLES / 'rosbridge_roslibpy.py')], site)
    assert_outlines(lines)


def assert_outlines(lines):
    """The examples' output: DRVS's answer and the outline the camera saw, in either order (the
    camera's callback may reach the client before the server's answer does)."""
    assert len(lines) == 2 and 'status 0 vision systems 1' in lines, lines
    (seen,) = [line for line in lines if line.startswith(SEES)]
    assert json.loads(seen.removeprefix(SEES)) == BOX


def test_the_roslibjs_example_does_the_same_in_node(site):
    folder = EXAMPLES / 'roslibjs'
    if shutil.which('node') is None or shutil.which('npm') is None:
        pytest.skip('Node.js and npm are not installed (make setup installs them)')
    if not (folder / 'node_modules' / 'roslib').is_dir():
        subprocess.run(['npm', 'ci', '--no-audit', '--no-fund'], cwd=folder, check=True, timeout=300)
    lines = run_example(['node', 'client.js'], site, cwd=folder)
    assert_outlines(lines)


def test_a_client_that_never_answers_delays_nobody_and_garbage_is_refused(site):
    async def main():
        async with connect(site['url'], site['full']) as mute, connect(site['url'], site['full']) as good:
            for socket, name in ((mute, '/mute/callback'), (good, '/good/callback')):
                await socket.send_json(
                    {'op': 'advertise_service', 'type': 'drvs/CallbackCoordinates', 'service': name}
                )
                for garbage in ('{"op": "publish"', '\x00\xff', '{"op": "advertise", "topic": "/a"}', '[]'):
                    await socket.send_str(garbage)
                    assert (await receive(socket))['level'] == 'error'
            started = time.monotonic()
            for socket, name in ((mute, '/mute/callback'), (good, '/good/callback')):
                await socket.send_json(
                    {
                        'op': 'call_service',
                        'id': name,
                        'service': '/drvs/detect_object_boundary',
                        'args': {
                            'algorithm': COLOUR,
                            'region_of_interest': {'max_x': 4, 'max_y': 4},
                            'callback_service': name,
                            'request_id': name,
                        },
                    }
                )
            outlines = None
            while outlines is None:  # the good client is called back, whatever the mute one does
                message = await receive(good)
                if message['op'] == 'call_service':
                    outlines = message['args']['objects']
                    await good.send_json(
                        {
                            'op': 'service_response',
                            'id': message['id'],
                            'service': '/good/callback',
                            'values': {},
                            'result': True,
                        }
                    )
            assert time.monotonic() - started < 1.5  # before the mute one's call could time out
            assert [v for p in outlines[0]['boundary']['points'] for v in (p['x'], p['y'])] == pytest.approx(
                sum(BOX, [])
            )
            # The mute client is asked too; its silence ends that one call within ~rosbridge_call_timeout.
            messages = [await receive(mute), await receive(mute)]
            assert {m['op'] for m in messages} == {'service_response', 'call_service'}
            call = next(m for m in messages if m['op'] == 'call_service')
            await asyncio.sleep(2.0)  # past the 1.5 s deadline: now the answer is too late
            await mute.send_json({'op': 'service_response', 'id': call['id'], 'service': '/mute/callback'})
            late = await receive(mute)
            assert late['op'] == 'status' and 'too late' in late['msg']

    asyncio.run(asyncio.wait_for(main(), 60))


def test_rights_per_token_over_the_wire(site):
    async def main():
        async with connect(site['url'], site['viewer']) as socket:
            await socket.send_json(
                {'op': 'advertise_service', 'type': 'drvs/CallbackCoordinates', 'service': '/v'}
            )
            assert 'may not advertise_service' in (await receive(socket))['msg']
            await socket.send_json({'op': 'subscribe', 'topic': '/drvs/objects'})  # allowed: no answer
            await socket.send_json({'op': 'set_level', 'level': 'nope'})
            assert (await receive(socket))['msg'].startswith('level:')
        upgrade = {
            'Authorization': 'Bearer drvs.0.wrong',
            'Connection': 'Upgrade',
            'Upgrade': 'websocket',
            'Sec-WebSocket-Version': '13',
            'Sec-WebSocket-Key': 'dGhlIHNhbXBsZSBub25jZQ==',
        }
        async with aiohttp.ClientSession() as session:
            async with session.get(site['url'].replace('ws://', 'http://'), headers=upgrade) as refused:
                assert refused.status == 401

    asyncio.run(asyncio.wait_for(main(), 30))


def _random_frames(site, count):
    """``count`` random frames after a warm-up of a tenth as many; then the gateway's memory within
    20 MiB of where the warm-up left it, its rosbridge connections back to none, and still serving."""
    pid, port = site['gateway'].pid, int(site['address'].rpartition(':')[2])

    async def main(count, seed):
        rng = random.Random(seed)
        async with connect(site['url'], site['full']) as socket:
            reader = asyncio.get_running_loop().create_task(_drain(socket))
            for _ in range(count):
                await socket.send_str(random_frame(rng))
            await socket.send_json({'op': 'set_level', 'level': 'none'})
            reader.cancel()

    asyncio.run(asyncio.wait_for(main(count // 10, -count), 120))
    wait_for(lambda: established(pid, port) == 0, 10, 'the warm-up connection closed')
    before = rss(pid)
    asyncio.run(asyncio.wait_for(main(count, count), 120))
    wait_for(lambda: established(pid, port) == 0, 10, 'the connection closed')
    assert rss(pid) - before < 20 * MIB, f'{(rss(pid) - before) / MIB:.1f} MiB more'
    # Still serving: the roslibpy client runs the whole flow.
    test_the_roslibpy_example_asks_hosts_its_callback_and_gets_the_outlines(site)
    assert site['gateway'].running()


async def _drain(socket):
    async for _ in socket:
        pass


def test_a_few_hundred_random_frames_leave_it_serving(site):
    _random_frames(site, 300)


@pytest.mark.slow
def test_thousands_of_random_frames_leave_it_serving(site):
    _random_frames(site, 5000)
