"""The gateway's HTTP side against a fake DRVS (no ROS): routes, the OpenAPI document, status
mapping, tokens, limits, watches over Server-Sent Events, and a flood of random bodies."""

import asyncio
import json
import random
import time

import pytest
from aiohttp import test_utils

from drvs.common.status import ACCEPTED, BUSY, INVALID, RATE_LIMITED, UNAVAILABLE, UNSUPPORTED
from drvs.gateway.app import Gateway
from drvs.gateway.backend import Ack, NoServer
from drvs.gateway.params import GatewaySettings
from drvs.gateway.routes import ROUTES, openapi
from drvs.gateway.tokens import Tokens, make_entry
from drvs.testing.clock import ManualClock
from drvs.testing.hostile_bodies import random_body

REGION = {'min_x': 0, 'min_y': 0, 'max_x': 4, 'max_y': 4}
COLOUR = 'colour:0,0,150,80,80,255'
DETECT = {'algorithm': COLOUR, 'region': REGION, 'wait': 5}
REGISTRY = [
    {
        'name': '/cam1/detect_object_boundary',
        'provider': '/cam1',
        'field_of_view': [[0, 0], [2, 0], [2, 2], [0, 2]],
        'algorithms': ['apriltag', 'colour'],
    },
    {
        'name': '/cam2/detect_object_boundary',
        'provider': '/cam2',
        'field_of_view': [[5, 5], [8, 5], [8, 8], [5, 8]],
        'algorithms': ['motion'],
    },
]
CALLBACK = {
    'vision_system': '/cam1/detect_object_boundary',
    'stamp': 12.5,
    'algorithm': COLOUR,
    'objects': [],
}


class FakeDrvs:
    """DRVS as the gateway sees it: answers ``ack`` (or raises ``no_server``), records every call, and
    calls the gateway back with ``callbacks`` after each accepted request or watch."""

    def __init__(self):
        self.ack = Ack(ACCEPTED, 'accepted', vision_systems=1, period=0.5, duration=10.0)
        self.no_server = None
        self.callbacks = [CALLBACK]
        self.calls = []
        self.withdrawals = []  # answers to withdrawals, then ACCEPTED
        self.loop = self.gateway = None

    def _answer(self, request_id):
        if self.no_server:
            raise NoServer(self.no_server)
        if self.ack.status == ACCEPTED:
            for data in self.callbacks:
                self.loop.call_soon_threadsafe(self.gateway.deliver, request_id, data)
        return self.ack

    def detect(self, body, request_id):
        self.calls.append(('detect', request_id, body))
        return self._answer(request_id)

    def watch(self, body, request_id, duration):
        self.calls.append(('watch', request_id, duration))
        if not duration:
            return self.withdrawals.pop(0) if self.withdrawals else Ack(ACCEPTED)
        return self._answer(request_id)

    def registry(self):
        return REGISTRY

    def objects(self):
        return None

    def robots(self):
        return {}

    def diagnostics(self):
        return [
            {
                'name': 'drvs: /drvs',
                'level': 'OK',
                'message': 'ok',
                'hardware_id': 'h',
                'values': {},
                'age': 0.5,
            }
        ]


def serve(test, tokens=None, clock=time.monotonic, **settings):
    """Run ``await test(client, drvs, gateway)`` against a gateway on a fake DRVS."""
    drvs = FakeDrvs()
    gateway = Gateway(drvs, GatewaySettings(**settings), tokens, clock)
    drvs.gateway = gateway

    async def main():
        drvs.loop = asyncio.get_running_loop()
        async with test_utils.TestClient(test_utils.TestServer(gateway.application())) as client:
            await test(client, drvs, gateway)

    asyncio.run(asyncio.wait_for(main(), 30))
    return drvs


async def until(condition, seconds=5.0):
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, 'condition not met in time'
        await asyncio.sleep(0.01)


async def read_events(response, count, seconds=5.0):
    """The next ``count`` events of an SSE stream as (id, event, data)."""
    events, fields = [], {}
    while len(events) < count:
        line = (await asyncio.wait_for(response.content.readline(), seconds)).decode().rstrip('\n')
        if not line:
            if 'event' in fields:
                events.append((int(fields['id']), fields['event'], json.loads(fields['data'])))
            fields = {}
        elif not line.startswith(':'):
            key, _, value = line.partition(': ')
            fields[key] = value
    return events


def test_the_openapi_document_has_every_route_and_nothing_else():
    async def test(client, drvs, gateway):
        served = {
            (route.method, route.resource.canonical)
            for route in client.app.router.routes()
            if route.method != 'HEAD'
        }
        response = await client.get('/v1/openapi.json')
        document = await response.json()
        documented = {(method.upper(), path) for path, item in document['paths'].items() for method in item}
        assert served == documented == {(route.method, route.path) for route in ROUTES}
        assert document == openapi() and document['openapi'].startswith('3.')
        refs = {ref.split('/')[-1] for ref in _refs(document)}
        assert refs <= set(document['components']['schemas'])

    serve(test)


def _refs(value):
    if isinstance(value, dict):
        for key, item in value.items():
            if key == '$ref':
                yield item
            else:
                yield from _refs(item)
    elif isinstance(value, list):
        for item in value:
            yield from _refs(item)


def test_detect_answers_with_the_callbacks_as_soon_as_every_vision_system_called_back():
    async def test(client, drvs, gateway):
        started = time.monotonic()
        response = await client.post('/v1/detect', json=DETECT)
        answer = await response.json()
        assert response.status == 200, answer
        assert (answer['status'], answer['vision_systems'], answer['callbacks']) == (
            'ACCEPTED',
            1,
            [CALLBACK],
        )
        assert time.monotonic() - started < 4, 'waited for the whole `wait` although every camera answered'
        (call,) = drvs.calls
        assert call[2].algorithm == COLOUR and call[1] == answer['request_id']

    serve(test)


@pytest.mark.parametrize(
    ('status', 'http', 'error'),
    [
        (INVALID, 400, 'INVALID'),
        (UNSUPPORTED, 422, 'UNSUPPORTED'),
        (RATE_LIMITED, 429, 'RATE_LIMITED'),
        (BUSY, 503, 'BUSY'),
        (UNAVAILABLE, 503, 'UNAVAILABLE'),
    ],
)
def test_drvs_refusals_map_to_http(status, http, error):
    async def test(client, drvs, gateway):
        drvs.ack = Ack(status, 'region_of_interest: the message of DRVS', retry_after=0.4)
        response = await client.post('/v1/detect', json=DETECT)
        answer = await response.json()
        assert (response.status, answer['error']) == (http, error)
        assert answer['message'] == 'region_of_interest: the message of DRVS'
        if status == INVALID:
            assert answer['field'] == 'region'
        if status == UNSUPPORTED:
            assert answer['available_algorithms'] == ['apriltag', 'colour', 'motion']
        assert response.headers.get('Retry-After') == ('1' if http in (429, 503) else None)

    serve(test)


def test_no_drvs_server_is_503_with_retry_after():
    async def test(client, drvs, gateway):
        drvs.no_server = 'service /drvs/detect_object_boundary: timed out after 2 s'
        for path, body in (('/v1/detect', DETECT), ('/v1/watches', {'algorithm': COLOUR, 'region': REGION})):
            response = await client.post(path, json=body)
            answer = await response.json()
            assert (response.status, answer['error'], response.headers['Retry-After']) == (
                503,
                'NO_SERVER',
                '1',
            )
            assert answer['message'] == drvs.no_server
        assert len(gateway.hub) == 0

    serve(test)


@pytest.mark.parametrize(
    ('data', 'http', 'field'),
    [
        (b'{"algorithm": ', 400, 'body'),
        (b'[]', 400, 'body'),
        (json.dumps({**DETECT, 'colour': 1}).encode(), 400, 'colour'),
        (json.dumps({**DETECT, 'wait': 'long'}).encode(), 400, 'wait'),
        (json.dumps({**DETECT, 'region': {**REGION, 'min_x': 9}}).encode(), 400, 'region'),
        (b'{"x": "' + b'a' * 20000 + b'"}', 413, None),
    ],
)
def test_bad_bodies_are_refused_naming_the_field(data, http, field):
    async def test(client, drvs, gateway):
        response = await client.post('/v1/detect', data=data, headers={'Content-Type': 'application/json'})
        answer = await response.json()
        assert response.status == http, answer
        assert answer.get('field') == field
        assert drvs.calls == []

    serve(test)


def test_tokens_401_403_and_rights_by_algorithm():
    robot, robot_entry = make_entry('robot', ops=['detect', 'watch'], algorithms=['colour'], cost=16)
    viewer, viewer_entry = make_entry('viewer', ops=['read'], cost=16)

    async def test(client, drvs, gateway):
        def bearer(token):
            return {'Authorization': f'Bearer {token}'}

        cases = [
            (client.post('/v1/detect', json=DETECT), 401),
            (client.post('/v1/detect', json=DETECT, headers=bearer('drvs.nope.nope')), 401),
            (client.post('/v1/detect', json=DETECT, headers=bearer(viewer)), 403),
            (client.post('/v1/detect', json={**DETECT, 'algorithm': 'motion'}, headers=bearer(robot)), 403),
            (client.get('/v1/vision_systems', headers=bearer(robot)), 403),
            (client.get('/v1/vision_systems', headers=bearer(viewer)), 200),
            (client.post('/v1/detect', json=DETECT, headers=bearer(robot)), 200),
            (client.get('/v1/openapi.json'), 200),
        ]
        for request, http in cases:
            response = await request
            assert response.status == http, await response.text()
        response = await client.get('/v1/health')
        assert response.headers['WWW-Authenticate'].startswith('Bearer')

    serve(test, tokens=Tokens([robot_entry, viewer_entry]))


def test_the_request_rate_is_limited_per_token():
    first, first_entry = make_entry('first', cost=16)
    second, second_entry = make_entry('second', cost=16)

    async def test(client, drvs, gateway):
        statuses = []
        for token in (first, first, first, second):
            response = await client.get('/v1/objects', headers={'Authorization': f'Bearer {token}'})
            statuses.append(response.status)
        assert statuses == [200, 200, 429, 200]
        assert response.status == 200

    serve(test, tokens=Tokens([first_entry, second_entry]), burst=2, max_requests_per_s=0.01)


def test_a_watch_streams_its_callbacks_and_resumes_after_last_event_id():
    async def test(client, drvs, gateway):
        response = await client.post(
            '/v1/watches', json={'algorithm': COLOUR, 'region': REGION, 'period': 0.5}
        )
        watch = await response.json()
        assert response.status == 201 and response.headers['Location'] == watch['events']
        assert (watch['vision_systems'], watch['period']) == (1, 0.5)
        stream = await client.get(watch['events'])
        assert stream.headers['Content-Type'] == 'text/event-stream'
        assert await read_events(stream, 1) == [(1, 'callback', CALLBACK)]  # delivered before anyone listened
        request_id = drvs.calls[0][1]
        gateway.deliver(request_id, {**CALLBACK, 'stamp': 13.0})
        gateway.deliver(request_id, {**CALLBACK, 'stamp': 14.0})
        assert [event[:2] for event in await read_events(stream, 2)] == [(2, 'callback'), (3, 'callback')]
        stream.close()
        resumed = await client.get(watch['events'], headers={'Last-Event-ID': '2'})
        assert await read_events(resumed, 1) == [(3, 'callback', {**CALLBACK, 'stamp': 14.0})]
        bad = await client.get(watch['events'], headers={'Last-Event-ID': 'x'})
        assert (bad.status, (await bad.json())['field']) == (400, 'Last-Event-ID')
        deleted = await client.delete(f'/v1/watches/{watch["id"]}')
        assert deleted.status == 204
        assert (await read_events(resumed, 1))[0][1:] == ('end', {'reason': 'deleted'})
        await until(lambda: ('watch', request_id, 0.0) in drvs.calls)
        assert (await client.get(watch['events'])).status == 404
        assert (await client.delete(f'/v1/watches/{watch["id"]}')).status == 404

    serve(test)


def test_watches_are_renewed_while_listened_to_and_withdrawn_after_the_linger():
    clock = ManualClock(0.0)

    async def test(client, drvs, gateway):
        watch = await (await client.post('/v1/watches', json={'algorithm': COLOUR, 'region': REGION})).json()
        request_id = drvs.calls[0][1]
        stream = await client.get(watch['events'])
        await read_events(stream, 1)
        clock.now = 5.0  # half the granted 10 s
        gateway.tick()
        await until(lambda: len(drvs.calls) == 2)
        assert drvs.calls[1] == ('watch', request_id, 10.0)
        stream.close()
        await until(lambda: not gateway.hub.get(watch['id']).listeners)
        clock.now = 5.0 + 30.0
        gateway.tick()
        await until(lambda: ('watch', request_id, 0.0) in drvs.calls)
        assert gateway.hub.get(watch['id']) is None

    serve(test, clock=clock, watch_duration=10.0, watch_linger=30.0)


def test_watch_limits_per_token_and_listeners_per_watch():
    async def test(client, drvs, gateway):
        body = {'algorithm': COLOUR, 'region': REGION}
        opened = [await client.post('/v1/watches', json=body) for _ in range(3)]
        assert [response.status for response in opened] == [201, 201, 429]
        watch = await opened[0].json()
        streams = [await client.get(watch['events']) for _ in range(2)]
        assert [stream.status for stream in streams] == [200, 200]
        third = await client.get(watch['events'])
        assert (third.status, (await third.json())['error']) == (429, 'TOO_MANY_LISTENERS')

    serve(test, max_watches_per_token=2, max_listeners=2)


def test_read_routes():
    async def test(client, drvs, gateway):
        systems = await (await client.get('/v1/vision_systems')).json()
        assert systems == {'vision_systems': REGISTRY}
        covered = await (await client.get('/v1/coverage?min_x=1&min_y=1&max_x=3&max_y=3')).json()
        assert [entry['name'] for entry in covered['vision_systems']] == ['/cam1/detect_object_boundary']
        assert covered['algorithms'] == ['apriltag', 'colour']
        touching = await (await client.get('/v1/coverage?min_x=2&min_y=0&max_x=3&max_y=1')).json()
        assert touching['vision_systems'] == []
        bad = await client.get('/v1/coverage?min_x=1&min_y=1&max_x=3')
        assert (bad.status, (await bad.json())['field']) == (400, 'max_y')
        objects = await (await client.get('/v1/objects')).json()
        assert objects == {'stamp': None, 'algorithms': [], 'objects': []}
        health = await (await client.get('/v1/health')).json()
        assert health['server']['level'] == 'OK' and health['gateway']['watches'] == 0
        missing = await client.get('/v1/nothing')
        assert (missing.status, (await missing.json())['error']) == (404, 'NOT_FOUND')

    serve(test)


def test_random_bodies_get_clean_answers_and_the_gateway_keeps_serving():
    rng = random.Random(27)

    async def test(client, drvs, gateway):
        drvs.callbacks = []
        seen = set()
        for _ in range(500):
            path = rng.choice(['/v1/detect', '/v1/watches'])
            response = await client.post(
                path, data=random_body(rng, path), headers={'Content-Type': 'application/json'}
            )
            assert 200 <= response.status < 500, (response.status, await response.text())
            body = await response.json()
            seen.add(response.status)
            if response.status == 201:
                await client.delete(f'/v1/watches/{body["id"]}')
        assert {200, 201, 400} <= seen
        assert gateway.counters.snapshot()['errors'] == 0
        assert (await client.get('/v1/health')).status == 200

    serve(test, max_requests_per_s=1e6, burst=10**6, max_watches_per_token=10**4)


def test_a_withdrawal_refused_for_now_is_retried():
    async def test(client, drvs, gateway):
        drvs.withdrawals = [
            Ack(RATE_LIMITED, 'rate limited', retry_after=0.01),
            Ack(BUSY, 'busy', retry_after=0.01),
        ]
        watch = await (await client.post('/v1/watches', json={'algorithm': COLOUR, 'region': REGION})).json()
        assert (await client.delete(f'/v1/watches/{watch["id"]}')).status == 204
        await until(lambda: [call[2] for call in drvs.calls].count(0.0) == 3)
        assert drvs.withdrawals == []

    serve(test)
