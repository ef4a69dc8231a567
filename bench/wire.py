"""Table 1 measured on the wire: bytes per round of vision, DRVS against image sharing, and the robot's CPU.

The paper (section 4.4, Table 1) *calculates* the traffic of one round of vision for
1×1 … 10×50 robots × cameras: DRVS requests and responses of under 0.2 kB each, against
every camera sending every robot a 70.2 kB compressed image. Here the same round is run
with the real nodes and the bytes are *counted*: a raw capture on ``lo``
(:mod:`bench.capture`) sees every TCP payload byte, so TCPROS length prefixes,
connection headers and the service response's ok byte are all in, and nothing is
added up from message sizes. Each connection is attributed by the TCPROS header its
client sent (``callerid`` and ``service`` or ``topic``); XML-RPC (master lookups, topic
negotiation, every node's master watch) and connection headers are counted apart.

DRVS: nodes/drvs_server, N nodes/vision_system rendering an 800×600 view of a generated
world (flat orange squares on a white floor, cameras straight down), and R bench robots
(bench/nodes/drvs_robot.py). One-shot round: each robot sends one DetectObjectBoundary
for its region; the server forwards it to the C cameras that see it; each calls the
robot back with one four-vertex object. Watch round: one period of a standing
WatchObjectBoundary (its callbacks only). Fused round: each robot sends one
DetectObjectBoundary with ``fused`` true; the server forwards it to the same C cameras with
its own callback service (``/drvs/fusion_callback``), they call the server back, and the
server calls the robot back once with every object once (docs/interface.md, "Fused mode"):
its bytes are request, forwards, the cameras' callbacks to the server and the one
callback to the robot. Image sharing: bench/nodes/image_camera.py
publishes one JPEG (quality 80) per camera, bench/nodes/image_robot.py (every robot
subscribes to every camera) decodes and segments each with the same colour algorithm.
Two frames: the rendered view, and a natural photograph (scipy's ``face``, shipped by
Debian's python3-scipy, 1024×768 resized to 800×600); DRVS's bytes do not depend on
the photograph (the cameras still segment their rendered view).

One process set, started at once, serves every size: the world places the cameras so
that robot 1's region ``a`` is seen by camera 1 alone, regions ``p`` by cameras 1-20 and
regions ``q`` by all 50 (robots 2-10 do not ask at 1×C); image cameras are triggered in
groups (1, 2-20, 21-50), and as every image robot is subscribed all along, a 1×C image
round counts robot 1's connections only. Robot CPU is the robot process's
(time.process_time, every thread) over the round: for DRVS from the ask to the last
callback (a fused round: to its one callback), for image sharing from a mark (SIGUSR1)
before the frames to the last frame handled. Where the DRVS robot's CPU goes: a robot with
its service threads under cProfile asks a few 1×20 rounds of its own, per camera and fused.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path

from bench import capture
from bench.common import Context, Section, figure, save, table, target
from drvs.testing.harness import wait_for

NAME = 'wire'
TITLE = 'Table 1 on the wire: bytes and robot CPU per round of vision'

BENCH = '/drvs_wire_bench'
"""The caller id of the bench's own calls (triggers): their connections are not counted."""
ALGORITHM = 'colour:190,80,0,255,160,40'
OBJECT_COLOUR = [230, 120, 0]
HEIGHT = 6.0
"""Cameras look straight down from this height (metres)."""
OBJECT = 0.3
"""Side of the flat square objects (metres)."""
MARGIN = 0.1
"""A robot's region reaches this far beyond its object."""
SIZES = ((1, 1), (1, 20), (10, 20), (10, 50))
PAPER_KB = {
    # (robots, cameras): DRVS total, DRVS per robot, image total, image per robot (kB)
    (1, 1): (0.6, 1.0, 70.2, 70.0),
    (1, 20): (8.2, 4.0, 1404.0, 1400.0),
    (10, 20): (82.0, 4.0, 14040.0, 1400.0),  # image: not in Table 1, 70.2 kB per image as it computes
    (10, 50): (202.0, 10.0, 35100.0, 3500.0),
}
SERVER_PARAMS = {'forward_timeout': 10.0, 'check_timeout': 5.0, 'fused_deadline': 10.0, 'track_coast': 30.0}
VISION_PARAMS = {'callback_timeout': 10.0, 'register_timeout': 10.0}
"""The nodes' timeouts (2 s, 1 s by default; the fused deadline 2 s) are raised: the bench's 80
processes on a shared machine can hold a call that long, and a dropped call would leave a round
short. Bytes do not depend on them. The server's ``~track_coast`` (2 s) too: at 10×50 a frame
reaches the server up to 10 s after its capture (50 vision systems render and segment 800×600
for 10 requests each on a shared machine), and a track last seen longer than ``~track_coast``
before the server's clock ends before its round is answered: the fused callback would carry no
object."""
GROUPS = ((1, 1), (2, 20), (21, 50))
"""Image cameras per process (first, last): triggered together."""
PHOTO = (
    'scipy.misc.face() (Debian python3-scipy: scipy/misc/face.dat, a raccoon, 1024×768 JPEG-free RGB) '
    'resized to 800×600 (cv2.INTER_AREA, same 4:3 aspect, no crop)'
)
REPRODUCE = '`make bench` (all four sizes) or `.venv/bin/python -m bench.run --only wire --size quick`'


# -- the world -----------------------------------------------------------------------------------
@dataclass
class Layout:
    """The generated world and where each robot asks."""

    world: dict
    regions: dict[int, dict[str, list[float]]]  # robot -> {name: [min_x, min_y, max_x, max_y]}
    cameras: int


def _object(name: str, x: float, y: float) -> dict:
    return {
        'name': name,
        'kind': 'static',
        'position': [round(x, 3), round(y, 3)],
        'size': [OBJECT, OBJECT, 0.02],
        'colour': OBJECT_COLOUR,
        'decoy': True,  # objects of no role: the world's colour-model checks leave them out
    }


def _region(x: float, y: float) -> list[float]:
    half = OBJECT / 2 + MARGIN
    return [round(x - half, 3), round(y - half, 3), round(x + half, 3), round(y + half, 3)]


def camera_x(index: int) -> tuple[float, float]:
    """(x, y) of camera ``index`` (1-based): 1 sees a, p and q; 2-20 p and q; 21-50 q only."""
    if index == 1:
        return 5.3, 4.0
    if index <= 20:
        k = index - 2
        return 5.95 + 0.05 * (k % 4), 2.6 + 0.3 * (k // 4)
    k = index - 21
    return 10.75 + 0.04 * (k % 5), 2.6 + 0.5 * (k // 5)


def layout(cameras: int, resolution: tuple[int, int]) -> Layout:
    """A 16 m × 8 m floor: object a at x 1, ten objects p at x 3-5.8, ten objects q at x 6.6-9.4."""
    objects = [_object('a', 1.0, 4.0)]
    regions: dict[int, dict[str, list[float]]] = {1: {'a': _region(1.0, 4.0)}}
    for robot in range(1, 11):
        column, row = (robot - 1) % 5, (robot - 1) // 5
        for name, x0 in (('p', 3.0), ('q', 6.6)):
            x, y = x0 + 0.7 * column, 3.0 + 1.5 * row
            objects.append(_object(f'{name}{robot}', x, y))
            regions.setdefault(robot, {})[name] = _region(x, y)
    vision_systems = []
    for index in range(1, cameras + 1):
        x, y = camera_x(index)
        vision_systems.append(
            {
                'name': f'vs{index}',
                'position': [round(x, 3), round(y, 3), HEIGHT],
                'target': [round(x, 3), round(y, 3), 0.0],
                'fov_deg': 60,
                'resolution': list(resolution),
            }
        )
    world = {
        'floor': {'size': [16.0, 8.0]},
        'robot': {'position': [15.5, 0.5], 'size': [0.3, 0.3, 0.2], 'colour': [0, 200, 0]},
        'station': {'position': [15.5, 7.5], 'size': [0.4, 0.3, 0.1], 'colour': [0, 0, 220]},
        'objects': objects,
        'vision_systems': vision_systems,
        'colour_models': {
            'self': 'colour:0,150,0,80,255,80',
            'station': 'colour:0,0,150,80,80,255',
            'obstacle': 'colour:40,40,40,90,90,90',
            'human': 'colour:150,0,0,255,80,80',
        },
    }
    return Layout(world, regions, cameras)


def seeing(index: int, region: str) -> bool:
    """Whether camera ``index`` is meant to see (and to be asked about) regions ``region``."""
    return {'a': index == 1, 'p': index <= 20, 'q': True}[region]


def check_layout(plan: Layout, resolution: tuple[int, int]) -> None:
    """Each camera's field of view meets exactly the regions it is meant to, and holds their objects.

    :raises AssertionError: naming the camera and the region (a bug in :func:`layout`).
    """
    from shapely.geometry import Polygon, box

    from drvs.server.spatial_index import interiors_intersect
    from drvs.vision.camera import PinholeCamera

    floor = tuple(plan.world['floor']['size'])
    for index in range(1, plan.cameras + 1):
        x, y = camera_x(index)
        model = PinholeCamera(
            eye=(x, y, HEIGHT), target=(x, y, 0.0), fov_deg=60, width=resolution[0], height=resolution[1]
        )
        view = Polygon(model.floor_footprint(floor))
        for robot, named in plan.regions.items():
            for name, bounds in named.items():
                meant = seeing(index, name)
                region = box(*bounds)
                assert interiors_intersect(view, region) == meant, f'vs{index} and {name}{robot}'
                assert not meant or view.contains(region), f'vs{index} sees part of {name}{robot}'


# -- reading the nodes' JSON lines ------------------------------------------------------------------
class Lines:
    """The records appended to a node's JSON lines file since the last read."""

    def __init__(self, path: Path):
        self.path = path
        self.offset = 0
        self.records: list[dict] = []

    def read(self) -> list[dict]:
        try:
            with open(self.path, 'rb') as handle:
                handle.seek(self.offset)
                data = handle.read()
        except FileNotFoundError:
            return self.records
        end = data.rfind(b'\n') + 1
        self.offset += end
        self.records += [json.loads(line) for line in data[:end].splitlines() if line.strip()]
        return self.records


# -- the bench ------------------------------------------------------------------------------------
@dataclass
class Robot:
    index: int
    node: object
    lines: Lines
    clients: dict = field(default_factory=dict)


class WireBench:
    """The nodes, the capture and the triggers of one run."""

    def __init__(self, ctx: Context, ros, cap, cameras: int, resolution: tuple[int, int], period: float):
        self.ctx, self.ros, self.cap = ctx, ros, cap
        self.period = period
        self.owners: dict[int, str] = {}
        self.watch_forwards = 0
        self.profiled: Robot | None = None
        self.incomplete_rounds = 0  # rounds asked again: a vision system dropped a callback
        self.cameras = cameras
        self.resolution = resolution
        self.dir = ctx.work_dir / 'wire'
        self.dir.mkdir(parents=True, exist_ok=True)
        self.plan = layout(cameras, resolution)
        check_layout(self.plan, resolution)
        import yaml

        self.world_path = self.dir / 'world.yaml'
        self.world_path.write_text(yaml.safe_dump(self.plan.world, sort_keys=False))
        self.drvs_robots: dict[int, Robot] = {}
        self.image_robots: dict[int, Robot] = {}
        self.image_processes: dict[tuple[str, int], str] = {}  # (kind, group) -> node name
        self.image_clients: dict[str, object] = {}

    # -- starting ---------------------------------------------------------------------------
    def start_drvs(self, robots: int) -> None:
        ros = self.ros
        self.server = ros.start_node('nodes/drvs_server', 'drvs', SERVER_PARAMS)
        self.vision = [
            ros.start_node('nodes/vision_system', f'vs{index}', {'world': self.world_path, **VISION_PARAMS})
            for index in range(1, self.cameras + 1)
        ]
        for index in range(1, robots + 1):
            out = self.dir / f'drvs_robot{index}.jsonl'
            regions = json.dumps(self.plan.regions[index])  # YAML reads JSON
            node = ros.start_node(
                'bench/nodes/drvs_robot.py',
                f'robot{index}',
                {'out': out, 'algorithm': ALGORITHM, 'regions': regions, 'period': self.period},
            )
            self.drvs_robots[index] = Robot(index, node, Lines(out))

    def start_image_cameras(self, kinds: list[str], photo: Path | None) -> None:
        for kind in kinds:
            for group, (first, last) in enumerate(GROUPS):
                if first > self.cameras:
                    continue
                names = ','.join(f'vs{i}' for i in range(first, min(last, self.cameras) + 1))
                params = {'cameras': names, 'width': self.resolution[0], 'height': self.resolution[1]}
                params.update({'world': self.world_path} if kind == 'render' else {'image': photo})
                name = f'img_{kind}{group}'
                self.ros.start_node('bench/nodes/image_camera.py', name, params)
                self.image_processes[(kind, group)] = name

    def image_topics(self) -> list[str]:
        topics = []
        for (_, group), name in self.image_processes.items():
            first, last = GROUPS[group]
            topics += [f'/{name}/vs{i}/image/compressed' for i in range(first, min(last, self.cameras) + 1)]
        return topics

    def start_image_robots(self, indices) -> None:
        for index in indices:
            out = self.dir / f'image_robot{index}.jsonl'
            node = self.ros.start_node(
                'bench/nodes/image_robot.py',
                f'irobot{index}',
                {'topics': ','.join(self.image_topics()), 'out': out, 'algorithm': ALGORITHM},
            )
            self.image_robots[index] = Robot(index, node, Lines(out))

    def client(self, service: str):
        """A persistent trigger client (roscpp/Empty) with the bench's caller id."""
        import roscpp.srv

        from drvs.ros.service_client import ServiceClient

        return ServiceClient(service, roscpp.srv.Empty, 30.0, master_uri=self.ros.master.uri, caller_id=BENCH)

    def trigger(self, robot: Robot, service: str) -> None:
        import roscpp.srv

        if service not in robot.clients:
            robot.clients[service] = self.client(f'/robot{robot.index}/{service}')
        robot.clients[service].call(roscpp.srv.EmptyRequest())

    def publish(self, kind: str, cameras: int) -> None:
        import roscpp.srv

        for (name_kind, group), name in self.image_processes.items():
            if name_kind != kind or GROUPS[group][0] > cameras:
                continue
            if name not in self.image_clients:
                self.image_clients[name] = self.client(f'/{name}/publish')
            self.image_clients[name].call(roscpp.srv.EmptyRequest())

    def start_profiled(self) -> None:
        """Robot 99: robot 1's region ``p``, its service threads under cProfile (``~profile``)."""
        out = self.dir / 'drvs_robot_profiled.jsonl'
        self.profile_path = self.dir / 'robot_profile'
        params = {
            'out': out,
            'algorithm': ALGORITHM,
            'regions': json.dumps({'p': self.plan.regions[1]['p']}),
            'profile': self.profile_path,
        }
        self.profiled = Robot(
            99, self.ros.start_node('bench/nodes/drvs_robot.py', 'robot99', params), Lines(out)
        )

    def close(self) -> None:
        """Close the trigger connections."""
        for client in [
            *self.image_clients.values(),
            *(c for r in self.drvs_robots.values() for c in r.clients.values()),
        ]:
            client.close()

    def ready(self, robots_n: int, cameras_n: int, region: str) -> None:
        """Wait until what a size needs runs: robots' services, cameras registered, subscriptions."""
        timeout = self.ctx.pick(30.0, 120.0, 300.0)
        robots = [self.drvs_robots[i] for i in range(1, robots_n + 1)]
        if self.profiled and (robots_n, cameras_n) == (1, 20):
            robots.append(self.profiled)
        for robot in robots:
            self.ros.wait_for_service(f'/robot{robot.index}/ask_{region}', timeout=timeout, node=robot.node)
        for (_, group), name in self.image_processes.items():
            if GROUPS[group][0] <= cameras_n:
                self.ros.wait_for_service(f'/{name}/publish', timeout=timeout)

        cameras = {f'/vs{k}' for k in range(1, cameras_n + 1)}

        def registered():  # seen on the wire: each camera's registration was answered
            if not cameras <= set(self.owners.values()):
                self.refresh_owners()
            snap = self.snapshot()
            done = {
                c.caller
                for c in snap.values()
                if category(c) == 'registration' and c.down.framer.messages >= 1
            }
            return cameras <= done

        self.refresh_owners()
        self.wait(registered, timeout, f'vision systems 1-{cameras_n} to register')
        self.refresh_owners()
        wait_subscribed(self, list(self.image_robots.values()), cameras_n)

    # -- marks and waits ---------------------------------------------------------------------
    def mark(self, robots: list[Robot]) -> dict[int, float]:
        """SIGUSR1 every robot; their CPU at that moment, once each has written it."""
        counts = {r.index: sum(1 for x in r.lines.read() if x['event'] == 'mark') for r in robots}
        for robot in robots:
            os.kill(robot.node.pid, signal.SIGUSR1)

        def marked():
            found = {}
            for robot in robots:
                marks = [x for x in robot.lines.read() if x['event'] == 'mark']
                if len(marks) > counts[robot.index]:
                    found[robot.index] = marks[-1]['cpu']
            return found if len(found) == len(robots) else None

        return wait_for(marked, 10.0, 'robots to write their CPU mark', interval=0.01)

    def snapshot(self) -> dict:
        """Our nodes' connections, every packet sent so far counted (flushed capture)."""
        self.cap.flush()
        return self.cap.snapshot(self.owners.keys() if self.owners else None)

    def refresh_owners(self) -> dict[int, str]:
        """Learn the ports of nodes not known yet (from the master)."""
        known = set(self.owners.values())
        for node, ports in capture.node_ports(self.ros.master.uri, BENCH, known).items():
            for port in ports.values():
                self.owners[port] = node
        return self.owners

    def settle(self, timeout: float = 10.0) -> dict:
        """A snapshot once every service call on the wire has its response (flushed capture)."""

        def answered():
            snap = self.snapshot()
            for connection in snap.values():
                if connection.kind == 'service' and connection.up.framer.framing and not connection.closed:
                    if connection.up.framer.messages != connection.down.framer.messages:
                        return None
            return snap

        return wait_for(answered, timeout, 'every service call on the wire to be answered', interval=0.02)

    def wait(self, condition, timeout: float, what: str):
        return wait_for(condition, timeout, what, interval=0.03)


# -- counting -----------------------------------------------------------------------------------
def category(connection: capture.Connection) -> str:
    """What a connection carries: request, forward, callback, watch, image, registration, ..."""
    if connection.caller == BENCH:
        return 'bench'
    if connection.kind == 'http':
        return 'xmlrpc'
    fields = connection.fields
    if fields.get('probe') == '1':
        return 'probe'
    name = connection.name
    if connection.kind == 'topic':
        return 'image' if name.endswith('/image/compressed') else 'topic'
    if name == '/drvs/detect_object_boundary':
        return 'request'
    if name == '/drvs/watch_object_boundary':
        return 'watch_request'
    if name == '/drvs/register_vision_service':
        return 'registration'
    if name.endswith('/detect_object_boundary'):
        return 'forward'
    if name.endswith('/watch_object_boundary'):
        return 'watch_forward'
    if name.endswith('/fusion_callback'):
        return 'fusion_callback'
    if name.endswith('/callback_coordinates'):
        return 'callback'
    return 'other' if connection.kind != 'unknown' else 'unknown'


@dataclass
class Counted:
    """The bytes between two snapshots, by category, with per-robot receive counts."""

    by_category: dict[str, int]
    setup: int  # connection headers of connections opened in between
    received: dict[str, int]  # robot node -> bytes towards it
    messages: dict[str, int]  # category -> messages (requests and responses / topic messages)
    requests: dict[str, int]  # category -> messages from client to server (service requests)
    ip_bytes: int  # IP-level bytes (headers and ACKs included) of the counted categories
    connections: list


ROUND_CATEGORIES = {
    'oneshot': ('request', 'forward', 'callback'),
    'fused': ('request', 'forward', 'fusion_callback', 'callback'),  # callback: the server's, to the robot
    'watch': ('callback', 'watch_request', 'watch_forward'),
    'image': ('image',),
}


def robot_of(connection: capture.Connection, owners: dict[int, str]) -> str | None:
    """The robot at one end of a connection (as client, or as the server it called), if any."""
    for node in (connection.caller, owners.get(connection.server[1], '')):
        if node.startswith(('/robot', '/irobot')):
            return node
    return None


def count(before: dict, after: dict, counted: tuple[str, ...], owners: dict[int, str], robots) -> Counted:
    """What crossed the wire between two snapshots; of robots' connections, only ``robots``'."""
    by_category: dict[str, int] = {}
    received: dict[str, int] = {}
    messages: dict[str, int] = {}
    requests: dict[str, int] = {}
    setup = ip = 0
    changed = []
    for key, connection in after.items():
        old = before.get(key)
        up = connection.up.bytes - (old.up.bytes if old else 0)
        down = connection.down.bytes - (old.down.bytes if old else 0)
        if not (up or down):
            continue
        if connection.server[1] not in owners and connection.client[1] not in owners:
            continue  # another process's traffic on lo
        kind = category(connection)
        robot = robot_of(connection, owners)
        if kind == 'bench' or (robot is not None and robot not in robots):
            continue  # a trigger, or a robot not in this size (image robots 2-10 at 1×C)
        headers = connection.header_bytes if old is None else 0
        if kind not in counted:
            by_category[kind] = by_category.get(kind, 0) + up + down - headers
            by_category['setup:' + kind] = by_category.get('setup:' + kind, 0) + headers
            continue
        by_category[kind] = by_category.get(kind, 0) + up + down - headers
        setup += headers
        ip += connection.up.ip_bytes + connection.down.ip_bytes
        ip -= (old.up.ip_bytes + old.down.ip_bytes) if old else 0
        count_up = connection.up.framer.messages - (old.up.framer.messages if old else 0)
        count_down = connection.down.framer.messages - (old.down.framer.messages if old else 0)
        messages[kind] = messages.get(kind, 0) + count_up + count_down
        requests[kind] = requests.get(kind, 0) + count_up
        changed.append((connection, up, down))
        # Bytes towards the robot, connection headers left out: what it receives as the client,
        # what it is sent as the server.
        if robot is not None and robot == connection.caller:
            received[robot] = (
                received.get(robot, 0) + down - (connection.down.framer.header_bytes if old is None else 0)
            )
        elif robot is not None:
            received[robot] = (
                received.get(robot, 0) + up - (connection.up.framer.header_bytes if old is None else 0)
            )
    by_category = {k: v for k, v in by_category.items() if v}
    return Counted(by_category, setup, received, messages, requests, ip, changed)


# -- the photograph ---------------------------------------------------------------------------------
def photograph(path: Path, size: tuple[int, int]) -> str | None:
    """Write scipy's face photograph resized to ``size``; None, or why it is unavailable.

    Read as ``scipy.misc.face()`` reads it (bz2-compressed 768×1024×3 bytes in
    ``scipy/misc/face.dat``) without importing scipy, which takes seconds and warns that
    ``scipy.misc.face`` moves to ``scipy.datasets`` (which downloads it).
    """
    import bz2
    import importlib.util

    import cv2
    import numpy as np

    spec = importlib.util.find_spec('scipy')
    data = Path(spec.submodule_search_locations[0]) / 'misc' / 'face.dat' if spec else None
    if data is None or not data.exists():
        return 'scipy/misc/face.dat not found: install python3-scipy (Debian) for the photograph'
    rgb = np.frombuffer(bz2.decompress(data.read_bytes()), np.uint8).reshape(768, 1024, 3)
    image = cv2.resize(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), size, interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(path), image)
    return None


# -- the run ---------------------------------------------------------------------------------------
def run(ctx: Context) -> Section:
    section = Section(NAME, TITLE)
    ok, why = capture.available()
    if not ok:
        return unavailable(section, f'no capture: {why}')
    from drvs.testing.harness import RosHarness

    sizes = ctx.pick(SIZES[:1], SIZES[:1], SIZES)  # quick: 20 vision systems take 40 s to start
    resolution = ctx.pick((320, 240), (800, 600), (800, 600))
    rounds = ctx.pick(1, 1, 3)
    cameras = max(c for _, c in sizes)
    work = ctx.work_dir / 'wire'
    work.mkdir(parents=True, exist_ok=True)
    photo = work / 'photo.png'
    photo_problem = photograph(photo, resolution) if ctx.size != 'tiny' else 'tiny: the rendered frame only'
    kinds = ['render'] + ([] if photo_problem else ['photo'])
    results: dict = {
        'sizes_run': [f'{r}x{c}' for r, c in sizes],
        'resolution': list(resolution),
        'rounds_per_measure': rounds,
        'photo': PHOTO if not photo_problem else photo_problem,
        'algorithm': ALGORITHM,
        'sizes': {},
    }
    # Every connection on lo is followed: the nodes' ports are known only once they run, and the
    # first connections (registrations, subscriptions) are opened before.
    with RosHarness() as ros, capture.Capture(None) as cap, interrupting(ros):
        bench = WireBench(ctx, ros, cap, cameras, resolution, period=ctx.pick(0.2, 1.0, 2.0))
        try:
            measure(ctx, bench, sizes, kinds, rounds, photo, results)
        finally:
            bench.close()
    return report(ctx, section, results, sizes, kinds)


def measure(ctx: Context, bench: WireBench, sizes, kinds: list[str], rounds: int, photo: Path, results: dict):
    """Start every node, measure each size in turn, profile a robot; into ``results``."""
    cameras = max(c for _, c in sizes)
    robots = max(r for r, _ in sizes)
    ctx.progress(f'wire: starting server, {cameras} vision systems, {robots} robots')
    t0 = time.monotonic()
    bench.start_drvs(robots)
    if (1, 20) in sizes:
        bench.start_profiled()
    bench.start_image_cameras(kinds, photo)
    bench.start_image_robots(range(1, robots + 1))
    results['startup'] = {}
    fresh = True  # image robots that have not decoded a frame yet: their first round warms up
    for robots_n, cameras_n in sizes:
        label = f'{robots_n}x{cameras_n}'
        results['sizes'][label] = measure_size(ctx, bench, (robots_n, cameras_n), kinds, rounds, fresh)
        results['startup'][label] = round(results['sizes'][label].pop('ready') - t0, 2)
        for key in ('profile', 'profile_fused'):
            if key in results['sizes'][label]:
                results[key] = results['sizes'][label].pop(key)
        fresh = False
    results['capture'] = capture_summary(bench)
    results['dropped_callbacks'] = dropped_callbacks(bench)
    results['incomplete_rounds'] = bench.incomplete_rounds


@contextlib.contextmanager
def interrupting(ros):
    """On the way out, SIGINT every node at once (the harness then stops them one by one: 45
    rospy nodes take a while to exit each); the harness still reaps and kills them all."""
    try:
        yield
    finally:
        masters = {id(node) for node in ros.master.processes}
        for node in ros.nodes:
            if id(node) not in masters and node.running():
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(node.pid, signal.SIGINT)


def unavailable(section: Section, why: str) -> Section:
    section.results = {'unavailable': why}
    for name, limit, at_most in (
        ('callback_bytes_one_object', 200, True),
        ('image_to_drvs_bytes_10x50_photo', 174, False),
        ('robot_cpu_image_over_drvs', 100, False),
        ('robot_cpu_image_over_drvs_fused', 100, False),
    ):
        section.targets[name] = target(None, limit, at_most=at_most, note=why)
    section.markdown = (
        f'Not measured: {why}.\n\nReproduce: {REPRODUCE} (as root: the capture uses AF_PACKET).\n'
    )
    return section


def capture_summary(bench: WireBench) -> dict:
    ours = bench.snapshot().values()
    return {
        'interface': bench.cap.interface,
        'kernel_drops': bench.cap.drops,
        'gaps': sum(c.up.gaps + c.down.gaps for c in ours),
        'connections': len(ours),
        'connections_on_lo': bench.cap.tracked,
        'tcpros_bytes_total': sum(c.bytes for c in ours if c.protocol == 'tcpros' and c.caller != BENCH),
    }


def measure_size(ctx, bench: WireBench, size, kinds, rounds: int, fresh: bool) -> dict:
    robots_n, cameras_n = size
    label = f'{robots_n}x{cameras_n}'
    region = 'a' if cameras_n == 1 else ('p' if cameras_n == 20 else 'q')
    drvs_robots = [bench.drvs_robots[i] for i in range(1, robots_n + 1)]
    image_robots = [bench.image_robots[i] for i in range(1, robots_n + 1)]
    out: dict = {'robots': robots_n, 'cameras': cameras_n, 'region': region}
    ctx.progress(f'wire: {label} warming up')
    bench.ready(robots_n, cameras_n, region)
    out['ready'] = time.monotonic()
    profiled = bench.profiled if size == (1, 20) else None
    warm_up(bench, drvs_robots + ([profiled] if profiled else []), region, cameras_n)
    owners = bench.owners
    # DRVS one-shot rounds.
    oneshot = []
    for number in range(rounds):
        ctx.progress(f'wire: {label} DRVS one-shot round {number + 1}/{rounds}')
        oneshot.append(oneshot_round(bench, drvs_robots, region, cameras_n, owners))
    out['drvs_oneshot'] = summarise(oneshot)
    # DRVS fused rounds: the server's first fused rounds open the cameras' connections to it.
    warm_up(bench, drvs_robots + ([profiled] if profiled else []), region, cameras_n, fused=True)
    fused = []
    for number in range(rounds):
        ctx.progress(f'wire: {label} DRVS fused round {number + 1}/{rounds}')
        fused.append(fused_round(bench, drvs_robots, region, cameras_n, owners))
    out['drvs_fused'] = summarise(fused)
    if profiled:
        ctx.progress(f'wire: {label} profiling a DRVS robot')
        out['profile'] = profile_robot(bench, profiled, ctx.pick(0, 2, 10))
        out['profile_fused'] = profile_robot(bench, profiled, ctx.pick(0, 5, 20), fused=True)
    # A DRVS watch: one period.
    ctx.progress(f'wire: {label} DRVS watch, {rounds} period(s)')
    out['drvs_watch'] = watch_periods(bench, drvs_robots, region, cameras_n, rounds, owners)
    # Image sharing.
    for kind in kinds:
        measured = []
        if fresh:  # the robots' first frames (cv2's first calls): not counted
            image_round(bench, image_robots, kind, cameras_n, owners)
            fresh = False
        for number in range(rounds):
            ctx.progress(f'wire: {label} image sharing ({kind}) round {number + 1}/{rounds}')
            measured.append(image_round(bench, image_robots, kind, cameras_n, owners))
        out[f'image_{kind}'] = summarise(measured)
    return out


STALL = VISION_PARAMS['callback_timeout'] + 3.0
"""Seconds without a new callback after which a round's missing callbacks are taken as dropped."""


def arrived(bench: WireBench, robots: list[Robot], asked: dict[int, dict], cameras_n: int) -> bool:
    """Wait until every robot has ``cameras_n`` callbacks of its request; False if they stall
    (a vision system dropped one: logged in its log) before. A fused request: until its one
    callback came, False unless all ``cameras_n`` vision systems answered in it."""
    if asked[robots[0].index]['request_id'].startswith('fused_'):
        return fused_arrived(bench, robots, asked, cameras_n)
    last = {'count': -1, 'at': time.monotonic()}

    def done():
        counts = [len(callbacks_of(r, asked[r.index]['request_id'])) for r in robots]
        if all(n >= cameras_n for n in counts):
            return 'all'
        if sum(counts) != last['count']:
            last.update(count=sum(counts), at=time.monotonic())
        elif time.monotonic() - last['at'] > STALL:
            return 'stalled'
        return None

    return bench.wait(done, 3600.0, 'callbacks') == 'all'


def fused_arrived(bench: WireBench, robots: list[Robot], asked: dict[int, dict], cameras_n: int) -> bool:
    """Wait for each robot's one fused callback (the server sends it by ``~fused_deadline`` at the
    latest); True when every one says all ``cameras_n`` vision systems answered."""

    def answers():
        found = [callbacks_of(r, asked[r.index]['request_id']) for r in robots]
        return found if all(found) else None

    timeout = SERVER_PARAMS['fused_deadline'] + bench.ctx.pick(20.0, 60.0, 120.0)
    found = bench.wait(answers, timeout, 'fused callbacks')
    return all(x[0]['status'] == 0 and x[0]['answered'] == cameras_n for x in found)


def warm_up(bench: WireBench, robots: list[Robot], region: str, cameras_n: int, fused: bool = False) -> None:
    """Rounds not counted, until one reaches every robot from all its cameras: the cameras open
    their connections to the robots' callback services (fused: to the server's; a first contact
    can be dropped, see :func:`dropped_callbacks`) and every registration is in the server's
    registry."""
    timeout = bench.ctx.pick(30.0, 180.0, 600.0)
    deadline = time.monotonic() + timeout
    while True:
        asked = {robot.index: ask(bench, robot, region, fused) for robot in robots}
        reached = {i: x['vision_systems'] for i, x in asked.items()}
        if all(n == cameras_n for n in reached.values()) and arrived(bench, robots, asked, cameras_n):
            return
        if time.monotonic() > deadline:
            raise AssertionError(
                f'no warm-up round of {len(robots)}x{cameras_n} came through in {timeout:g} s: '
                f'requests reached {reached} cameras'
            )
        if not all(n == cameras_n for n in reached.values()):
            time.sleep(0.5)  # a registration answered, not in the registry yet: ask again


def profile_robot(bench: WireBench, robot: Robot, rounds: int, fused: bool = False) -> dict:
    """Where a DRVS robot's CPU goes: ``robot`` (see :meth:`WireBench.start_profiled`) asks ``rounds``
    1×20 one-shot rounds, per camera or fused (the profiler inflates its numbers: only the shares
    count). Per callback: per camera, 20 a round; fused, one a round (so: per round)."""
    import pstats

    path = bench.profile_path
    done = path.with_name(path.name + '.done')
    os.kill(robot.node.pid, signal.SIGUSR2)  # statistics of the warm-up: subtracted below
    bench.wait(done.exists, 20.0, 'the profile of the warm-up')
    done.unlink()
    before = pstats.Stats(*sorted(map(str, path.parent.glob(path.name + '.[0-9]*')))).stats
    for _ in range(rounds):
        arrived(bench, [robot], {robot.index: ask(bench, robot, 'p', fused)}, 20)
    os.kill(robot.node.pid, signal.SIGUSR2)
    bench.wait(done.exists, 20.0, 'the profile')
    done.unlink()
    stats = pstats.Stats(*sorted(map(str, path.parent.glob(path.name + '.[0-9]*')))).stats
    callbacks = rounds * (1 if fused else 20)
    rows = []
    for key, (_, calls, tottime, cumtime, _) in stats.items():
        old = before.get(key, (0, 0, 0.0, 0.0, None))
        calls, tottime, cumtime = calls - old[1], tottime - old[2], cumtime - old[3]
        if calls > 0:
            rows.append((key, calls, tottime, cumtime))
    total = sum(r[2] for r in rows)
    groups: dict[str, float] = {}
    for (file, _, function), _, tottime, _ in rows:
        groups[code_group(file, function)] = groups.get(code_group(file, function), 0.0) + tottime
    top = sorted(rows, key=lambda r: -r[2])[:12]
    return {
        'rounds': rounds,
        'fused': fused,
        'callbacks': callbacks,
        'profiled_us_per_callback': total / callbacks * 1e6 if callbacks else math.nan,
        'groups_us_per_callback': {
            k: v / callbacks * 1e6 for k, v in sorted(groups.items(), key=lambda x: -x[1])
        },
        'top': [
            {
                'function': f'{Path(file).name}:{line}({function})',
                'calls_per_callback': calls / callbacks,
                'tottime_us_per_callback': tottime / callbacks * 1e6,
                'cumtime_us_per_callback': cumtime / callbacks * 1e6,
            }
            for (file, line, function), calls, tottime, cumtime in top
        ],
    }


def code_group(file: str, function: str) -> str:
    """Whose code a profiled function is: the bench robot's, DRVS's, rospy's/genpy's, or Python's."""
    if file.endswith('drvs_robot.py'):
        return 'robot handler (bench node)'
    if '/rospy/' in file or '/genpy/' in file or '/drvs/srv/' in file or '/drvs/msg/' in file:
        return 'rospy + genpy (TCPROS, (de)serialisation)'
    if '/drvs/' in file:
        return 'drvs (ServiceClient: the ask)'
    if file == '~' and ('socket' in function or 'select' in function or 'poll' in function):
        return 'socket calls'
    if file == '~':
        return 'builtins (C)'
    return 'Python stdlib (threading, struct, io, ...)'


def dropped_callbacks(bench: WireBench) -> int:
    """Callbacks the vision systems dropped (logged). rospy's TCPROS server listens with a backlog
    of 5: when 20 cameras first call one robot at once, some connects wait for a SYN to be
    resent (1 s, 3 s, ...); on a loaded machine a call can also outlast ``callback_timeout``."""
    return sum(node.log(100_000).count('dropped: service /robot') for node in bench.vision)


def ask(bench: WireBench, robot: Robot, region: str, fused: bool = False) -> dict:
    """Have ``robot`` ask about its region ``region`` once (``fused``: with fused true); its ``ask`` line."""
    before = len([x for x in robot.lines.read() if x['event'] == 'ask'])
    bench.trigger(robot, f'fuse_{region}' if fused else f'ask_{region}')
    asks = [x for x in robot.lines.read() if x['event'] == 'ask']
    if len(asks) <= before:
        raise AssertionError(f'robot{robot.index} did not log its ask')
    if asks[-1]['status'] != 0:
        raise AssertionError(f'robot{robot.index}: request refused: {asks[-1]["message"]}')
    return asks[-1]


def names(robots: list[Robot], prefix: str = 'robot') -> set[str]:
    return {f'/{prefix}{robot.index}' for robot in robots}


def callbacks_of(robot: Robot, request_id: str) -> list[dict]:
    """The robot's callbacks for ``request_id`` (ending in ``_``: for every id starting so)."""
    if request_id.endswith('_'):
        return [
            x
            for x in robot.lines.read()
            if x['event'] == 'callback' and x['request_id'].startswith(request_id)
        ]
    return [x for x in robot.lines.read() if x['event'] == 'callback' and x['request_id'] == request_id]


def wait_callbacks(bench: WireBench, robot: Robot, request_id: str, n: int) -> list[dict]:
    return bench.wait(
        lambda: (found if len(found := callbacks_of(robot, request_id)) >= n else None),
        bench.ctx.pick(20.0, 60.0, 120.0),
        f'{n} callbacks of {request_id} at robot{robot.index}',
    )


def oneshot_round(bench: WireBench, robots: list[Robot], region: str, cameras_n: int, owners) -> dict:
    """One one-shot round: every robot asks once; asked again (up to 3 times) if a callback is dropped."""
    attempts = 0
    while True:
        attempts += 1
        before = bench.settle()
        asked = {robot.index: ask(bench, robot, region) for robot in robots}
        if arrived(bench, robots, asked, cameras_n):
            break
        bench.incomplete_rounds += 1
        if attempts == 3:
            raise AssertionError(f'three {len(robots)}x{cameras_n} one-shot rounds in a row lost callbacks')
    callbacks = {i: callbacks_of(bench.drvs_robots[i], x['request_id']) for i, x in asked.items()}
    after = bench.settle()
    counted = count(before, after, ROUND_CATEGORIES['oneshot'], owners, names(robots))
    cpu = [max(x['cpu'] for x in callbacks[i]) - asked[i]['cpu0'] for i in asked]
    vertices = [x['vertices'] for found in callbacks.values() for x in found]
    handler = statistics.fmean(x['handler'] for found in callbacks.values() for x in found)
    objects = [x['objects'] for found in callbacks.values() for x in found]
    result = round_result(counted, ROUND_CATEGORIES['oneshot'], robots, owners, cpu)
    result.update(vertices=sorted(set(vertices)), objects=sorted(set(objects)), handler_per_callback=handler)
    result['attempts'] = attempts
    if len(robots) == 1 and cameras_n == 1:
        result['callback'] = one_callback(counted, robots[0])
    return result


def fused_round(bench: WireBench, robots: list[Robot], region: str, cameras_n: int, owners) -> dict:
    """One fused round: every robot asks once with ``fused`` true and gets one callback; asked again
    (up to 3 times) if the server answered it without every camera (a callback to it dropped)."""
    attempts = 0
    while True:
        attempts += 1
        before = bench.settle()
        asked = {robot.index: ask(bench, robot, region, fused=True) for robot in robots}
        if fused_arrived(bench, robots, asked, cameras_n):
            break
        bench.incomplete_rounds += 1
        if attempts == 3:
            raise AssertionError(f'three {len(robots)}x{cameras_n} fused rounds in a row lacked a camera')
    callbacks = {i: callbacks_of(bench.drvs_robots[i], x['request_id']) for i, x in asked.items()}
    after = bench.settle()
    counted = count(before, after, ROUND_CATEGORIES['fused'], owners, names(robots))
    cpu = [max(x['cpu'] for x in callbacks[i]) - asked[i]['cpu0'] for i in asked]
    every = [x for found in callbacks.values() for x in found]
    result = round_result(counted, ROUND_CATEGORIES['fused'], robots, owners, cpu)
    result.update(
        vertices=sorted({x['vertices'] for x in every}),
        objects=sorted({x['objects'] for x in every}),
        handler_per_callback=statistics.fmean(x['handler'] for x in every),
        callbacks_per_robot=statistics.fmean(len(found) for found in callbacks.values()),
        ask_cpu=statistics.fmean(x['cpu'] - x['cpu0'] for x in asked.values()),
        latency=statistics.median(
            x['received'] - asked[i]['sent'] for i, found in callbacks.items() for x in found
        ),
        attempts=attempts,
    )
    return result


def one_callback(counted: Counted, robot: Robot) -> dict:
    """The callback's request and response bytes on its established connection (1×1)."""
    found = [(c, up, down) for c, up, down in counted.connections if category(c) == 'callback']
    if len(found) != 1:
        return {'error': f'{len(found)} callback connections in the round'}
    connection, up, down = found[0]
    return {
        'request_bytes': up,
        'response_bytes': down,
        'bytes': up + down,
        'connection_header_bytes': connection.header_bytes,
        'request_messages': 1,
        'vision_system': connection.caller,
        'service': connection.name,
    }


def round_result(counted: Counted, categories, robots: list[Robot], owners, cpu: list[float]) -> dict:
    total = sum(counted.by_category.get(k, 0) for k in categories)
    # Everything else meanwhile, by every node: XML-RPC (master watch, lookups), registrations, probes.
    others = {k: v for k, v in counted.by_category.items() if k not in categories}
    received = list(counted.received.values())
    return {
        'total': total,
        'with_setup': total + counted.setup,
        'ip_bytes': counted.ip_bytes,
        'by_category': {k: counted.by_category.get(k, 0) for k in categories},
        'messages': counted.messages,
        'others_meanwhile': others,
        'received_per_robot': statistics.fmean(received) if received else 0,
        'received_max': max(received) if received else 0,
        'cpu_per_robot': statistics.fmean(cpu) if cpu else math.nan,
        'cpu_max': max(cpu) if cpu else math.nan,
    }


def watch_periods(bench: WireBench, robots: list[Robot], region: str, cameras_n: int, periods: int, owners):
    """Start one watch per robot, skip its first period, count ``periods`` periods' callbacks; cancel."""
    request_id = f'watch_{region}'
    for robot in robots:
        bench.trigger(robot, f'watch_{region}')
    started = {r.index: len(callbacks_of(r, request_id)) for r in robots}
    for robot in robots:  # the first period: the VSs open their connections (if needed)
        wait_callbacks(bench, robot, request_id, started[robot.index] + cameras_n)
    marks = bench.mark(robots)
    before = bench.snapshot()  # callbacks keep coming: no quiet moment to wait for
    counts = {r.index: len(callbacks_of(r, request_id)) for r in robots}
    for robot in robots:
        wait_callbacks(bench, robot, request_id, counts[robot.index] + periods * cameras_n)
    after = bench.snapshot()
    news = {r.index: callbacks_of(r, request_id)[counts[r.index] :] for r in robots}
    counted = count(before, after, ROUND_CATEGORIES['watch'], owners, names(robots))
    for robot in robots:
        bench.trigger(robot, f'unwatch_{region}')
    n_callbacks = counted.requests.get('callback', 0)
    scale = len(robots) * cameras_n / n_callbacks if n_callbacks else math.nan  # to one period
    cpu = [(max(x['cpu'] for x in news[i]) - marks[i]) / len(news[i]) * cameras_n for i in news if news[i]]
    result = round_result(counted, ROUND_CATEGORIES['watch'], robots, owners, cpu)
    for key in ('total', 'with_setup', 'ip_bytes', 'received_per_robot', 'received_max'):
        result[key] = result[key] * scale
    result['callbacks_counted'] = n_callbacks
    result['period_s'] = bench.period
    result['withdrawal_seen'] = wait_unwatched(bench, robots, cameras_n)
    return result


def wait_unwatched(bench: WireBench, robots: list[Robot], cameras_n: int) -> bool:
    """Until every vision system answered the server's withdrawal of every watch (seen on the wire),
    or, failing that, no watch callback came for three periods; True in the first case."""
    expected = bench.watch_forwards + 2 * len(robots) * cameras_n  # each watch: its start and its end
    callbacks = {r.index: len(callbacks_of(r, 'watch_')) for r in robots}
    quiet = {'since': time.monotonic(), 'seen': dict(callbacks)}

    def forwards() -> int:
        snap = bench.snapshot()
        return sum(c.up.framer.messages for c in snap.values() if category(c) == 'watch_forward')

    def withdrawn():
        if forwards() >= expected:
            return 'answered'
        now = {r.index: len(callbacks_of(r, 'watch_')) for r in robots}
        if now != quiet['seen']:
            quiet.update(since=time.monotonic(), seen=now)
        elif time.monotonic() - quiet['since'] > max(3 * bench.period, 2.0):
            return 'quiet'
        return None

    how = bench.wait(withdrawn, 60.0, f'the watches to be withdrawn ({forwards()} of {expected} forwards)')
    bench.watch_forwards = forwards()
    return how == 'answered'


def wait_subscribed(bench: WireBench, robots: list[Robot], cameras_n: int) -> None:
    """Until every image robot has a TCPROS connection to the topics of cameras 1-``cameras_n``
    (headers exchanged)."""
    topics = {t for t in bench.image_topics() if int(t.split('/vs')[1].split('/')[0]) <= cameras_n}

    def connected():
        snap = bench.snapshot()
        for robot in robots:
            have = {
                c.name
                for c in snap.values()
                if c.kind == 'topic' and c.caller == f'/irobot{robot.index}' and c.down.framer.fields
            }
            if not topics <= have:
                return False
        return True

    bench.wait(connected, bench.ctx.pick(30.0, 60.0, 180.0), 'image robots to connect to the cameras')


def image_round(bench: WireBench, robots: list[Robot], kind: str, cameras_n: int, owners) -> dict:
    marks = bench.mark(robots)
    before = bench.settle()
    start = {r.index: len(r.lines.read()) for r in robots}
    bench.publish(kind, cameras_n)

    def frames(robot: Robot) -> list[dict]:
        return [x for x in robot.lines.read()[start[robot.index] :] if x['event'] == 'frame']

    for robot in robots:
        bench.wait(
            lambda robot=robot: len(frames(robot)) >= cameras_n,
            bench.ctx.pick(20.0, 60.0, 180.0),
            f'{cameras_n} {kind} frames at irobot{robot.index}',
        )
    after = bench.settle()
    counted = count(before, after, ROUND_CATEGORIES['image'], owners, names(robots, 'irobot'))
    got = {r.index: frames(r) for r in robots}
    cpu = [max(x['cpu'] for x in got[i]) - marks[i] for i in got]
    result = round_result(counted, ROUND_CATEGORIES['image'], robots, owners, cpu)
    every = [x for found in got.values() for x in found]
    result['jpeg_bytes'] = statistics.fmean(x['bytes'] for x in every)
    result['work_per_frame'] = statistics.fmean(x['work'] for x in every)
    result['decode_per_frame'] = statistics.fmean(x.get('decode', math.nan) for x in every)
    result['objects_per_frame'] = statistics.fmean(x['objects'] for x in every)
    result['latency_p50'] = statistics.median(x['latency'] for x in every)
    return result


def summarise(rounds: list[dict]) -> dict:
    """The median of each number over the rounds (the rounds kept under ``rounds``)."""
    keys = [k for k, v in rounds[0].items() if isinstance(v, int | float) and not isinstance(v, bool)]
    summary = {k: statistics.median(r[k] for r in rounds) for k in keys}
    summary['by_category'] = rounds[-1]['by_category']
    summary['others_meanwhile'] = rounds[-1]['others_meanwhile']
    summary['messages'] = rounds[-1]['messages']
    for extra in ('vertices', 'objects', 'callback'):
        if extra in rounds[-1]:
            summary[extra] = rounds[-1][extra]
    summary['rounds'] = [{k: r[k] for k in keys} for r in rounds]
    return summary


# -- the report --------------------------------------------------------------------------------------
def kb(value: float) -> float:
    return value / 1000.0


def report(ctx: Context, section: Section, results: dict, sizes, kinds) -> Section:
    section.results = results
    measured = results['sizes']
    rows = []
    for robots_n, cameras_n in sizes:
        label = f'{robots_n}x{cameras_n}'
        entry = measured[label]
        paper = PAPER_KB[(robots_n, cameras_n)]
        one, watch, fused = entry['drvs_oneshot'], entry['drvs_watch'], entry['drvs_fused']
        row = [label] + [
            f'{kb(drvs["total"]):.2f} / {kb(drvs["received_per_robot"]):.2f}' for drvs in (one, watch, fused)
        ]
        row.append(f'{paper[0]:g} / {paper[1]:g}')
        for kind in ('render', 'photo'):
            image = entry.get(f'image_{kind}')
            row.append(f'{kb(image["total"]):,.1f} / {kb(image["received_per_robot"]):,.1f}' if image else '')
        row.append(f'{paper[2]:g} / {paper[3]:g}')
        best = entry.get('image_photo') or entry['image_render']
        row += [f'{best["total"] / one["total"]:.0f}', f'{best["total"] / fused["total"]:.0f}']
        rows.append(row)
    header = [
        'robots×cameras',
        'DRVS one-shot',
        'DRVS watch (1 period)',
        'DRVS fused',
        'paper DRVS',
        'image: render',
        'image: photo',
        'paper image',
        'image (photo, else render) / DRVS one-shot',
        '… / DRVS fused',
    ]
    cpu_rows = []
    for robots_n, cameras_n in sizes:
        entry = measured[f'{robots_n}x{cameras_n}']
        one, watch, fused = entry['drvs_oneshot'], entry['drvs_watch'], entry['drvs_fused']
        row = [f'{robots_n}x{cameras_n}'] + [drvs['cpu_per_robot'] * 1e3 for drvs in (one, watch, fused)]
        for kind in ('render', 'photo'):
            image = entry.get(f'image_{kind}')
            cpu = image['cpu_per_robot'] if image else None
            row += [cpu * 1e3, cpu / one['cpu_per_robot'], cpu / fused['cpu_per_robot']] if cpu else [''] * 3
        cpu_rows.append(row)
    cpu_header = [
        'robots×cameras',
        'DRVS one-shot ms',
        'DRVS watch ms',
        'DRVS fused ms',
        'image render ms',
        '/ one-shot',
        '/ fused',
        'image photo ms',
        '/ one-shot',
        '/ fused',
    ]
    # Targets.
    first = measured[f'{sizes[0][0]}x{sizes[0][1]}']
    callback = first['drvs_oneshot'].get('callback', {})
    value = callback.get('bytes')
    note = (
        f'request {callback.get("request_bytes")} + response {callback.get("response_bytes")} B on an '
        f'established connection; its connection headers {callback.get("connection_header_bytes")} B once'
        if value
        else callback.get('error', 'not measured')
    )
    section.targets['callback_bytes_one_object'] = target(value, 200, note=note)
    largest = sizes[-1]
    big = measured[f'{largest[0]}x{largest[1]}']
    ratio_kind = 'photo' if 'image_photo' in big else 'render'
    ratio = big[f'image_{ratio_kind}']['total'] / big['drvs_oneshot']['total']
    if largest == (10, 50) and ratio_kind == 'photo':
        section.targets['image_to_drvs_bytes_10x50_photo'] = target(ratio, 174, at_most=False)
    else:
        section.targets['image_to_drvs_bytes_10x50_photo'] = target(
            None,
            174,
            at_most=False,
            note=f'no 10×50 at size {ctx.size}; at {largest[0]}×{largest[1]} ({ratio_kind}): {ratio:.0f}',
        )
    image_cpu = big[f'image_{ratio_kind}']['cpu_per_robot']
    cpu_ratio = image_cpu / big['drvs_oneshot']['cpu_per_robot']
    fused_ratio = image_cpu / big['drvs_fused']['cpu_per_robot']
    for name, value, drvs in (
        ('robot_cpu_image_over_drvs', cpu_ratio, 'DRVS one-shot (per camera)'),
        ('robot_cpu_image_over_drvs_fused', fused_ratio, 'DRVS fused'),
    ):
        section.targets[name] = target(
            value,
            100,
            at_most=False,
            note=f'at {largest[0]}×{largest[1]}, {ratio_kind}: image sharing / {drvs} robot CPU per round',
        )
    results['ratios'] = {
        'bytes_image_over_drvs_largest': ratio,
        'bytes_image_over_drvs_fused_largest': big[f'image_{ratio_kind}']['total']
        / big['drvs_fused']['total'],
        'cpu_image_over_drvs_largest': cpu_ratio,
        'cpu_image_over_drvs_fused_largest': fused_ratio,
    }
    section.plots = [plot(ctx, measured, sizes)]
    capture_info = results['capture']
    width, height = results['resolution']
    lines = [
        'Bytes per round of vision in kB (total / received per robot), counted on the wire by a raw capture '
        "on `lo` (TCP payload: TCPROS length prefixes and headers included), next to the paper's calculated "
        'Table 1, on established connections (connection headers, and the XML-RPC every node sends '
        'meanwhile, are in latest.json).',
        '',
        table(header, rows),
        'DRVS fused: the robot sends one request and gets one callback (every object once) from the server, '
        "which gathers the cameras' callbacks on `/drvs/fusion_callback`; its bytes are the request, the "
        "forwards, the cameras' callbacks to the server and the one callback to the robot. "
        + fused_line(measured, sizes),
        '',
        'Robot CPU per round and robot (process CPU, every thread), same run; image CPU over DRVS one-shot '
        '(per camera) and over DRVS fused:',
        '',
        table(cpu_header, cpu_rows),
        f'One callback with one four-vertex object: {note} (paper: under 200 B); '
        + messages_line(first['drvs_oneshot'])
        + f' Frames {width}×{height}; the photograph: {results["photo"]}. DRVS bytes do not depend on the '
        'photograph (the vision systems segment their rendered view).',
        f'Capture: {capture_info["kernel_drops"]} packets dropped by the kernel, {capture_info["gaps"]} '
        f'gaps, {capture_info["connections"]} connections of our nodes ({capture_info["connections_on_lo"]} '
        'on lo). '
        'Every node is started at once; seconds until each size was ready (its cameras registered, '
        'its robots subscribed): ' + ', '.join(f'{k} {v:.1f} s' for k, v in results['startup'].items()) + '.',
        '',
        f'Reproduce: {REPRODUCE}.',
    ]
    lines[-2:-2] = cpu_breakdown(results, sizes)
    section.markdown = '\n'.join(lines) + '\n'
    return section


def fused_line(measured: dict, sizes) -> str:
    """One sentence: what a robot gets in a fused round at the largest size, and how its CPU splits."""
    robots_n, cameras_n = sizes[-1]
    fused = measured[f'{robots_n}x{cameras_n}']['drvs_fused']
    to_server, to_robots = (kb(fused['by_category'].get(k, 0)) for k in ('fusion_callback', 'callback'))
    objects = ', '.join(map(str, fused['objects']))
    calls = fused['messages'].get('callback', 0) / 2  # requests and responses
    each = fused['by_category'].get('callback', 0) / calls if calls else math.nan
    return (
        f'At {robots_n}×{cameras_n} each robot got {fused["callbacks_per_robot"]:g} callback per fused round '
        f'(objects in it: {objects}; p50 {fused["latency"] * 1e3:.0f} ms after its request), the '
        f"cameras' callbacks ({cameras_n} a robot) going to the server instead ({to_server:.1f} kB a round "
        f'in all, against {to_robots:.2f} kB to the robots, {each:.0f} B a fused callback with its response: '
        'it names every vision system that answered (`answered`) and, for each object, those that saw it '
        "(`seen_by`), by their service names); of the robot's "
        f'{fused["cpu_per_robot"] * 1e6:.0f} µs of CPU per round, {fused["ask_cpu"] * 1e6:.0f} µs went on '
        f'the ask (until the acknowledgement) and {fused["handler_per_callback"] * 1e6:.0f} µs on its '
        'callback handler.'
    )


def messages_line(oneshot: dict) -> str:
    """One sentence: the bytes of each message pair of a 1×1 one-shot round."""
    parts = oneshot['by_category']
    return (
        f'a 1×1 one-shot round is robot↔server {parts.get("request", 0)} B, server↔camera '
        f'{parts.get("forward", 0)} B and camera↔robot {parts.get("callback", 0)} B (each request with '
        'its response).'
    )


def cpu_breakdown(results: dict, sizes) -> list[str]:
    """Markdown: where the robots' CPU goes, per camera (measured; the profile's shares), and why."""
    robots_n, cameras_n = max((s for s in sizes if s[0] == 1), key=lambda s: s[1])
    entry = results['sizes'][f'{robots_n}x{cameras_n}']
    one = entry['drvs_oneshot']
    image = entry.get('image_photo') or entry['image_render']
    per_callback = one['cpu_per_robot'] / cameras_n
    handler = one['handler_per_callback']
    per_frame = image['cpu_per_robot'] / cameras_n
    decode, work = image['decode_per_frame'], image['work_per_frame']
    lines = [
        f'Where the robot CPU goes ({robots_n}×{cameras_n}, per camera): DRVS {per_callback * 1e6:.0f} µs '
        f'of process CPU per callback (its share of the ask included), {handler * 1e6:.0f} µs of it in the '
        f"robot's handler; image sharing {per_frame * 1e3:.1f} ms per frame: decoding {decode * 1e3:.1f} ms, "
        f'segmenting {(work - decode) * 1e3:.1f} ms, receiving {(per_frame - work) * 1e3:.1f} ms. The DRVS '
        "robot's cost is rospy's per call: its TCPROS service server receives, deserialises (genpy), calls "
        'the handler, serialises and sends, in Python, in a thread per connection. A fused request makes '
        'it one call per round (the server gathers the cameras\' answers) however many cameras see the '
        f'region: {entry["drvs_fused"]["cpu_per_robot"] * 1e6:.0f} µs of robot CPU per fused round here.',
    ]
    profile, fused = results.get('profile'), results.get('profile_fused')
    if not profile:
        return [*lines, '']
    groups = profile['groups_us_per_callback']
    total = sum(groups.values())
    fused_groups = fused['groups_us_per_callback'] if fused and fused['rounds'] else {}
    fused_total = sum(fused_groups.values())
    rows = [
        [k, v, f'{v / total:.0%}']
        + ([fused_groups.get(k, 0.0), f'{fused_groups.get(k, 0.0) / fused_total:.0%}'] if fused_total else [])
        for k, v in groups.items()
    ]
    header = ['code', 'per camera: µs / callback', 'share']
    header += ['fused: µs / round (one callback)', 'share'] if fused_total else []
    lines += [
        '',
        f"cProfile (thread CPU time) of a DRVS robot's service threads, {profile['callbacks']} callbacks at "
        '1×20 (µs per callback; the profiler inflates every call: the shares count)'
        + (
            f", and {fused['rounds']} fused 1×20 rounds of the same robot (µs per round: its ask and its one "
            'callback)'
            if fused_total
            else ''
        )
        + ':',
        '',
        table(header, rows),
        table(
            ['function (top by own time)', 'calls / callback', 'own µs', 'cumulative µs'],
            [
                [
                    t['function'],
                    t['calls_per_callback'],
                    t['tottime_us_per_callback'],
                    t['cumtime_us_per_callback'],
                ]
                for t in profile['top'][:8]
            ],
        ),
    ]
    return lines


def plot(ctx: Context, measured: dict, sizes) -> str:
    fig, axes, name = figure(ctx, f'{NAME}-bytes')
    labels = [f'{r}×{c}' for r, c in sizes]
    xs = list(range(len(sizes)))
    series = [
        ('DRVS one-shot', lambda e: e['drvs_oneshot']['total'], 'o-'),
        ('DRVS watch (1 period)', lambda e: e['drvs_watch']['total'], 's-'),
        ('DRVS fused', lambda e: e['drvs_fused']['total'], 'D-'),
        ('image sharing, render', lambda e: e.get('image_render', {}).get('total'), '^-'),
        ('image sharing, photo', lambda e: e.get('image_photo', {}).get('total'), 'v-'),
    ]
    for label, value, style in series:
        values = [value(measured[f'{r}x{c}']) for r, c in sizes]
        if all(v for v in values):
            axes.plot(xs, values, style, label=label)
    axes.plot(xs, [PAPER_KB[s][0] * 1000 for s in sizes], 'kx', markersize=10, label='paper: DRVS')
    axes.plot(xs, [PAPER_KB[s][2] * 1000 for s in sizes], 'k+', markersize=12, label='paper: image')
    axes.set_yscale('log')
    axes.set_xticks(xs, labels)
    axes.set_xlabel('robots × cameras')
    axes.set_ylabel('bytes per round (TCP payload)')
    axes.set_title('One round of vision on the wire')
    axes.legend(fontsize=8)
    axes.grid(True, which='both', alpha=0.3)
    return save(ctx, fig, name)
