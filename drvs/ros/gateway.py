"""The ``drvs_gateway`` node: the gateway's HTTP application (:mod:`drvs.gateway.app`) on its own
thread and event loop, beside rospy, as a ROS client of DRVS like any robot.

It hosts a CallbackCoordinates service for every request and watch it sends, calls the server's
DetectObjectBoundary and WatchObjectBoundary with a deadline each
(:class:`drvs.ros.service_client.ServiceClient`), and keeps the newest ``/drvs/registry``,
``/drvs/objects`` and ``/diagnostics`` for the read routes. For the floor-plan page it also follows
every robot it finds on the master (a publisher of ``/<robot>/status``, drvs/RobotStatus) with its
``/<robot>/path``. Beside it, on ``~rosbridge_bind``, the rosbridge endpoint
(:mod:`drvs.gateway.bridge` with :mod:`drvs.ros.gateway_rosbridge`). The contract: docs/gateway.md;
the parameters: docs/nodes/drvs_gateway.md.
"""

from __future__ import annotations

import asyncio
import math
import socket
import threading
import time
from typing import Any

import rospy
from aiohttp import web
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Path

from drvs.common.guard import SHUTDOWN
from drvs.common.settings import ParamError
from drvs.common.status import name as status_name
from drvs.gateway.app import Gateway
from drvs.gateway.backend import Ack, NoServer
from drvs.gateway.body import DetectBody, WatchBody
from drvs.gateway.bridge import Rosbridge
from drvs.gateway.guard import GuardedRunner
from drvs.gateway.live import MAX_ROBOTS
from drvs.gateway.params import GatewaySettings, is_loopback, split_bind
from drvs.gateway.tokens import Tokens, load_tokens
from drvs.msg import BoundingBox, Registry, RobotStatus, TrackedObjects
from drvs.ros.conversions import polygon_to_points
from drvs.ros.gateway_rosbridge import RosBridgeBackend
from drvs.ros.messages import registry_to_dict, robot_status_to_dict
from drvs.ros.node import NodeScaffold
from drvs.ros.service_client import ServiceCallError, ServiceClient
from drvs.srv import (
    CallbackCoordinates,
    CallbackCoordinatesResponse,
    DetectObjectBoundary,
    DetectObjectBoundaryRequest,
    WatchObjectBoundary,
    WatchObjectBoundaryRequest,
)

__all__ = ['GatewayNode', 'bind_socket', 'callback_to_dict', 'object_to_dict']

MAX_DIAGNOSTICS = 512
"""Statuses of ``/diagnostics`` kept (one per name, DRVS's nodes only)."""
STOP_TIMEOUT = 5.0
"""Seconds the HTTP thread is given to close its connections and withdraw its watches."""
DIAGNOSTIC_LEVELS = {0: 'OK', 1: 'WARN', 2: 'ERROR', 3: 'STALE'}
ROBOT_LOOKUP = 2.0
"""Seconds between two looks on the master for new robots (publishers of drvs/RobotStatus)."""
ROBOT_FIELDS = ('state', 'reason', 'stamp', 'distance_to_goal', 'position', 'heading', 'goal')
"""What the floor-plan page gets of a robot's status."""


def _number(value: float) -> float | None:
    """JSON has no NaN or infinity: None for them."""
    return value if math.isfinite(value) else None


def object_to_dict(detected) -> dict[str, Any]:
    """drvs/DetectedObject -> the gateway's JSON object (docs/gateway.md, "Objects")."""
    box = detected.bounding_box
    velocity = detected.velocity
    return {
        'boundary': [[_number(x), _number(y)] for x, y in polygon_to_points(detected.boundary)],
        'bounding_box': {
            'min_x': _number(box.min_x),
            'min_y': _number(box.min_y),
            'max_x': _number(box.max_x),
            'max_y': _number(box.max_y),
        },
        'label': detected.label,
        'height': _number(detected.height),
        'clearance': _number(detected.clearance),
        'track_id': detected.track_id,
        'confidence': _number(detected.confidence),
        'velocity': [_number(velocity.x), _number(velocity.y), _number(velocity.z)],
        'stationary': detected.stationary,
        'seen_by': list(detected.seen_by),
    }


def callback_to_dict(request) -> dict[str, Any]:
    """A CallbackCoordinates request -> the gateway's JSON callback; a fused one with its status."""
    data: dict[str, Any] = {
        'vision_system': request.vision_system,
        'stamp': request.stamp.to_sec(),
        'algorithm': request.algorithm,
        'objects': [object_to_dict(detected) for detected in request.objects],
        'fused': request.fused,
    }
    if request.fused:
        data.update(
            status='OK' if request.status == request.OK else status_name(request.status),
            message=request.message,
            answered=list(request.answered),
            refused=list(request.refused),
            missing=list(request.missing),
            gone=list(request.gone),
        )
    return data


def bind_socket(settings: GatewaySettings, tokens: Tokens | None, param: str = 'bind') -> socket.socket:
    """The listening socket of ``~bind`` (or the parameter ``param``: ``rosbridge_bind``), bound now,
    so that a port in use or a non-loopback address without ``~tokens`` stops the node with one
    message (exit 2).

    :raises ParamError: the address not loopback without ``~tokens``.
    :raises OSError: the address cannot be bound.
    """
    address = getattr(settings, param)
    host, port = split_bind(param, address)
    if tokens is None and not is_loopback(host):
        raise ParamError(
            param,
            f'{host} is not a loopback address, and without ~tokens anyone who reaches it could use DRVS: '
            'give a tokens file (drvs_token add NAME --file FILE, then _tokens:=FILE) or bind 127.0.0.1',
        )
    family = socket.AF_INET6 if ':' in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(128)
    except OSError as error:
        sock.close()
        raise OSError(error.errno, f'~{param} {address}: {error.strerror}') from None
    sock.setblocking(False)
    return sock


class RosDrvs:
    """DRVS over ROS for the gateway (:class:`drvs.gateway.backend.Drvs`): one pair of service
    clients per worker thread, the topics' newest messages under ``_lock``."""

    def __init__(self, settings: GatewaySettings, callback_service: str):
        self.settings = settings
        self.callback_service = callback_service
        self._local = threading.local()
        self._clients: list[ServiceClient] = []
        self._lock = threading.Lock()  # guards _clients, _registry, _objects, _diagnostics, _robots
        self._registry: list[dict[str, Any]] | None = None
        self._objects: dict[str, Any] | None = None
        self._diagnostics: dict[str, tuple[dict[str, Any], float]] = {}
        self._robots: dict[str, dict[str, Any]] = {}

    def _client(self, service: str, service_class) -> ServiceClient:
        clients = self._local.__dict__.setdefault('clients', {})
        if service not in clients:
            clients[service] = ServiceClient(
                f'{self.settings.server}/{service}', service_class, self.settings.server_timeout
            )
            with self._lock:
                self._clients.append(clients[service])
        return clients[service]

    def close(self) -> None:
        with self._lock:
            clients, self._clients = self._clients, []
        for client in clients:
            client.close()

    def _call(self, service: str, service_class, request):
        try:
            return self._client(service, service_class).call(request)
        except ServiceCallError as error:
            raise NoServer(str(error)) from None

    def detect(self, body: DetectBody, request_id: str) -> Ack:
        request = DetectObjectBoundaryRequest(
            algorithm=body.algorithm,
            region_of_interest=BoundingBox(*body.region),
            callback_service=self.callback_service,
            request_id=request_id,
            fused=body.fused,
        )
        reply = self._call('detect_object_boundary', DetectObjectBoundary, request)
        return Ack(reply.status, reply.message, reply.vision_systems, reply.retry_after)

    def watch(self, body: WatchBody, request_id: str, duration: float) -> Ack:
        request = WatchObjectBoundaryRequest(
            algorithm=body.algorithm,
            region_of_interest=BoundingBox(*body.region),
            callback_service=self.callback_service,
            request_id=request_id,
            period=body.period,
            duration=duration,
            changes_only=body.changes_only,
            fused=body.fused,
        )
        reply = self._call('watch_object_boundary', WatchObjectBoundary, request)
        return Ack(
            reply.status, reply.message, reply.vision_systems, reply.retry_after, reply.period, reply.duration
        )

    # -- topics ----------------------------------------------------------------------------------
    def on_registry(self, msg: Registry) -> None:
        entries = [
            {
                'name': entry['service_name'],
                'provider': entry['provider'],
                'field_of_view': entry['field_of_view'],
                'algorithms': entry['algorithms'],
            }
            for entry in registry_to_dict(msg)['vision_systems']
        ]
        with self._lock:
            self._registry = entries

    def on_objects(self, msg: TrackedObjects) -> None:
        objects = []
        for algorithm, detected in zip(msg.algorithms, msg.objects, strict=False):
            objects.append({'algorithm': algorithm, **object_to_dict(detected)})
        with self._lock:
            self._objects = {
                'stamp': msg.header.stamp.to_sec(),
                'algorithms': sorted(set(msg.algorithms)),
                'objects': objects,
            }

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        now = time.monotonic()
        with self._lock:
            for status in msg.status:
                if not status.name.startswith('drvs: '):
                    continue
                if status.name not in self._diagnostics and len(self._diagnostics) >= MAX_DIAGNOSTICS:
                    continue
                self._diagnostics[status.name] = (
                    {
                        'name': status.name,
                        'level': DIAGNOSTIC_LEVELS.get(status.level, str(status.level)),
                        'message': status.message,
                        'hardware_id': status.hardware_id,
                        'values': {value.key: value.value for value in status.values},
                    },
                    now,
                )

    def on_robot_status(self, robot: str, msg: RobotStatus) -> None:
        status = robot_status_to_dict(msg)
        view = {key: status[key] for key in ROBOT_FIELDS}
        with self._lock:
            self._robots[robot] = {**self._robots.get(robot, {}), 'status': view}

    def on_robot_path(self, robot: str, msg: Path) -> None:
        points = [[pose.pose.position.x, pose.pose.position.y] for pose in msg.poses]
        points = [[_number(x), _number(y)] for x, y in points]
        with self._lock:
            self._robots[robot] = {**self._robots.get(robot, {}), 'path': points}

    def robots(self) -> dict[str, dict[str, Any]]:
        with self._lock:
            return dict(self._robots)

    def registry(self) -> list[dict[str, Any]] | None:
        with self._lock:
            return self._registry

    def objects(self) -> dict[str, Any] | None:
        with self._lock:
            return self._objects

    def diagnostics(self) -> list[dict[str, Any]]:
        now = time.monotonic()
        with self._lock:
            return [
                {**status, 'age': round(now - received, 3)}
                for _, (status, received) in sorted(self._diagnostics.items())
            ]


class GatewayNode:
    """``drvs_gateway``: :meth:`start` serves HTTP on the socket :func:`bind_socket` made;
    :meth:`stop` (on shutdown) ends every watch and closes the server."""

    def __init__(self, settings: GatewaySettings):
        self.settings = settings
        self.tokens = load_tokens(settings.tokens) if settings.tokens else None
        self.sock = bind_socket(settings, self.tokens)
        self.node = NodeScaffold(None)
        self.drvs = RosDrvs(settings, f'{rospy.get_name()}/callback_coordinates')
        self.gateway = Gateway(self.drvs, settings, self.tokens)
        self.bridge_sock = (
            bind_socket(settings, self.tokens, 'rosbridge_bind') if settings.rosbridge_on else None
        )
        self.bridge_backend = RosBridgeBackend(settings)
        self.bridge = Rosbridge(
            self.bridge_backend,
            settings,
            self.tokens,
            self.gateway.limiter,
            graph_prefix=f'{rospy.get_name()}/rosbridge',
        )
        self.loop: asyncio.AbstractEventLoop | None = None
        self.ready = threading.Event()
        self._stop: asyncio.Event | None = None
        self._http: threading.Thread | None = None

    @property
    def url(self) -> str:
        host, port = self.sock.getsockname()[:2]
        return f'http://[{host}]:{port}' if ':' in host else f'http://{host}:{port}'

    @property
    def rosbridge_url(self) -> str:
        """``ws://HOST:PORT`` of the rosbridge endpoint; empty without one."""
        if self.bridge_sock is None:
            return ''
        host, port = self.bridge_sock.getsockname()[:2]
        return f'ws://[{host}]:{port}' if ':' in host else f'ws://{host}:{port}'

    def start(self) -> None:
        self.node.start()
        self._http = self.node.spawn(self._serve, 'http', policy=SHUTDOWN)
        if not self.ready.wait(10.0):
            raise RuntimeError('the HTTP server did not start within 10 s')
        rospy.Service(self.drvs.callback_service, CallbackCoordinates, self._on_callback)
        server = self.settings.server
        rospy.Subscriber(f'{server}/registry', Registry, self.drvs.on_registry, queue_size=1)
        rospy.Subscriber(f'{server}/objects', TrackedObjects, self.drvs.on_objects, queue_size=1)
        rospy.Subscriber('/diagnostics', DiagnosticArray, self.drvs.on_diagnostics, queue_size=10)
        self._robots: set[str] = set()
        self._follow_robots()
        self.node.every(ROBOT_LOOKUP, self._follow_robots, 'robots')
        rospy.set_param('~url', self.url)
        rospy.set_param('~rosbridge_url', self.rosbridge_url)
        rospy.loginfo(
            '%s: listening on %s%s (%s)',
            rospy.get_name(),
            self.url,
            f' and {self.rosbridge_url} (rosbridge)' if self.rosbridge_url else '',
            f'{len(self.tokens)} token(s)' if self.tokens is not None else 'no tokens: loopback only',
        )

    def _follow_robots(self) -> None:
        """Subscribe to the status and path of every robot on the master not yet followed."""
        try:
            topics = rospy.get_published_topics()
        except Exception as error:  # the master is away: try again at the next look
            self.node.log_throttled('robots', rospy.logwarn, 'looking for robots: %s', error)
            return
        for topic, kind in topics:
            robot = topic.removesuffix('/status').lstrip('/')
            if kind != RobotStatus._type or not topic.endswith('/status') or robot in self._robots:
                continue
            if len(self._robots) >= MAX_ROBOTS:
                return
            self._robots.add(robot)
            rospy.Subscriber(
                topic, RobotStatus, lambda msg, r=robot: self.drvs.on_robot_status(r, msg), queue_size=1
            )
            rospy.Subscriber(
                f'/{robot}/path', Path, lambda msg, r=robot: self.drvs.on_robot_path(r, msg), queue_size=1
            )

    def _on_callback(self, request) -> CallbackCoordinatesResponse:
        loop = self.loop
        if loop is not None and not loop.is_closed():
            data = callback_to_dict(request)
            try:
                loop.call_soon_threadsafe(self.gateway.deliver, request.request_id, data)
            except RuntimeError:  # the loop closed meanwhile: shutting down
                pass
        return CallbackCoordinatesResponse()

    def _serve(self) -> None:
        """The HTTP thread: an event loop of its own until :meth:`stop`."""
        loop = self.loop = asyncio.new_event_loop()
        try:
            loop.run_until_complete(self._run())
        finally:
            loop.close()

    async def _run(self) -> None:
        self._stop = asyncio.Event()
        guard = {
            'handle_signals': False,
            'access_log': None,
            'head_timeout': self.settings.request_timeout,
            'keepalive_timeout': self.settings.request_timeout,
            'max_per_address': self.settings.max_connections_per_address,
        }
        runner = GuardedRunner(self.gateway.application(), **guard)
        bridge = GuardedRunner(self.bridge.application(), **guard)
        await runner.setup()
        await bridge.setup()
        try:
            await web.SockSite(runner, self.sock, shutdown_timeout=1.0).start()
            if self.bridge_sock is not None:
                await web.SockSite(bridge, self.bridge_sock, shutdown_timeout=1.0).start()
            self.ready.set()
            await self._stop.wait()
        finally:
            await bridge.cleanup()
            await runner.cleanup()

    def stop(self) -> None:
        """End the watches, close the HTTP server and the DRVS connections (within :data:`STOP_TIMEOUT`)."""
        self.node.stop()
        loop, stop = self.loop, self._stop
        if loop is not None and stop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(stop.set)
            except RuntimeError:
                pass
        if self._http is not None and self._http is not threading.current_thread():
            self._http.join(STOP_TIMEOUT)
        self.drvs.close()
        self.bridge_backend.close()
