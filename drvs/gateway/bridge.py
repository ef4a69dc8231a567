"""The rosbridge v2 WebSocket endpoint of ``drvs_gateway``: one :class:`Session` per connection on
aiohttp, the protocol's decisions in :mod:`drvs.gateway.rosbridge`, ROS behind a
:class:`BridgeBackend` (:mod:`drvs.ros.gateway_rosbridge` over ROS, a fake in the unit tests).

A client calls DRVS's services (``call_service``), hosts its own CallbackCoordinates service
(``advertise_service``: the backend serves a real ROS service for it, and each call DRVS makes to
it becomes a ``call_service`` to the client, answered by its ``service_response`` within
``~rosbridge_call_timeout``), and subscribes to DRVS's topics. Nothing waits without a deadline; a
slow client loses its oldest messages, not the gateway's memory. The contract: docs/gateway.md
("rosbridge endpoint").
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Protocol
from urllib.parse import urlsplit

from aiohttp import WSMsgType, web

from drvs.common.counters import Counters
from drvs.common.rate_limit import RateLimiter
from drvs.gateway.backend import NoServer
from drvs.gateway.params import GatewaySettings, is_loopback
from drvs.gateway.rosbridge import (
    DEFAULT_LEVEL,
    SUBPROTOCOL,
    Op,
    PendingCalls,
    ProtocolError,
    SendQueue,
    Throttle,
    bearer_from_protocols,
    parse,
    required_right,
    shown,
    status,
)
from drvs.gateway.rosjson import FieldError
from drvs.gateway.tokens import OPEN, Grant, Tokens, Unauthorized

__all__ = ['COUNTERS', 'BridgeBackend', 'ClientRefused', 'Rosbridge', 'Session']

logger = logging.getLogger('rosout.' + __name__)

AUTH_DEADLINE = 10.0
"""Seconds a connection that must authenticate has for its ``auth``; then it is closed."""
MAX_HOSTED = 16
"""Services one connection may host at once."""
MAX_SUBSCRIPTIONS = 16
"""Subscriptions one connection may hold at once."""
MAX_CALLS = 16
"""Calls to DRVS one connection may have in flight, and calls to its hosted services waiting."""
MAX_BAD_FRAMES = 1000
"""Refused frames in a row before the connection is closed (policy violation)."""
COUNTERS = (
    'connections',
    'frames',
    'refused',
    'calls',
    'client_calls',
    'client_timeouts',
    'dropped',
    'errors',
)


class ClientRefused(Exception):
    """A client-hosted service answered ``result: false``, or could not be asked; the message says why."""


class BridgeBackend(Protocol):
    """ROS as the endpoint sees it. Blocking methods run on worker threads; ``deliver`` and hosted
    services' ``serve`` are called on ROS's threads."""

    services: dict[str, str]
    """DRVS's services a client may call -> the token operation each needs."""
    topics: dict[str, str]
    """The topics a client may subscribe to -> their message type."""
    hostable: tuple[str, ...]
    """The service types a client may host (``drvs/CallbackCoordinates``)."""

    def call(self, service: str, args: dict[str, Any] | list[Any], timeout: float) -> dict[str, Any]:
        """Call ``service`` with the JSON ``args``; its response as JSON.

        :raises FieldError: ``args`` do not fit the request. :raises NoServer: no answer within ``timeout``.
        """

    def host(
        self, graph_name: str, service_type: str, serve: Callable[[dict[str, Any]], dict[str, Any]]
    ) -> Callable[[], None]:
        """Serve a ROS service ``graph_name`` whose requests (as JSON) ``serve`` answers (JSON values,
        or an exception: the ROS call fails); returns the function that withdraws it."""

    def subscribe(self, topic: str, deliver: Callable[[dict[str, Any]], None]) -> Callable[[], None]:
        """Hand every message of ``topic`` (as JSON) to ``deliver``; returns the function that stops."""


class Rosbridge:
    """The endpoint: :meth:`application` serves it at ``/``; :meth:`handle` serves it on any route.

    :param backend: ROS.
    :param settings: the gateway's settings (``rosbridge_*``, ``server_timeout``, ``ros_calls``).
    :param tokens: the tokens; None: every client may do everything (loopback only).
    :param limiter: the per-token request rate, shared with the HTTP routes (``call_service`` takes one).
    :param clock: monotonic seconds.
    """

    def __init__(
        self,
        backend: BridgeBackend,
        settings: GatewaySettings,
        tokens: Tokens | None,
        limiter: RateLimiter | None = None,
        clock: Callable[[], float] = time.monotonic,
        graph_prefix: str = '/drvs_gateway/rosbridge',
    ):
        self.backend = backend
        self.settings = settings
        self.tokens = tokens
        self.limiter = limiter or RateLimiter(settings.max_requests_per_s, settings.burst, clock)
        self.clock = clock
        self.graph_prefix = graph_prefix.rstrip('/')
        self.counters = Counters(COUNTERS)
        self.sessions: set[Session] = set()
        self.loop: asyncio.AbstractEventLoop | None = None
        self._executor = ThreadPoolExecutor(settings.ros_calls, thread_name_prefix='drvs-bridge')
        self._calls: asyncio.Semaphore | None = None
        self._numbers = 0

    def application(self) -> web.Application:
        app = web.Application()
        app.router.add_get('/', self.handle)
        app.on_startup.append(self.started)
        app.on_shutdown.append(self.shutdown)
        return app

    async def started(self, app: web.Application | None = None) -> None:
        self.loop = asyncio.get_running_loop()
        self._calls = asyncio.Semaphore(self.settings.ros_calls)

    async def shutdown(self, app: web.Application | None = None) -> None:
        await asyncio.gather(
            *(session.close('the gateway is shutting down') for session in list(self.sessions))
        )
        self._executor.shutdown(wait=False, cancel_futures=True)

    def owned_by(self, owner: str) -> int:
        return sum(1 for session in self.sessions if session.owner == owner)

    async def handle(self, request: web.Request) -> web.StreamResponse:
        """One WebSocket connection, from the upgrade to the close."""
        offered = request.headers.get('Sec-WebSocket-Protocol')
        origin = request.headers.get('Origin')
        if self.tokens is None and origin and not is_loopback(urlsplit(origin).hostname or ''):
            # Without tokens, a web page from elsewhere must not reach DRVS through a visitor's browser.
            return web.json_response(
                {
                    'error': 'FORBIDDEN',
                    'message': f'connections from the web page {origin[:100]} are refused',
                },
                status=403,
            )
        grant: Grant | None = OPEN if self.tokens is None else None
        if self.tokens is not None:
            token = bearer_from_protocols(offered)
            authorization = request.headers.get('Authorization') or (token and f'Bearer {token}')
            if authorization:
                try:
                    grant = self.tokens.authenticate(authorization)
                except Unauthorized as error:
                    return web.json_response({'error': 'UNAUTHORIZED', 'message': str(error)}, status=401)
        owner = self.owner(request, grant)
        if grant is not None and self.owned_by(owner) >= self.settings.rosbridge_max_clients:
            return self._too_many(owner)
        socket = web.WebSocketResponse(
            protocols=(SUBPROTOCOL,),
            heartbeat=self.settings.rosbridge_heartbeat,
            max_msg_size=self.settings.rosbridge_max_frame,
        )
        await socket.prepare(request)
        self._numbers += 1
        session = Session(self, socket, request, grant, self._numbers)
        self.sessions.add(session)
        self.counters.add(connections=1)
        try:
            await session.run()
        finally:
            try:
                await session.close()
            finally:
                self.sessions.discard(session)
        return socket

    def _too_many(self, owner: str) -> web.Response:
        return web.json_response(
            {
                'error': 'TOO_MANY_CONNECTIONS',
                'message': f'{owner} holds {self.settings.rosbridge_max_clients} connections '
                '(~rosbridge_max_clients)',
            },
            status=429,
        )

    @staticmethod
    def owner(request: web.Request, grant: Grant | None) -> str:
        if grant is not None and grant.name:
            return f'token {grant.name!r}'
        return f'address {request.remote}'

    async def call_drvs(self, service: str, args: Any, timeout: float) -> dict[str, Any]:
        """``backend.call`` on a worker thread, at most ``~ros_calls`` at once.

        :raises NoServer: no worker free within ``~server_timeout``, or from the call.
        """
        assert self._calls is not None and self.loop is not None, 'the endpoint has not started'
        try:
            await asyncio.wait_for(self._calls.acquire(), self.settings.server_timeout)
        except TimeoutError:
            raise NoServer(f'{self.settings.ros_calls} calls to DRVS in flight') from None
        try:
            return await self.loop.run_in_executor(self._executor, self.backend.call, service, args, timeout)
        finally:
            self._calls.release()

    async def in_thread(self, function: Callable[..., Any], *args: Any) -> Any:
        assert self.loop is not None
        return await self.loop.run_in_executor(self._executor, function, *args)


class Session:
    """One client connection: its grant, hosted services, subscriptions, pending calls and send queue."""

    def __init__(
        self,
        bridge: Rosbridge,
        socket: web.WebSocketResponse,
        request: web.Request,
        grant: Grant | None,
        number: int,
    ):
        self.bridge = bridge
        self.socket = socket
        self.request = request
        self.grant = grant
        self.number = number
        self.owner = bridge.owner(request, grant)
        self.level = DEFAULT_LEVEL
        self.queue = SendQueue(bridge.settings.rosbridge_queue)
        self.hosted: dict[str, tuple[str, Callable[[], None]]] = {}  # client's name -> (graph name, withdraw)
        self.subscriptions: dict[str, tuple[Throttle, Callable[[], None]]] = {}
        self.pending: PendingCalls[asyncio.Future] = PendingCalls(bridge.clock, MAX_CALLS)
        self.calls_in_flight = 0
        self.bad_frames = 0
        self._wake = asyncio.Event()
        self._tasks: set[asyncio.Task] = set()
        self._closed = False

    # -- the connection ----------------------------------------------------------------------
    async def run(self) -> None:
        writer = asyncio.get_running_loop().create_task(self._write_forever())
        deadline = None if self.grant is not None else self.bridge.clock() + AUTH_DEADLINE
        try:
            while not self.socket.closed:
                timeout = None if deadline is None else deadline - self.bridge.clock()
                if timeout is not None and timeout <= 0:
                    await self.socket.close(code=4001, message=b'no auth within the deadline')
                    return
                try:
                    message = await asyncio.wait_for(self.socket.receive(), timeout)
                except TimeoutError:
                    continue
                if message.type in (WSMsgType.CLOSE, WSMsgType.CLOSING, WSMsgType.CLOSED, WSMsgType.ERROR):
                    return
                self.bridge.counters.add(frames=1)
                if message.type == WSMsgType.TEXT:
                    await self.on_frame(message.data)
                else:
                    self.refuse(ProtocolError('frame', 'binary frames are not served: send JSON text'))
                if self.grant is not None:
                    deadline = None
                if self.bad_frames >= MAX_BAD_FRAMES:
                    await self.socket.close(code=1008, message=b'too many refused frames in a row')
                    return
        finally:
            writer.cancel()

    async def close(self, reason: str = '') -> None:
        """Withdraw the hosted services and subscriptions, fail the waiting calls, close the socket."""
        if self._closed:
            return
        self._closed = True
        for task in list(self._tasks):
            task.cancel()
        for call in self.pending.clear():
            if not call.waiter.done():
                call.waiter.set_exception(ClientRefused('the client disconnected'))
        subscriptions, self.subscriptions = list(self.subscriptions.values()), {}
        for _, stop in subscriptions:
            try:
                await self.bridge.in_thread(stop)
            except RuntimeError:  # the executor is gone: shutting down, ROS goes with the node
                pass
        hosted, self.hosted = list(self.hosted.values()), {}
        for _, withdraw in hosted:
            try:
                await self.bridge.in_thread(withdraw)
            except Exception:  # the master or the executor gone: the service goes with the node
                logger.exception('withdrawing a hosted service')
        if not self.socket.closed:
            await self.socket.close(message=reason.encode()[:120])

    def send(self, message: dict[str, Any]) -> None:
        """Queue a message for the client (the oldest dropped when the queue is full)."""
        if message.get('op') == 'status' and not shown(message['level'], self.level):
            return
        before = self.queue.dropped_total
        self.queue.put(json.dumps(message, allow_nan=False))
        self.bridge.counters.add(dropped=self.queue.dropped_total - before)
        self._wake.set()

    async def _write_forever(self) -> None:
        """Send the queue's frames; a client that takes none for two heartbeats is cut off."""
        patience = 2 * self.bridge.settings.rosbridge_heartbeat
        while not self.socket.closed:
            await self._wake.wait()
            self._wake.clear()
            for frame in self.queue.take(self.level):
                try:
                    await asyncio.wait_for(self.socket.send_str(frame), patience)
                except (TimeoutError, ConnectionResetError, RuntimeError):
                    if self.request.transport is not None:
                        self.request.transport.abort()
                    return

    def refuse(self, error: ProtocolError | FieldError, id: str | int | None = None) -> None:
        self.bad_frames += 1
        self.bridge.counters.add(refused=1)
        self.send(status('error', str(error), getattr(error, 'id', None) if id is None else id))

    def spawn(self, coroutine) -> None:
        task = asyncio.get_running_loop().create_task(coroutine)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # -- the operations ----------------------------------------------------------------------
    async def on_frame(self, text: str) -> None:
        try:
            op = parse(text)
        except ProtocolError as error:
            self.refuse(error)
            return
        try:
            if op.op == 'auth':
                self.authenticate(op)
            elif self.grant is None:
                raise ProtocolError('op', 'authenticate first: send {"op": "auth", "mac": TOKEN}', op.id)
            else:
                self.check_rights(op)
                await getattr(self, op.op)(op)
        except (ProtocolError, FieldError) as error:
            self.refuse(error, op.id)
            if op.op == 'call_service':
                self.send(self.call_failed(op, str(error)))
            return
        except Exception as error:  # a bug: logged with its traceback, the connection goes on
            self.bridge.counters.add(errors=1)
            logger.exception('rosbridge op %s failed', op.op)
            self.send(status('error', f'internal error ({type(error).__name__}); it is logged', op.id))
            return
        self.bad_frames = 0

    def check_rights(self, op: Op) -> None:
        assert self.grant is not None
        ops, algorithm = required_right(op, self.bridge.backend.services)
        if ops and not any(self.grant.may(right, algorithm) for right in ops):
            what = f' with the algorithm {algorithm.partition(":")[0]!r}' if algorithm else ''
            raise ProtocolError(
                'op',
                f'refused: token {self.grant.name!r} may not {op.op}{what} (it needs {" or ".join(ops)})',
                op.id,
            )

    def authenticate(self, op: Op) -> None:
        if self.bridge.tokens is None:
            return  # no tokens: every client is in already
        try:
            grant = self.bridge.tokens.authenticate(f'Bearer {op.mac}')
        except Unauthorized as error:
            raise ProtocolError('mac', str(error), op.id) from None
        owner = self.bridge.owner(self.request, grant)
        if self.grant is None and self.bridge.owned_by(owner) >= self.bridge.settings.rosbridge_max_clients:
            raise ProtocolError('mac', f'{owner} holds too many connections (~rosbridge_max_clients)', op.id)
        self.grant, self.owner = grant, owner

    async def set_level(self, op: Op) -> None:
        self.level = op.level

    @staticmethod
    def call_failed(op: Op, message: str) -> dict[str, Any]:
        answer = {'op': 'service_response', 'service': op.service, 'values': message, 'result': False}
        if op.id is not None:
            answer['id'] = op.id
        return answer

    async def call_service(self, op: Op) -> None:
        services = self.bridge.backend.services
        if op.service not in services:
            raise ProtocolError(
                'service', f'{op.service[:80]!r} is not served here (served: {", ".join(services)})', op.id
            )
        if self.calls_in_flight >= MAX_CALLS:
            raise ProtocolError(
                'op', f'{MAX_CALLS} calls of this connection in flight: wait for their answers', op.id
            )
        wait = self.bridge.limiter.take(self.owner)
        if wait:
            raise ProtocolError(
                'op',
                f'RATE_LIMITED: more than {self.bridge.settings.max_requests_per_s:g} calls/s '
                f'for {self.owner}; '
                f'retry in {wait:.2f} s',
                op.id,
            )
        args = op.fields.get('args') or {}
        callback = args.get('callback_service') if isinstance(args, dict) else None
        if isinstance(callback, str) and callback in self.hosted:
            args = {**args, 'callback_service': self.hosted[callback][0]}
        timeout = min(
            float(op.fields.get('timeout') or self.bridge.settings.server_timeout),
            self.bridge.settings.server_timeout,
        )
        self.calls_in_flight += 1
        self.spawn(self._call(op, args, timeout))

    async def _call(self, op: Op, args: Any, timeout: float) -> None:
        self.bridge.counters.add(calls=1)
        try:
            values = await self.bridge.call_drvs(op.service, args, timeout)
        except FieldError as error:
            self._call_failed(op, f'INVALID: args.{error}')
            return
        except NoServer as error:
            self._call_failed(op, f'NO_SERVER: {error}')
            return
        except Exception as error:  # a bug: logged with its traceback, the call answered
            self.bridge.counters.add(errors=1)
            logger.exception('rosbridge call_service %s failed', op.service)
            self._call_failed(op, f'INTERNAL: {type(error).__name__}; it is logged')
            return
        finally:
            self.calls_in_flight -= 1
        answer = {'op': 'service_response', 'service': op.service, 'values': values, 'result': True}
        if op.id is not None:
            answer['id'] = op.id
        self.send(answer)

    def _call_failed(self, op: Op, message: str) -> None:
        self.send(status('error', message, op.id))
        self.send(self.call_failed(op, message))

    async def advertise_service(self, op: Op) -> None:
        hostable = self.bridge.backend.hostable
        if op.type not in hostable:
            raise ProtocolError(
                'type', f'{op.type[:80]!r}: only {", ".join(hostable)} can be hosted here', op.id
            )
        name = op.service
        if not _is_name(name):
            raise ProtocolError('service', 'expected a ROS name: letters, digits, _ and /', op.id)
        if name in self.hosted:
            return  # advertised already: as rosbridge, nothing to do
        if len(self.hosted) >= MAX_HOSTED:
            raise ProtocolError('service', f'this connection hosts {MAX_HOSTED} services already', op.id)
        graph_name = f'{self.bridge.graph_prefix}/c{self.number}/{name.strip("/")}'
        loop = asyncio.get_running_loop()

        def serve(request: dict[str, Any]) -> dict[str, Any]:  # on a ROS thread
            future = asyncio.run_coroutine_threadsafe(self.call_client(name, request), loop)
            return future.result(self.bridge.settings.rosbridge_call_timeout + 1.0)

        withdraw = await self.bridge.in_thread(self.bridge.backend.host, graph_name, op.type, serve)
        if self._closed:
            await self.bridge.in_thread(withdraw)
            return
        self.hosted[name] = (graph_name, withdraw)

    async def unadvertise_service(self, op: Op) -> None:
        hosted = self.hosted.pop(op.service, None)
        if hosted is None:
            raise ProtocolError('service', f'{op.service[:80]!r} is not advertised by this connection', op.id)
        await self.bridge.in_thread(hosted[1])

    async def call_client(self, service: str, request: dict[str, Any]) -> dict[str, Any]:
        """DRVS's call to a hosted service: a ``call_service`` to the client, its ``service_response``
        within ``~rosbridge_call_timeout``.

        :raises ClientRefused: the client answered ``result: false``, or too many calls wait.
        :raises TimeoutError: no answer in time.
        """
        timeout = self.bridge.settings.rosbridge_call_timeout
        waiter = asyncio.get_running_loop().create_future()
        call = self.pending.add(service, timeout, waiter)
        if call is None:
            raise ClientRefused(f'{MAX_CALLS} calls to this client wait already')
        self.bridge.counters.add(client_calls=1)
        self.send({'op': 'call_service', 'id': call.id, 'service': service, 'args': request})
        try:
            return await asyncio.wait_for(waiter, timeout)
        except TimeoutError:
            self.bridge.counters.add(client_timeouts=1)
            raise TimeoutError(f'{service}: the client did not answer within {timeout:g} s') from None
        finally:
            self.pending.drop(call.id)

    async def service_response(self, op: Op) -> None:
        call = self.pending.answer(op.fields['id'], op.service)  # parse() checked it is there
        if call.waiter.done():
            return
        values = op.fields.get('values')
        if op.fields.get('result', True) is False:
            call.waiter.set_exception(
                ClientRefused(f'{op.service}: the client answered result false: {values}')
            )
        elif values is not None and not isinstance(values, dict):
            call.waiter.set_exception(ClientRefused(f'{op.service}: values: expected an object'))
            raise ProtocolError('values', 'expected an object (the response fields)', op.id)
        else:
            call.waiter.set_result(values or {})

    async def subscribe(self, op: Op) -> None:
        topics = self.bridge.backend.topics
        topic = op.topic
        if topic not in topics:
            raise ProtocolError(
                'topic', f'{topic[:80]!r} is not served here (served: {", ".join(topics)})', op.id
            )
        if op.fields.get('type') not in (None, topics[topic]):
            raise ProtocolError('type', f'{topic} carries {topics[topic]}', op.id)
        if topic in self.subscriptions:
            self.subscriptions[topic][0].milliseconds = float(op.fields.get('throttle_rate') or 0)
            return
        if len(self.subscriptions) >= MAX_SUBSCRIPTIONS:
            raise ProtocolError(
                'topic', f'this connection holds {MAX_SUBSCRIPTIONS} subscriptions already', op.id
            )
        throttle = Throttle(float(op.fields.get('throttle_rate') or 0))
        loop = asyncio.get_running_loop()

        def deliver(message: dict[str, Any]) -> None:  # on a ROS thread
            try:
                loop.call_soon_threadsafe(self._publish, topic, message)
            except RuntimeError:  # the loop closed: shutting down
                pass

        self.subscriptions[topic] = (throttle, lambda: None)
        stop = await self.bridge.in_thread(self.bridge.backend.subscribe, topic, deliver)
        if self._closed or self.subscriptions.get(topic, (None,))[0] is not throttle:
            await self.bridge.in_thread(stop)  # closed or unsubscribed meanwhile
        else:
            self.subscriptions[topic] = (throttle, stop)

    def _publish(self, topic: str, message: dict[str, Any]) -> None:
        subscription = self.subscriptions.get(topic)
        if subscription is not None and subscription[0].due(self.bridge.clock()):
            self.send({'op': 'publish', 'topic': topic, 'msg': message})

    async def unsubscribe(self, op: Op) -> None:
        subscription = self.subscriptions.pop(op.topic, None)
        if subscription is not None:
            await self.bridge.in_thread(subscription[1])


def _is_name(name: str) -> bool:
    parts = name.strip('/').split('/')
    return 0 < len(name) <= 200 and all(
        part and part.replace('_', '').isalnum() and part.isascii() and not part[0].isdigit()
        for part in parts
    )
