"""Load through the real server: nothing lost, nothing duplicated, resources flat.

``test_every_forward_yields_exactly_one_callback``: N robots ask M vision systems K
times each. Each robot is a :class:`ServiceClient` in this process with its own
caller id (``/robot3``) and its own callback service (``/robot3/callback_coordinates``;
one callback_recorder process serves them all). The robots respect the server's
default rate limit (50 requests/s per caller, bursts of 100): each asks at most
every ``Size.interval`` seconds and, refused with a temporary status, waits
``retry_after`` and asks again with the same request id (a refusal forwards nothing).
The vision systems are fakes (``test/nodes/fake_cameras.py``, several per process)
that call back once per forward they receive: twenty real ones, each rendering,
would not fit on two cores. Routing, forwarding, leases and limits are the real
server's, with its default parameters.

``test_short_lived_callers_leave_the_vision_system_flat``: hundreds of distinct
callers, each with its own callback service, ask a real vision system once and
are gone; its bounded callback-connection cache (``~max_callback_clients`` 8,
``~callback_idle`` 1 s) keeps its open files and threads flat.

Resources come from ``/proc/<pid>`` (:func:`drvs.testing.reliability_log.sample_resources`),
compared within the run: before (after a warm-up that opens every long-lived
connection) and after.
"""

import doctest
import math
import random
import threading
import time
from collections import Counter
from dataclasses import dataclass

import pytest
from shapely.geometry import Polygon, box

import drvs.testing.reliability_table
from drvs.common.status import ACCEPTED, is_temporary
from drvs.common.status import name as status_name
from drvs.msg import BoundingBox
from drvs.ros.service_client import ServiceCallError, ServiceClient
from drvs.srv import DetectObjectBoundary, DetectObjectBoundaryRequest
from drvs.testing import WaitTimeout, read_json_lines, reliability_log, wait_for
from drvs.testing.reliability_log import Resources, Trial, sample_resources

pytestmark = pytest.mark.shared_master  # see test/conftest.py

SERVER = 'nodes/drvs_server'
VISION_SYSTEM = 'nodes/vision_system'
RECORDER = 'test/nodes/callback_recorder.py'
CAMERAS = 'test/nodes/fake_cameras.py'
DETECT = '/drvs/detect_object_boundary'
ALGORITHM = 'colour:0,0,150,80,80,255'  # the fakes see whatever they are asked for
WORLD = 'test/worlds/small.yaml'
CRATE = 'colour:40,40,40,90,90,90'  # small.yaml's obstacle model: vs1 sees the crate
PITCH, SIDE, HALF = 2.0, 2.5, 0.3  # camera grid spacing, field-of-view side, half a region of interest
FDS_TOLERANCE, THREADS_TOLERANCE, RSS_TOLERANCE_KB = 5, 3, 20 * 1024


def start_server(ros, **params):
    server = ros.start_node(SERVER, name='drvs', params=params)
    ros.wait_for_service(DETECT, node=server)
    return server


def detect_request(request_id, roi, callback, algorithm=ALGORITHM):
    return DetectObjectBoundaryRequest(
        algorithm=algorithm,
        region_of_interest=BoundingBox(*roi),
        callback_service=callback,
        request_id=request_id,
    )


def within(before: Resources, after: Resources) -> bool:
    return (
        after.fds <= before.fds + FDS_TOLERANCE
        and after.threads <= before.threads + THREADS_TOLERANCE
        and after.rss_kb <= before.rss_kb + RSS_TOLERANCE_KB
    )


def settled_resources(pid: int, before: Resources, timeout: float = 10.0) -> Resources:
    """A sample of ``pid`` once it is back within tolerance of ``before``, or the last one after ``timeout``.

    Connections closed a moment ago may still hold a thread or a descriptor.
    """
    try:
        return wait_for(lambda: within(before, s := sample_resources(pid)) and s, timeout, 'resources')
    except WaitTimeout:
        return sample_resources(pid)


def resource_numbers(trial, prefix, before: Resources, after: Resources) -> None:
    trial.update(
        **{
            f'{prefix}rss_before': before.rss_kb,
            f'{prefix}rss_after': after.rss_kb,
            f'{prefix}fds_before': before.fds,
            f'{prefix}fds_after': after.fds,
            f'{prefix}threads_before': before.threads,
            f'{prefix}threads_after': after.threads,
        }
    )


def assert_flat(what, before: Resources, after: Resources) -> None:
    assert after.fds <= before.fds + FDS_TOLERANCE, f'{what}: open files {before.fds} -> {after.fds}'
    assert (
        after.threads <= before.threads + THREADS_TOLERANCE
    ), f'{what}: threads {before.threads} -> {after.threads}'
    assert (
        after.rss_kb <= before.rss_kb + RSS_TOLERANCE_KB
    ), f'{what}: resident memory {before.rss_kb} kB -> {after.rss_kb} kB'


# -- N robots x M vision systems x K requests -------------------------------------------------------
@dataclass(frozen=True)
class Size:
    robots: int
    cameras: int
    requests: int  # per robot
    processes: int  # fake_cameras processes the cameras are spread over
    interval: float  # seconds between one robot's requests

    def __str__(self):
        return f'{self.robots} robots x {self.cameras} vision systems x {self.requests} requests'


@dataclass
class Asked:
    """One request a robot made and what the server answered."""

    request_id: str
    robot: str
    callback: str
    expected: frozenset  # service names of the vision systems whose field of view meets the region
    vision_systems: int = 0
    message: str = ''


def camera_layout(size: Size) -> dict[str, tuple[int, Polygon]]:
    """Service name -> (process index, field of view): a grid, neighbours overlapping by 0.5 m."""
    columns = math.ceil(math.sqrt(size.cameras))
    cameras = {}
    for index in range(size.cameras):
        x, y = PITCH * (index % columns), PITCH * (index // columns)
        process = index % size.processes
        name = f'/cams{process}/c{index:02d}/detect_object_boundary'
        cameras[name] = (process, box(x, y, x + SIDE, y + SIDE))
    return cameras


def seeing(cameras, roi) -> frozenset:
    region = box(*roi)
    return frozenset(name for name, (_, fov) in cameras.items() if fov.intersection(region).area > 0)


def callback_of(robot: int) -> str:
    return f'/robot{robot}/callback_coordinates'


class Robot:
    """A robot: its own caller id and callback service, asking through the server at its own pace."""

    def __init__(self, index: int, cameras, deadline: float):
        self.name = f'/robot{index}'
        self.callback = callback_of(index)
        self.cameras = cameras
        self.deadline = deadline
        self.client = ServiceClient(DETECT, DetectObjectBoundary, 10.0, caller_id=self.name)
        self.rng = random.Random(index)
        self.asked: list[Asked] = []
        self.refusals: Counter = Counter()
        self.errors: list[str] = []

    def region(self, camera: str | None = None) -> tuple[float, float, float, float]:
        """A region of interest inside ``camera``'s field of view (a random camera's by default)."""
        fov = self.cameras[camera or self.rng.choice(sorted(self.cameras))][1]
        x0, y0, x1, y1 = fov.bounds
        x, y = self.rng.uniform(x0 + HALF, x1 - HALF), self.rng.uniform(y0 + HALF, y1 - HALF)
        return (x - HALF, y - HALF, x + HALF, y + HALF)

    def ask(self, request_id: str, roi) -> Asked:
        """Ask until accepted, waiting ``retry_after`` after each temporary refusal."""
        message = detect_request(request_id, roi, self.callback)
        while True:
            answer = self.client.call(message)
            if answer.status == ACCEPTED:
                break
            self.refusals[status_name(answer.status)] += 1
            if not is_temporary(answer.status):
                raise AssertionError(f'{self.name}: {request_id} refused: {answer.message}')
            if time.monotonic() + answer.retry_after > self.deadline:
                raise AssertionError(
                    f'{self.name}: {request_id} still refused at the deadline: {answer.message}'
                )
            time.sleep(answer.retry_after)
        asked = Asked(request_id, self.name, self.callback, seeing(self.cameras, roi))
        asked.vision_systems, asked.message = answer.vision_systems, answer.message
        return asked

    def run(self, count: int, interval: float) -> None:
        try:
            for number in range(count):
                started = time.monotonic()
                self.asked.append(self.ask(f'{self.name[1:]}-{number}', self.region()))
                time.sleep(max(0.0, interval - (time.monotonic() - started)))  # pacing, not waiting
        except (AssertionError, ServiceCallError) as error:
            self.errors.append(str(error))


SIZES = [
    pytest.param(Size(2, 3, 10, processes=3, interval=0.05), id='2x3x10'),
    pytest.param(
        Size(10, 20, 50, processes=4, interval=0.1),
        id='10x20x50',
        marks=[pytest.mark.slow, pytest.mark.timeout(1200)],
    ),
]


@pytest.fixture
def closing():
    """Clients to close at teardown, whatever happened."""
    clients = []
    yield clients
    for client in clients:
        client.close()


@pytest.mark.parametrize('size', SIZES)
def test_every_forward_yields_exactly_one_callback(graph, request, tmp_path, closing, size):
    ros = graph
    with Trial('load', request.node.name, f'{size}, fake vision systems', 'held') as trial:
        server = start_server(ros)
        callbacks = tmp_path / 'callbacks.jsonl'
        services = [callback_of(index) for index in range(size.robots)]
        recorder = ros.start_node(RECORDER, name='robots', params={'output': callbacks, 'services': services})
        for service in services:
            ros.wait_for_service(service, node=recorder)

        cameras = camera_layout(size)
        outputs = [tmp_path / f'cams{process}.jsonl' for process in range(size.processes)]
        for process, output in enumerate(outputs):
            mine = {
                name.split('/')[2]: [list(p) for p in fov.exterior.coords[:-1]]
                for name, (owner, fov) in cameras.items()
                if owner == process
            }
            ros.start_node(CAMERAS, name=f'cams{process}', params={'output': output, 'cameras': mine})

        def fake_records(kind):
            return [r for output in outputs for r in read_json_lines(output) if r['kind'] == kind]

        def all_registered():
            accepted = {r['camera'] for r in fake_records('register') if r['status'] == ACCEPTED}
            return accepted == set(cameras)

        wait_for(all_registered, 60, f'{size.cameras} vision systems to register', on_timeout=ros.describe)

        # Warm-up: every robot connects, every vision system gets a forward and calls back,
        # so that every long-lived connection is open before the resources are sampled.
        deadline = time.monotonic() + 600
        robots = [Robot(index, cameras, deadline) for index in range(size.robots)]
        closing.extend(robot.client for robot in robots)
        warm = []
        for index, camera in enumerate(sorted(cameras)):
            robot = robots[index % len(robots)]
            warm.append(robot.ask(f'warm-{index}', robot.region(camera)))
        for robot in robots[len(cameras) :]:
            warm.append(robot.ask(f'warm-{robot.name[1:]}', robot.region()))
        warm_pairs = sum(a.vision_systems for a in warm)
        wait_for(
            lambda: len(read_json_lines(callbacks)) >= warm_pairs,
            60,
            f'{warm_pairs} warm-up callbacks',
            on_timeout=ros.describe,
        )
        before = sample_resources(server.pid)

        started = time.monotonic()
        threads = [
            threading.Thread(target=robot.run, args=(size.requests, size.interval), name=robot.name)
            for robot in robots
        ]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(max(1.0, deadline - time.monotonic()))
        load_seconds = time.monotonic() - started
        assert not any(thread.is_alive() for thread in threads), 'a robot did not finish before the deadline'
        errors = [error for robot in robots for error in robot.errors]
        assert not errors, errors

        asked = {a.request_id: a for robot in robots for a in robot.asked}
        promised = sum(a.vision_systems for a in asked.values())

        def counted():
            forwards = [r for r in fake_records('forward') if r['request_id'] in asked]
            sent = [r for r in fake_records('callback') if r['request_id'] in asked]
            received = [r for r in read_json_lines(callbacks) if r['request_id'] in asked]
            return forwards, sent, received

        def settled():
            forwards, sent, received = counted()
            delivered = sum(r['ok'] for r in sent)
            return len(forwards) >= promised and len(sent) >= len(forwards) and len(received) >= delivered

        try:
            wait_for(settled, 60 + promised / 20, 'every forward and callback', interval=0.5)
        except WaitTimeout:
            pass  # counted below: the numbers say what is missing
        forwards, sent, received = counted()
        after = settled_resources(server.pid, before)

        forwarded = Counter((r['request_id'], r['camera']) for r in forwards)
        got = Counter((r['request_id'], r['vision_system']) for r in received)
        expected = set()
        skipped = 0
        for a in asked.values():
            if a.vision_systems == len(a.expected):
                expected |= {(a.request_id, name) for name in a.expected}
            else:  # the server said it skipped busy ones: expect what it did forward
                skipped += len(a.expected) - a.vision_systems
                expected |= {pair for pair in forwarded if pair[0] == a.request_id}
        lost = sorted(expected - set(got))
        duplicated = sum(count - 1 for count in got.values() if count > 1)
        unexpected = sorted(set(got) - expected)
        misrouted = [r for r in received if r['service'] != asked[r['request_id']].callback]
        refusals = sum((robot.refusals for robot in robots), Counter())
        trial.update(
            robots=size.robots,
            vision_systems=size.cameras,
            requests_per_robot=size.requests,
            requests=len(asked),
            refusals=dict(refusals),
            forwards_promised=promised,
            forwards_received=len(forwards),
            skipped_busy=skipped,
            callbacks_expected=len(expected),
            callbacks_received=len(got),
            lost=len(lost),
            duplicated=duplicated,
            unexpected=len(unexpected),
            misrouted=len(misrouted),
            load_seconds=load_seconds,
            requests_per_second=len(asked) / load_seconds,
        )
        resource_numbers(trial, '', before, after)

        assert len(asked) == size.robots * size.requests
        short = {
            rid: (a.vision_systems, n)
            for rid, a in asked.items()
            if a.vision_systems != (n := sum(c for (r, _), c in forwarded.items() if r == rid))
        }
        assert not short, f'vision_systems promised vs forwards received: {short}'
        assert max(forwarded.values(), default=1) == 1, 'a vision system got the same request twice'
        failed = [r for r in sent if not r['ok']]
        assert not failed, f'{len(failed)} callbacks failed at the vision systems: {failed[:3]}'
        assert (lost, duplicated, unexpected, misrouted) == ([], 0, [], []), (lost[:10], unexpected[:10])
        assert_flat('the server', before, after)
        assert 'Traceback' not in server.log(tail=100000)


# -- many short-lived callers ------------------------------------------------------------------------
CALLER_SIZES = [
    pytest.param(200, 50, id='200'),
    pytest.param(1000, 100, id='1000', marks=[pytest.mark.slow, pytest.mark.timeout(1200)]),
]


@pytest.mark.parametrize('callers, batch', CALLER_SIZES)
def test_short_lived_callers_leave_the_vision_system_flat(graph, request, tmp_path, callers, batch):
    ros = graph
    what = f'{callers} distinct callers, each asking once then gone; real vision system, 8 cached callbacks'
    with Trial('load', request.node.name, what, 'held') as trial:
        server = start_server(ros)
        vs1 = ros.start_node(
            VISION_SYSTEM,
            name='vs1',
            params={'world': WORLD, 'max_callback_clients': 8, 'callback_idle': 1.0},
        )
        ros.wait_for_service('/vs1/detect_object_boundary', node=vs1)
        output = tmp_path / 'callbacks.jsonl'
        peaks = {'vs_fds': 0, 'vs_threads': 0, 'server_fds': 0, 'server_threads': 0}
        before = {}
        served = 0

        def sample_peaks():
            vs, srv = sample_resources(vs1.pid), sample_resources(server.pid)
            peaks['vs_fds'] = max(peaks['vs_fds'], vs.fds)
            peaks['vs_threads'] = max(peaks['vs_threads'], vs.threads)
            peaks['server_fds'] = max(peaks['server_fds'], srv.fds)
            peaks['server_threads'] = max(peaks['server_threads'], srv.threads)

        started = time.monotonic()
        for number in range(callers // batch):
            names = [f'/caller{number}_{index}' for index in range(batch)]
            services = [f'{name}/callback_coordinates' for name in names]
            recorder = ros.start_node(
                RECORDER, name=f'callers{number}', params={'output': output, 'services': services}
            )
            wait_for(
                lambda services=services: set(services) <= {name for name, _ in ros.master.system_state()[2]},
                60,
                f'batch {number} callback services',
                on_timeout=recorder.describe,
            )
            for name, service in zip(names, services, strict=True):
                client = ServiceClient(DETECT, DetectObjectBoundary, 10.0, caller_id=name)
                try:
                    answer = wait_for(
                        lambda c=client, s=service, n=name: (
                            a := c.call(detect_request(f'{n[1:]}', (0, 0, 4, 3), s, CRATE))
                        ).vision_systems
                        == 1
                        and a,
                        30,
                        f'{name}: vs1 to cover the region',
                        interval=0.2,
                        on_timeout=ros.describe,
                    )
                finally:
                    client.close()
                assert answer.status == ACCEPTED, answer.message
                if before:
                    sample_peaks()
            ids = {name[1:] for name in names}
            wait_for(
                lambda ids=ids: ids <= {r['request_id'] for r in read_json_lines(output)},
                60,
                f'the callbacks of batch {number}',
                on_timeout=ros.describe,
            )
            recorder.stop()  # the callers are gone
            served += batch
            if not before:  # batch 0 warms up: vs1's callback cache is full from here on
                before = {'vs': sample_resources(vs1.pid), 'server': sample_resources(server.pid)}
                sample_peaks()
        seconds = time.monotonic() - started
        after_vs = settled_resources(vs1.pid, before['vs'])
        after_server = settled_resources(server.pid, before['server'])
        received = Counter(r['request_id'] for r in read_json_lines(output))
        trial.update(
            callers=callers,
            requests=served,
            callbacks_expected=served,
            callbacks_received=len(received),
            lost=served - len(received),
            duplicated=sum(count - 1 for count in received.values()),
            seconds=seconds,
            vs_fds_peak=peaks['vs_fds'],
            vs_threads_peak=peaks['vs_threads'],
            server_fds_peak=peaks['server_fds'],
            server_threads_peak=peaks['server_threads'],
        )
        resource_numbers(trial, 'vs_', before['vs'], after_vs)
        resource_numbers(trial, 'server_', before['server'], after_server)

        assert (len(received), max(received.values())) == (callers, 1)
        assert peaks['vs_fds'] <= before['vs'].fds + FDS_TOLERANCE, (before['vs'], peaks)
        assert peaks['vs_threads'] <= before['vs'].threads + THREADS_TOLERANCE, (before['vs'], peaks)
        assert_flat('the vision system', before['vs'], after_vs)
        assert_flat('the server', before['server'], after_server)
        for node in (server, vs1):
            assert 'Traceback' not in node.log(tail=100000), node.describe()


# -- the lines these tests leave, and the report made of them ----------------------------------------
def test_lines_are_written_only_when_asked_and_failures_are_recorded(monkeypatch, tmp_path):
    monkeypatch.delenv(reliability_log.ENV_VARIABLE, raising=False)
    assert reliability_log.record('load', 't') is None
    log = tmp_path / 'reliability.jsonl'
    monkeypatch.setenv(reliability_log.ENV_VARIABLE, str(log))
    with Trial('load', 'held', '2 x 3 x 10', 'held') as trial:
        trial.update(lost=0, rss_before=100, rss_after=101.23456)
    with pytest.raises(AssertionError), Trial('fault', 'broken', 'kill -9'):
        raise AssertionError('vs2 never came back\nmore detail')
    with pytest.raises(ValueError) as error:
        reliability_log.record('load', 't', recovery_seconds=math.nan)
    assert str(error.value) == 'recovery_seconds: must be a finite number, got nan'
    held, broken = read_json_lines(log)
    assert held.pop('duration_seconds') >= 0 and broken.pop('duration_seconds') >= 0
    assert held == {
        'suite': 'load',
        'test': 'held',
        'what': '2 x 3 x 10',
        'outcome': 'held',
        'lost': 0,
        'rss_before': 100,
        'rss_after': 101.235,
    }
    assert broken == {
        'suite': 'fault',
        'test': 'broken',
        'what': 'kill -9',
        'outcome': 'failed',
        'error': 'AssertionError: vs2 never came back',
    }


def test_the_report_counts_every_suite_and_shows_each_tests_numbers():
    assert doctest.testmod(drvs.testing.reliability_table).failed == 0
    lines = [
        {
            'suite': 'fault',
            'test': 'kill',
            'what': 'kill -9',
            'outcome': 'survived',
            'recovery_seconds': 0.48,
        },
        {'suite': 'fault', 'test': 'hang', 'what': 'hung', 'outcome': 'failed', 'error': 'AssertionError: x'},
        {
            'suite': 'load',
            'test': 'nxm',
            'what': 'a|b',
            'outcome': 'held',
            'lost': 2,
            'fds_before': 17,
            'fds_after': 18,
            'refusals': {'BUSY': 1},
            'duration_seconds': 2.25,
        },
        {'suite': 'master', 'test': 'restart', 'what': 'roscore', 'outcome': 'survived', 'lost': 0},
    ]
    text = drvs.testing.reliability_table.report(
        lines, 'Generated now.', ['`test/live/test_security.py`: not there yet']
    )
    assert text.splitlines()[:11] == [
        '# Reliability',
        '',
        'Generated now.',
        '',
        '| Reliability | |',
        '|---|---|',
        '| Faults survived | 1 of 2 |',
        '| Load held | 1 of 1 |',
        '| Inputs tried | not run |',
        '| Data lost | 2 callbacks, in 2 tests that count them |',
        '| Master restarts survived | 1 of 1 |',
    ]
    assert '- **Failed:** fault: hang' in text
    assert '| `nxm` | a\\|b | held | lost 2; fds 17 → 18; refusals {BUSY: 1} | 2.25 |' in text
    assert '| `hang` | hung | failed: AssertionError: x |  |  |' in text
    assert text.index('## Faults') < text.index('## Load') < text.index('## Master restart')
