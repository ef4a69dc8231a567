"""The floor-plan page's side of the gateway without ROS: tickets, the live feed's coalescing, the
page's files, and the live event stream against a fake DRVS."""

import asyncio
import re

from test_app import REGISTRY, read_events, serve

from drvs.gateway.live import LiveFeed, Tickets, thin_path
from drvs.gateway.page import STATIC
from drvs.gateway.tokens import Tokens, make_entry
from drvs.testing.clock import ManualClock


def test_a_ticket_is_good_once_and_only_for_its_lifetime():
    clock = ManualClock(0.0)
    tickets = Tickets(clock, lifetime=30, limit=3)
    first, second = tickets.issue('a'), tickets.issue('b')
    assert first != second
    assert tickets.redeem(first) == 'a' and tickets.redeem(first) is None
    clock.now += 30.0
    assert tickets.redeem(second) is None
    assert tickets.redeem('') is None and tickets.redeem(None) is None
    issued = [tickets.issue(n) for n in range(5)]
    assert len(tickets) == 3 and tickets.redeem(issued[0]) is None and tickets.redeem(issued[-1]) == 4


def test_the_feed_marks_what_changed_once_however_often_it_changed():
    views = {'registry': None, 'objects': None, 'robots': {}}
    feed = LiveFeed(lambda: views['registry'], lambda: views['objects'], lambda: views['robots'])
    assert feed.poll() == []
    views['registry'] = [{'name': 'a'}]
    listener = feed.listen()
    assert listener.take() == [('registry', '')]
    for n in range(100):  # a slow listener: a hundred positions, one pending part
        views['robots'] = {'r1': {'status': {'position': [n, 0]}}}
        feed.poll()
    assert len(listener) == 1
    assert listener.take() == [('robot', 'r1')]
    assert feed.event(('robot', 'r1')) == ('robot', {'name': 'r1', 'position': [99, 0]})
    assert feed.poll() == []  # the same objects: nothing changed
    views['robots'] = {'r1': {**views['robots']['r1'], 'path': [[0, 0], [1, 1]]}}
    assert feed.poll() == [('path', 'r1')]
    assert feed.event(('path', 'r1')) == ('path', {'name': 'r1', 'points': [[0, 0], [1, 1]]})
    feed.leave(listener)
    assert not feed.listeners


def test_a_long_path_is_thinned_with_its_ends():
    points = [[float(n), 0.0] for n in range(1001)]
    thinned = thin_path(points, 400)
    assert len(thinned) == 400 and thinned[0] == points[0] and thinned[-1] == points[-1]


def test_the_page_and_its_files_are_served_without_a_token_and_nothing_else():
    token, entry = make_entry('viewer', ops=['read'], cost=2**4)

    async def test(client, drvs, gateway):
        page = await client.get('/')
        html = await page.text()
        assert page.status == 200 and page.content_type == 'text/html'
        assert 'name="viewport"' in html and '/static/floorplan.js' in html
        assert not re.search(r'(src|href)="(https?:)?//', html)  # nothing from elsewhere: works offline
        assert "default-src 'self'" in page.headers['Content-Security-Policy']
        script = await client.get('/static/floorplan.js')
        assert script.status == 200 and script.content_type == 'text/javascript'
        assert 'sessionStorage' in await script.text()
        for missing in ('/static/nothing.js', '/static/..%2Fpage.py', '/static/'):
            assert (await client.get(missing)).status == 404, missing

    serve(test, tokens=Tokens([entry]))
    assert {path.name for path in STATIC.iterdir()} >= {'index.html', 'floorplan.js', 'floorplan.css'}


def test_the_live_stream_needs_a_ticket_that_needs_a_token():
    token, entry = make_entry('viewer', ops=['read'], cost=2**4)
    _, writer = make_entry('writer', ops=['detect'], cost=2**4)

    async def test(client, drvs, gateway):
        assert (await client.post('/v1/tickets')).status == 401
        assert (await client.post('/v1/tickets', headers={'Authorization': 'Bearer drvs.x.y'})).status == 401
        assert (await client.get('/v1/live')).status == 401
        assert (await client.get('/v1/live?ticket=made-up')).status == 401
        answer = await client.post('/v1/tickets', headers={'Authorization': f'Bearer {token}'})
        ticket = await answer.json()
        assert answer.status == 201 and ticket['live'] == f'/v1/live?ticket={ticket["ticket"]}'
        drvs.robots = lambda: {'robot': {'status': {'state': 'moving', 'position': [1.0, 2.0]}}}
        async with client.get(ticket['live']) as stream:
            assert stream.status == 200 and stream.content_type == 'text/event-stream'
            events = {kind: data for _, kind, data in await read_events(stream, 2)}
            assert events['registry'] == {'vision_systems': REGISTRY}
            assert events['robot'] == {'name': 'robot', 'state': 'moving', 'position': [1.0, 2.0]}
            drvs.robots = lambda: {'robot': {'status': {'state': 'moving', 'position': [1.5, 2.0]}}}
            [(_, kind, data)] = await read_events(stream, 1)
            assert kind == 'robot' and data['position'] == [1.5, 2.0]
        assert (await client.get(ticket['live'])).status == 401  # used
        assert len(gateway.floor_plan.feed.listeners) == 0 or await _until_no_listeners(gateway)

    serve(test, tokens=Tokens([entry, writer]))


async def _until_no_listeners(gateway):
    for _ in range(200):
        if not gateway.floor_plan.feed.listeners:
            return True
        await asyncio.sleep(0.01)
    return False


def test_without_tokens_the_page_gets_a_ticket_without_one():
    async def test(client, drvs, gateway):
        answer = await client.post('/v1/tickets')
        assert answer.status == 201
        async with client.get((await answer.json())['live']) as stream:
            [(_, kind, _)] = await read_events(stream, 1)
            assert kind == 'registry'

    serve(test)
