"""The gateway: request → first callback through HTTP against the same request over ROS, Server-Sent
Events delivery, 200 event streams held, and requests/s with and without tokens.

What is measured, on one graph: ``drvs_server``, one fake vision system
(``test/nodes/fake_vision_system.py``: it answers at once with one box, stamped when it calls
back) and two ``drvs_gateway`` nodes, one with a tokens file and one without.

- Request → first callback: rounds of ``POST /v1/detect`` (``wait`` 5 s; the answer comes as soon
  as the one vision system asked has called back) over one persistent HTTP connection, against
  the same request made by a ROS robot (``bench/nodes/latency_client.py``) in the same run, as
  many rounds, in alternating blocks (:data:`BLOCKS`) so both meet the same load: the ratio is what
  the gateway adds (an HTTP round trip, JSON, its own ROS call and callback).
- SSE delivery: a watch (period 0.1 s) read as an event stream; each callback event's delay from
  the fake's stamp (the moment it called the gateway back) to its arrival at the client.
- 200 listeners: one watch read by 200 event streams at once (``~max_listeners`` raised to 200);
  the gateway's resident memory before they open, while they are held (after every one has had an
  event), and after they have gone.
- Requests/s: ``GET /v1/vision_systems`` from 8 concurrent clients for a few seconds, with a token
  and without (the token's scrypt check is paid once and then remembered).

The rate limits of the server and the gateways are raised: one client asking back to back would
otherwise be refused after its burst. The docs: docs/gateway.md; the gateway: docs/nodes/drvs_gateway.md.
"""

from __future__ import annotations

import asyncio
import http.client
import json
import time
from pathlib import Path

import aiohttp
import psutil

from bench.common import Context, Section, spread, table, target
from drvs.gateway.tokens import add_token
from drvs.testing.harness import REPO, RosHarness, free_port, read_json_lines, wait_for

NAME = 'gateway'
TITLE = 'The gateway: HTTP and Server-Sent Events against ROS'

NODES = Path(__file__).resolve().parent / 'nodes'
ALGORITHM = 'colour:0,0,150,80,80,255'
REGION = {'min_x': 0, 'min_y': 0, 'max_x': 4, 'max_y': 4}
BOX = [[1.0, 1.0], [1.4, 1.0], [1.4, 1.4], [1.0, 1.4]]
LISTENERS = 200
CONCURRENCY = 8
UNLIMITED = {'max_requests_per_s': 1e6, 'burst': 1_000_000}


def start_graph(ros: RosHarness, ctx: Context) -> tuple[dict, str]:
    """The server, the fake camera, the echo service and both gateways: (gateway name -> URL, token)."""
    server = ros.start_node('nodes/drvs_server', name='drvs', params=UNLIMITED)
    ros.wait_for_service('/drvs/detect_object_boundary', node=server)
    ros.start_node(
        REPO / 'test/nodes/fake_vision_system.py',
        name='cam1',
        params={
            'output': ctx.work_dir / 'gateway-cam1.jsonl',
            'field_of_view': [[0, 0], [4, 0], [4, 4], [0, 4]],
            'algorithms': ['colour'],
            'answer': True,
            'watch': True,
            'objects': [BOX],
            'renew': 3.0,
        },
    )
    echo = ros.start_node(NODES / 'echo.py', name='echo')
    ros.wait_for_service('/echo/detect_object_boundary', node=echo)
    tokens = ctx.work_dir / 'gateway-tokens.json'
    tokens.unlink(missing_ok=True)
    token = add_token(tokens, 'bench')
    urls, nodes = {}, {}
    for name, extra in (('tokens', {'tokens': tokens}), ('open', {})):
        urls[name] = f'http://127.0.0.1:{free_port()}'
        nodes[name] = ros.start_node(
            'nodes/drvs_gateway',
            name=f'gateway_{name}',
            params={
                'bind': urls[name].removeprefix('http://'),
                'rosbridge_bind': 'none',  # two gateways at once: not both on 9090
                'max_listeners': LISTENERS,
                'max_wait': 10.0,
                **UNLIMITED,
                **extra,
            },
        )
    for name, url in urls.items():
        client = Http(url, token if name == 'tokens' else None)
        wait_for(
            lambda client=client: client('GET', '/v1/vision_systems')[0] == 200,
            60,
            f'gateway {name} to hear the registry',
            interval=0.2,
            on_timeout=ros.describe,
        )
    return {name: (url, nodes[name]) for name, url in urls.items()}, token


class Http:
    """One persistent HTTP connection: ``(status, JSON body)`` of a request."""

    def __init__(self, url: str, token: str | None):
        host, port = url.removeprefix('http://').split(':')
        self.connection = http.client.HTTPConnection(host, int(port), timeout=30)
        self.headers = {'Content-Type': 'application/json'}
        if token:
            self.headers['Authorization'] = f'Bearer {token}'

    def __call__(self, method: str, path: str, body: dict | None = None) -> tuple[int, dict]:
        try:
            self.connection.request(
                method, path, json.dumps(body) if body is not None else None, headers=self.headers
            )
            response = self.connection.getresponse()
            return response.status, json.loads(response.read() or b'null')
        except (OSError, http.client.HTTPException):
            self.connection.close()
            return 0, {}


def detect_rounds(url: str, token: str, rounds: int) -> list[float]:
    """Seconds from sending ``POST /v1/detect`` to its answer with the first callback, per round."""
    client = Http(url, token)
    body = {'algorithm': ALGORITHM, 'region': REGION, 'wait': 5}
    times = []
    for _ in range(rounds + 3):  # three warm-up rounds
        time.sleep(0.002)
        started = time.perf_counter()
        status, answer = client('POST', '/v1/detect', body)
        elapsed = time.perf_counter() - started
        if status != 200 or not answer.get('callbacks'):
            raise RuntimeError(f'POST /v1/detect: {status} {answer}')
        times.append(elapsed)
    return times[3:]


def ros_rounds(ros: RosHarness, ctx: Context, rounds: int, block: int = 0) -> list[float]:
    """The same request over ROS: request → first callback per round (bench/nodes/latency_client.py)."""
    out = ctx.work_dir / f'gateway-ros-{block}.jsonl'
    client = ros.start_node(
        NODES / 'latency_client.py',
        name=f'gateway_ros_client_{block}',
        params={
            'out': out,
            'plain': '/echo/detect_object_boundary',
            'rounds': rounds,
            'warmup': 3,
            'region': json.dumps([REGION[k] for k in ('min_x', 'min_y', 'max_x', 'max_y')]),
            'algorithm': ALGORITHM,
        },
    )
    wait_for(lambda: not client.running(), 60 + rounds * 0.1, 'the ROS client', on_timeout=ros.describe)
    lines = read_json_lines(out)
    if client.process.returncode != 0:
        raise RuntimeError(f'the ROS client failed\n{client.describe()}')
    return [line['first'] for line in lines if 'round' in line and line['first'] is not None]


async def _events(response: aiohttp.ClientResponse):
    """(event, data) of an event stream as they come."""
    fields: dict[str, str] = {}
    async for raw in response.content:
        line = raw.decode().rstrip('\n')
        if not line:
            if 'event' in fields:
                yield fields['event'], json.loads(fields['data'])
            fields = {}
        elif not line.startswith(':'):
            key, _, value = line.partition(': ')
            fields[key] = value


async def _open_watch(session: aiohttp.ClientSession, url: str, period: float) -> dict:
    body = {'algorithm': ALGORITHM, 'region': REGION, 'period': period}
    async with session.post(url + '/v1/watches', json=body) as response:
        if response.status != 201:
            raise RuntimeError(f'POST /v1/watches: {response.status} {await response.text()}')
        return await response.json()


async def sse_delivery(url: str, events: int) -> list[float]:
    """Seconds from each callback's stamp (the fake calling the gateway back) to its event here."""
    delays = []
    async with aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=60)) as session:
        watch = await _open_watch(session, url, 0.1)
        async with session.get(url + watch['events']) as response:
            async for kind, data in _events(response):
                if kind == 'callback':
                    delays.append(time.time() - data['stamp'])
                    if len(delays) >= events + 2:
                        break
        await session.delete(url + f'/v1/watches/{watch["id"]}')
    return delays[2:]


async def hold_listeners(url: str, pid: int, count: int) -> dict:
    """``count`` event streams on one watch: the gateway's RSS before, while held, after."""
    process = psutil.Process(pid)
    before = process.memory_info().rss
    connector = aiohttp.TCPConnector(limit=0)
    async with aiohttp.ClientSession(
        connector=connector, timeout=aiohttp.ClientTimeout(total=120)
    ) as session:
        watch = await _open_watch(session, url, 0.5)
        heard = 0
        all_heard = asyncio.Event()

        async def listen() -> None:
            nonlocal heard
            async with session.get(url + watch['events']) as response:
                if response.status != 200:
                    raise RuntimeError(f'event stream: {response.status} {await response.text()}')
                async for kind, _ in _events(response):
                    if kind == 'callback':
                        heard += 1
                        if heard >= count:
                            all_heard.set()
                        await asyncio.sleep(3600)  # held open, reading nothing more

        started = time.perf_counter()
        tasks = [asyncio.create_task(listen()) for _ in range(count)]
        try:
            await asyncio.wait_for(all_heard.wait(), 60)
            opened = time.perf_counter() - started
            held = process.memory_info().rss
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        await session.delete(url + f'/v1/watches/{watch["id"]}')
    await asyncio.sleep(1.0)
    after = process.memory_info().rss
    mib = 1024 * 1024
    return {
        'listeners': count,
        'seconds_to_all_heard': round(opened, 3),
        'rss_before_mib': round(before / mib, 1),
        'rss_held_mib': round(held / mib, 1),
        'rss_after_mib': round(after / mib, 1),
        'kib_per_listener': round((held - before) / 1024 / count, 1),
    }


async def request_rate(url: str, token: str | None, seconds: float) -> float:
    """``GET /v1/vision_systems`` answered per second, :data:`CONCURRENCY` clients at once."""
    headers = {'Authorization': f'Bearer {token}'} if token else {}
    done = 0
    async with aiohttp.ClientSession(headers=headers) as session:
        async with session.get(url + '/v1/vision_systems') as response:  # the token's check, once
            assert response.status == 200, response.status
        deadline = time.perf_counter() + seconds

        async def client() -> None:
            nonlocal done
            while time.perf_counter() < deadline:
                async with session.get(url + '/v1/vision_systems') as response:
                    await response.read()
                    if response.status != 200:
                        raise RuntimeError(f'GET /v1/vision_systems: {response.status}')
                done += 1

        started = time.perf_counter()
        await asyncio.gather(*(client() for _ in range(CONCURRENCY)))
        return done / (time.perf_counter() - started)


BLOCKS = 5
"""The ROS and HTTP rounds alternate in this many blocks, so both meet the same load on the machine."""


def interleaved(
    ros: RosHarness, ctx: Context, url: str, token: str, rounds: int
) -> tuple[list[float], list[float]]:
    """``rounds`` requests over ROS and as many through the gateway, in :data:`BLOCKS` alternating
    blocks (ROS first in one block, HTTP first in the next)."""
    over_ros: list[float] = []
    over_http: list[float] = []
    for block in range(BLOCKS):
        size = rounds // BLOCKS + (block < rounds % BLOCKS)
        if block % 2:
            over_http.extend(detect_rounds(url, token, size))
        over_ros.extend(ros_rounds(ros, ctx, size, block))
        if not block % 2:
            over_http.extend(detect_rounds(url, token, size))
    return over_ros, over_http


def run(ctx: Context) -> Section:
    rounds = ctx.pick(10, 50, 200)
    seconds = ctx.pick(1.0, 3.0, 5.0)
    listeners = ctx.pick(50, LISTENERS, LISTENERS)
    with RosHarness() as ros:
        ctx.progress('starting the server, a fake camera and two gateways')
        gateways, token = start_graph(ros, ctx)
        url, node = gateways['tokens']
        open_url, _ = gateways['open']
        ctx.progress(f'{rounds} requests over ROS and {rounds} through the gateway, in {BLOCKS} blocks')
        over_ros, over_http = interleaved(ros, ctx, url, token, rounds)
        ctx.progress('SSE delivery')
        delivery = asyncio.run(sse_delivery(open_url, ctx.pick(10, 50, 200)))
        ctx.progress(f'{listeners} event streams held')
        held = asyncio.run(hold_listeners(open_url, gateways['open'][1].pid, listeners))
        ctx.progress('requests/s with a token and without')
        with_tokens = asyncio.run(request_rate(url, token, seconds))
        without = asyncio.run(request_rate(open_url, None, seconds))
        del node
    http_ms, ros_ms, sse_ms = (
        spread([value * 1000 for value in values]) for values in (over_http, over_ros, delivery)
    )
    ratio = http_ms['p50'] / ros_ms['p50'] if ros_ms['p50'] else None
    results = {
        'first_callback_http_ms': http_ms,
        'first_callback_ros_ms': ros_ms,
        'first_callback_http_over_ros': ratio,
        'sse_delivery_ms': sse_ms,
        'listeners': held,
        'requests_per_s_tokens': round(with_tokens, 1),
        'requests_per_s_open': round(without, 1),
    }
    targets = {
        'gateway_first_callback_over_ros': target(
            ratio, 3.0, note='p50 of POST /v1/detect → first callback over the same request over ROS'
        ),
        'gateway_sse_delivery_p50_ms': target(sse_ms['p50'], 50.0),
        'gateway_listener_kib': target(held['kib_per_listener'], 256.0),
        'gateway_tokens_rate_over_open': target(
            with_tokens / without if without else None, 0.5, at_most=False
        ),
    }
    markdown = '\n'.join(
        [
            table(
                ['figure', 'p50', 'p99', 'mean'],
                [
                    ['request → first callback, HTTP (ms)', http_ms['p50'], http_ms['p99'], http_ms['mean']],
                    ['the same over ROS (ms)', ros_ms['p50'], ros_ms['p99'], ros_ms['mean']],
                    ['SSE delivery: callback → event (ms)', sse_ms['p50'], sse_ms['p99'], sse_ms['mean']],
                ],
            ),
            '',
            f'HTTP over ROS (p50): **{ratio:.2f}×**.' if ratio else 'HTTP over ROS: not measured.',
            f'{held["listeners"]} event streams on one watch: every one had an event within '
            f'{held["seconds_to_all_heard"]} s; the gateway\'s memory {held["rss_before_mib"]} MiB before, '
            f'{held["rss_held_mib"]} MiB held ({held["kib_per_listener"]} KiB per stream), '
            f'{held["rss_after_mib"]} MiB after they left.',
            f'`GET /v1/vision_systems`, {CONCURRENCY} clients: {with_tokens:.0f} requests/s with a token, '
            f'{without:.0f} without.',
        ]
    )
    return Section(NAME, TITLE, results=results, targets=targets, markdown=markdown)
