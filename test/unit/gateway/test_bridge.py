"""The rosbridge endpoint against a fake ROS (no master): the DRVS flow (host a callback, ask, get the
outlines), deadlines on every call, tokens and rights, subscriptions, a slow client's bounded queue,
heartbeats, and hostile frames."""

import asyncio
import json
import random
import threading
import time

import aiohttp
import pytest
from aiohttp import WSMsgType, test_utils

from drvs.gateway.backend import NoServer
from drvs.gateway.bridge import Rosbridge
from drvs.gateway.params import GatewaySettings
from drvs.gateway.rosjson import FieldError
from drvs.gateway.tokens import Tokens, make_entry
from drvs.testing.hostile_frames import random_frame

DETECT = '/drvs/detect_object_boundary'
COLOUR = 'colour:0,0,150,80,80,255'
OUTLINE = {'boundary': {'points': [{'x': 1.0, 'y': 1.0, 'z': 0.0}]}}


class FakeRos:
    """ROS as the endpoint sees it: DRVS accepts every call and, when its ``callback_service`` is
    hosted, calls it back (on a thread of its own, as a vision system would) with one outline."""

    services = {DETECT: 'detect', '/drvs/watch_object_boundary': 'watch'}
    topics = {'/drvs/registry': 'drvs/Registry', '/drvs/objects': 'drvs/TrackedObjects'}
    hostable = ('drvs/CallbackCoordinates',)

    def __init__(self):
        self.calls, self.hosted, self.receivers = [], {}, {}
        self.answers = []  # what each hosted service's call ended with: a dict or an exception
        self.no_server = False

    def call(self, service, args, timeout):
        self.calls.append((service, args, timeout))
        if self.no_server:
            raise NoServer(f'service {service}: timed out after {timeout:g} s')
        args = args if isinstance(args, dict) else {}
        if 'colour' in args:
            raise FieldError('colour', 'no such field')
        serve = self.hosted.get(str(args.get('callback_service')))
        if serve is not None:
            request = {'request_id': args.get('request_id', ''), 'objects': [OUTLINE]}
            threading.Thread(target=self._call_back, args=(serve, request), daemon=True).start()
        return {'status': 0, 'message': 'forwarded to 1 vision system', 'vision_systems': 1}

    def _call_back(self, serve, request):
        try:
            self.answers.append(serve(request))
        except Exception as error:
            self.answers.append(error)

    def host(self, graph_name, service_type, serve):
        self.hosted[graph_name] = serve
        return lambda: self.hosted.pop(graph_name, None)

    def subscribe(self, topic, deliver):
        self.receivers.setdefault(topic, set()).add(deliver)
        return lambda: self.receivers[topic].discard(deliver)

    def publish(self, topic, message):
        for deliver in list(self.receivers.get(topic, ())):
            deliver(message)


def serve(test, tokens=None, **settings):
    """Run ``await test(client, ros, bridge)`` against the endpoint on a fake ROS."""
    ros = FakeRos()
    settings = {'rosbridge_call_timeout': 0.3, 'max_requests_per_s': 1000, 'burst': 1000, **settings}
    bridge = Rosbridge(ros, GatewaySettings(**settings), tokens, graph_prefix='/gateway/rosbridge')

    async def main():
        async with test_utils.TestClient(test_utils.TestServer(bridge.application())) as client:
            await test(client, ros, bridge)

    asyncio.run(asyncio.wait_for(main(), 30))
    return ros


async def receive(socket, seconds=5.0):
    message = await asyncio.wait_for(socket.receive(), seconds)
    assert message.type == WSMsgType.TEXT, message
    return json.loads(message.data)


async def until(condition, seconds=5.0):
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, 'condition not met in time'
        await asyncio.sleep(0.01)


def ask(callback='/robot/callback', id='call_service:1', **args):
    return {
        'op': 'call_service',
        'id': id,
        'service': DETECT,
        'args': {'algorithm': COLOUR, 'callback_service': callback, 'request_id': 'r1', **args},
    }


ADVERTISE = {'op': 'advertise_service', 'type': 'drvs/CallbackCoordinates', 'service': '/robot/callback'}


def test_a_client_hosts_its_callback_asks_and_receives_the_outlines():
    async def test(client, ros, bridge):
        async with client.ws_connect('/') as socket:
            await socket.send_json(ADVERTISE)
            await socket.send_json(ask())
            call = await receive(socket)
            answer = await receive(socket)
            if call['op'] == 'service_response':
                call, answer = answer, call
            assert answer == {
                'op': 'service_response',
                'id': 'call_service:1',
                'service': DETECT,
                'values': {'status': 0, 'message': 'forwarded to 1 vision system', 'vision_systems': 1},
                'result': True,
            }
            assert call['op'] == 'call_service' and call['service'] == '/robot/callback'
            assert call['args'] == {'request_id': 'r1', 'objects': [OUTLINE]}
            await socket.send_json(
                {
                    'op': 'service_response',
                    'id': call['id'],
                    'service': '/robot/callback',
                    'values': {},
                    'result': True,
                }
            )
            await until(lambda: ros.answers)
            assert ros.answers == [{}]
            # The hosted service lives under the gateway's name; the call named it for DRVS.
            (graph_name,) = ros.hosted
            assert graph_name == '/gateway/rosbridge/c1/robot/callback'
            assert ros.calls[0][1]['callback_service'] == graph_name
            await socket.send_json({'op': 'unadvertise_service', 'service': '/robot/callback'})
            await until(lambda: not ros.hosted)

    serve(test)


def test_a_client_that_never_answers_times_out_that_call_only():
    async def test(client, ros, bridge):
        async with client.ws_connect('/') as mute, client.ws_connect('/') as other:
            await mute.send_json(ADVERTISE)
            await other.send_json(ADVERTISE)
            started = time.monotonic()
            await mute.send_json(ask(id='m'))
            await other.send_json(ask(id='o'))
            for _ in range(2):  # the other client answers its call at once
                message = await receive(other)
                if message['op'] == 'call_service':
                    await other.send_json(
                        {
                            'op': 'service_response',
                            'id': message['id'],
                            'service': '/robot/callback',
                            'values': {},
                        }
                    )
            await until(lambda: len(ros.answers) == 2)
            assert time.monotonic() - started < 2.0
            errors = [answer for answer in ros.answers if isinstance(answer, Exception)]
            assert len(errors) == 1 and 'did not answer within 0.3 s' in str(errors[0])
            assert {} in ros.answers
            assert bridge.counters.snapshot()['client_timeouts'] == 1
            (session,) = [s for s in bridge.sessions if s.number == 1]
            assert len(session.pending) == 0
            # Too late: the answer is refused, the connection goes on.
            call = next(m for m in [await receive(mute), await receive(mute)] if m['op'] == 'call_service')
            await mute.send_json({'op': 'service_response', 'id': call['id'], 'service': '/robot/callback'})
            refused = await receive(mute)
            assert refused['op'] == 'status' and refused['level'] == 'error' and 'too late' in refused['msg']

    serve(test)


def test_a_refusing_client_fails_the_call_and_a_client_leaving_fails_its_calls():
    async def test(client, ros, bridge):
        async with client.ws_connect('/') as socket:
            await socket.send_json(ADVERTISE)
            await socket.send_json(ask())
            call = next(
                m for m in [await receive(socket), await receive(socket)] if m['op'] == 'call_service'
            )
            await socket.send_json(
                {
                    'op': 'service_response',
                    'id': call['id'],
                    'service': '/robot/callback',
                    'result': False,
                    'values': 'busy',
                }
            )
            await until(lambda: ros.answers)
            assert 'result false: busy' in str(ros.answers[0])
            await socket.send_json(ask())
            await until(lambda: len(bridge.sessions) == 1 and len(next(iter(bridge.sessions)).pending) == 1)
        await until(lambda: len(ros.answers) == 2)
        assert 'disconnected' in str(ros.answers[1])
        await until(lambda: not bridge.sessions and not ros.hosted)

    serve(test)


@pytest.mark.parametrize(
    ('frame', 'expect'),
    [
        ('{"op": "publish", "topic": "/drvs/registry", "msg": {}}', "op: 'publish' is not supported here"),
        (
            '{"op": "call_service", "service": "/rosapi/topics", "id": 3}',
            "service: '/rosapi/topics' is not served",
        ),
        ('{"op": "advertise_service", "type": "std_srvs/Trigger", "service": "/t"}', 'type:'),
        ('{"op": "advertise_service", "type": "drvs/CallbackCoordinates", "service": "/a b"}', 'service:'),
        ('{"op": "subscribe", "topic": "/rosout"}', "topic: '/rosout' is not served"),
        ('{"op": "subscribe", "topic": "/drvs/registry", "type": "std_msgs/String"}', 'type:'),
        ('{"op": "unadvertise_service", "service": "/never"}', 'not advertised'),
        ('{"op": "service_response", "id": "x", "service": "/s"}', 'id:'),
        (
            '{"op": "call_service", "service": "' + DETECT + '", "args": {"colour": 1}}',
            'INVALID: args.colour',
        ),
        ('garbage', 'frame: not JSON'),
    ],
)
def test_bad_frames_get_an_error_status_and_the_connection_goes_on(frame, expect):
    async def test(client, ros, bridge):
        async with client.ws_connect('/') as socket:
            await socket.send_str(frame)
            answer = await receive(socket)
            assert answer['op'] == 'status' and answer['level'] == 'error', answer
            assert expect in answer['msg']
            if '"call_service"' in frame:  # a refused call is also answered, so that no client waits
                failed = await receive(socket)
                assert failed['op'] == 'service_response' and failed['result'] is False
                assert failed['values'] == answer['msg']
            await socket.send_bytes(b'\x00\x01')
            assert 'binary frames' in (await receive(socket))['msg']
            await socket.send_json(ask(callback='/nobody', id='after'))
            answers = [await receive(socket)]
            if answers[0]['op'] == 'service_response' and answers[0]['id'] != 'after':
                answers.append(await receive(socket))
            assert answers[-1]['id'] == 'after' and answers[-1]['result'] is True

    serve(test)


def test_no_drvs_server_fails_the_call_within_its_deadline():
    async def test(client, ros, bridge):
        ros.no_server = True
        async with client.ws_connect('/') as socket:
            await socket.send_json({**ask(), 'timeout': 60})
            status, answer = await receive(socket), await receive(socket)
            assert status['op'] == 'status' and status['msg'].startswith('NO_SERVER: ')
            assert answer == {
                'op': 'service_response',
                'service': DETECT,
                'id': 'call_service:1',
                'values': status['msg'],
                'result': False,
            }
            assert ros.calls[0][2] == 2.0  # a client's timeout is capped by ~server_timeout

    serve(test)


def test_a_huge_frame_closes_the_connection_cleanly():
    async def test(client, ros, bridge):
        async with client.ws_connect('/') as socket:
            await socket.send_str(json.dumps({'op': 'set_level', 'level': 'info', 'pad': 'x' * 5000}))
            message = await asyncio.wait_for(socket.receive(), 5)
            assert message.type == WSMsgType.CLOSE and message.data == aiohttp.WSCloseCode.MESSAGE_TOO_BIG
        await until(lambda: not bridge.sessions)

    serve(test, rosbridge_max_frame=1024)


def test_subscriptions_deliver_rosbridge_publish_messages_throttled():
    async def test(client, ros, bridge):
        async with client.ws_connect('/') as socket:
            await socket.send_json(
                {'op': 'subscribe', 'id': 's1', 'topic': '/drvs/registry', 'type': 'drvs/Registry'}
            )
            await socket.send_json({'op': 'subscribe', 'topic': '/drvs/objects', 'throttle_rate': 60_000})
            await until(lambda: len(ros.receivers.get('/drvs/objects', ())) == 1)
            ros.publish('/drvs/registry', {'vision_systems': []})
            assert await receive(socket) == {
                'op': 'publish',
                'topic': '/drvs/registry',
                'msg': {'vision_systems': []},
            }
            for i in range(3):
                ros.publish('/drvs/objects', {'n': i})
            assert (await receive(socket))['msg'] == {'n': 0}  # then nothing for a minute
            await socket.send_json({'op': 'unsubscribe', 'id': 's1', 'topic': '/drvs/registry'})
            await until(lambda: not ros.receivers['/drvs/registry'])
        await until(lambda: not ros.receivers['/drvs/objects'])

    serve(test)


def test_a_slow_client_loses_its_oldest_messages_and_is_told():
    async def test(client, ros, bridge):
        async with client.ws_connect('/') as socket:
            await socket.send_json({'op': 'set_level', 'level': 'warning'})
            await until(lambda: bridge.sessions)
            (session,) = bridge.sessions
            for i in range(100):  # faster than any writer: all in one turn of the loop
                session.send({'op': 'publish', 'topic': '/drvs/objects', 'msg': {'n': i}})
            warning = await receive(socket)
            assert warning == {
                'op': 'status',
                'level': 'warning',
                'msg': '96 message(s) dropped: this client read too slowly',
            }
            assert [(await receive(socket))['msg']['n'] for _ in range(4)] == [96, 97, 98, 99]
            assert bridge.counters.snapshot()['dropped'] == 96

    serve(test, rosbridge_queue=4)


def test_heartbeats_reap_a_client_that_answers_no_ping():
    async def test(client, ros, bridge):
        socket = await client.ws_connect('/', autoping=False)
        await until(lambda: bridge.sessions)
        await until(lambda: not bridge.sessions, 5.0)  # closed within half a heartbeat of a ping
        await socket.close()

    serve(test, rosbridge_heartbeat=0.2)


def test_tokens_in_the_auth_op_a_subprotocol_or_the_header_with_rights_per_op():
    robot, robot_entry = make_entry('robot', ops=['detect'], algorithms=['colour'], cost=2**4)
    viewer, viewer_entry = make_entry('viewer', ops=['read'], cost=2**4)
    tokens = Tokens([robot_entry, viewer_entry])

    async def test(client, ros, bridge):
        async with client.ws_connect('/') as socket:
            await socket.send_json(ask())
            assert 'authenticate first' in (await receive(socket))['msg']
            assert (await receive(socket))['result'] is False
            await socket.send_json({'op': 'auth', 'mac': 'drvs.nope.nope'})
            assert (await receive(socket))['msg'] == 'mac: unknown token'
            await socket.send_json(
                {
                    'op': 'auth',
                    'mac': robot,
                    'client': '',
                    'dest': '',
                    'rand': '',
                    't': 0,
                    'level': 'user',
                    'end': 0,
                }
            )
            await socket.send_json(ask(callback='/nobody', id='a1'))
            assert (await receive(socket))['id'] == 'a1'
            await socket.send_json(ask(callback='/nobody', id='a2', algorithm='apriltag:tag36h11'))
            refused = await receive(socket)
            assert (
                refused['op'] == 'status'
                and "may not call_service with the algorithm 'apriltag'" in refused['msg']
            )
            assert (await receive(socket))['result'] is False
            await socket.send_json({'op': 'subscribe', 'topic': '/drvs/registry'})
            assert 'it needs read' in (await receive(socket))['msg']
        async with client.ws_connect('/', protocols=('drvs', f'bearer.{viewer}')) as socket:
            assert socket.protocol == 'drvs'
            await socket.send_json({'op': 'subscribe', 'topic': '/drvs/registry'})
            await socket.send_json(ADVERTISE)
            assert 'it needs detect or watch' in (await receive(socket))['msg']
        async with client.ws_connect('/', headers={'Authorization': f'Bearer {robot}'}) as socket:
            await socket.send_json(ask(callback='/nobody', id='h1'))
            assert (await receive(socket))['id'] == 'h1'
        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
            await client.ws_connect('/', protocols=('bearer.drvs.0.wrong',))
        assert refused.value.status == 401

    serve(test, tokens=tokens)


def test_a_connection_that_never_authenticates_is_closed():
    _, entry = make_entry('robot', cost=2**4)

    async def test(client, ros, bridge):
        async with client.ws_connect('/') as socket:
            message = await asyncio.wait_for(socket.receive(), 5)
            assert message.type == WSMsgType.CLOSE and message.data == 4001

    import drvs.gateway.bridge as module

    deadline, module.AUTH_DEADLINE = module.AUTH_DEADLINE, 0.2
    try:
        serve(test, tokens=Tokens([entry]))
    finally:
        module.AUTH_DEADLINE = deadline


def test_connections_per_token_and_foreign_web_pages_are_limited():
    async def test(client, ros, bridge):
        first = await client.ws_connect('/')
        second = await client.ws_connect('/')
        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
            await client.ws_connect('/')
        assert refused.value.status == 429
        with pytest.raises(aiohttp.WSServerHandshakeError) as foreign:
            await client.ws_connect('/', headers={'Origin': 'http://evil.example'})
        assert foreign.value.status == 403
        await first.close()
        await second.close()
        await until(lambda: not bridge.sessions)
        async with client.ws_connect('/', headers={'Origin': 'http://127.0.0.1:8080'}):
            pass

    serve(test, rosbridge_max_clients=2)


def test_thousands_of_random_frames_leave_the_endpoint_serving():
    async def test(client, ros, bridge):
        rng = random.Random(27)
        async with client.ws_connect('/') as socket:
            reader = asyncio.get_running_loop().create_task(_drain(socket))
            for _ in range(3000):
                await socket.send_str(random_frame(rng))
            await socket.send_json({'op': 'set_level', 'level': 'error'})
            reader.cancel()
        await until(lambda: not bridge.sessions)
        assert not ros.hosted
        ros.answers.clear()
        async with client.ws_connect('/') as socket:  # the whole flow still works
            await socket.send_json(ADVERTISE)
            await socket.send_json(ask(id='last'))
            call = next(
                m for m in [await receive(socket), await receive(socket)] if m['op'] == 'call_service'
            )
            await socket.send_json({'op': 'service_response', 'id': call['id'], 'service': '/robot/callback'})
            await until(lambda: {} in ros.answers)
        counters = bridge.counters.snapshot()
        assert counters['frames'] >= 3001 and counters['refused'] > 500 and not counters['errors'], counters

    serve(test, rosbridge_call_timeout=0.05)


async def _drain(socket):
    async for _ in socket:
        pass


def test_the_docs_quote_the_examples_the_live_test_runs():
    from drvs.testing.harness import REPO

    page = (REPO / 'docs' / 'gateway.md').read_text()
    for example, fence in (('rosbridge_roslibpy.py', 'python'), ('roslibjs/client.js', 'js')):
        text = (REPO / 'examples' / example).read_text()
        assert f'```{fence}\n{text}```' in page, f'docs/gateway.md does not quote examples/{example} as it is'
