"""The gateway's aiohttp application: the routes of :data:`drvs.gateway.routes.ROUTES` wired to a
:class:`~drvs.gateway.backend.Drvs`, with tokens, per-token limits and watches.

:meth:`Gateway.application` builds the ``aiohttp.web.Application``; other endpoints (the
rosbridge WebSocket, the floor-plan page) extend it with routes of their own. No ROS: the ROS glue
(:mod:`drvs.ros.gateway`) gives it a DRVS client and hands it every callback with
:meth:`Gateway.deliver` on the event loop's thread. The contract: docs/gateway.md.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import logging
import secrets
import time
from collections.abc import Awaitable, Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from aiohttp import web
from shapely.geometry import Polygon

from drvs.common.counters import Counters
from drvs.common.rate_limit import RateLimiter
from drvs.common.status import ACCEPTED, INVALID, UNSUPPORTED, is_temporary, name
from drvs.common.validation import region_geometry
from drvs.gateway import answers, sse
from drvs.gateway.answers import HttpAnswer
from drvs.gateway.backend import Ack, Drvs, NoServer
from drvs.gateway.body import (
    BadRequest,
    DetectBody,
    WatchBody,
    detect_body,
    json_body,
    region_query,
    watch_body,
)
from drvs.gateway.page import FloorPlan
from drvs.gateway.params import GatewaySettings
from drvs.gateway.routes import ROUTES, Route, openapi
from drvs.gateway.tokens import OPEN, Forbidden, Grant, Tokens, Unauthorized
from drvs.gateway.watches import END, GatewayWatch, Listener, WatchHub

__all__ = ['COUNTERS', 'Gateway', 'TICK']

logger = logging.getLogger('rosout.' + __name__)

TICK = 0.25
"""Seconds between two looks at the watches (renewals, withdrawals)."""
DISCONNECT_CHECK = 0.5
"""Seconds between two looks, on an idle event stream, whether its client went away."""
MAX_CALLBACKS = 1000
"""Callbacks one ``POST /v1/detect`` answer holds at most."""
COUNTERS = ('requests', 'refused', 'callbacks', 'events', 'dropped', 'no_server', 'errors')

Handler = Callable[[web.Request, Grant], Awaitable[web.StreamResponse]]


def respond(answer: HttpAnswer) -> web.Response:
    return web.json_response(answer.body, status=answer.status, headers=dict(answer.headers))


class _Collector:
    """The callbacks of one ``POST /v1/detect``, as they come."""

    def __init__(self) -> None:
        self.callbacks: list[dict[str, Any]] = []
        self.arrived = asyncio.Event()

    def add(self, data: dict[str, Any]) -> None:
        if len(self.callbacks) < MAX_CALLBACKS:
            self.callbacks.append(data)
        self.arrived.set()

    async def wait(self, count: int, seconds: float, clock: Callable[[], float]) -> None:
        """Until ``count`` callbacks came or ``seconds`` passed."""
        deadline = clock() + seconds
        while len(self.callbacks) < count and (left := deadline - clock()) > 0:
            self.arrived.clear()
            try:
                await asyncio.wait_for(self.arrived.wait(), left)
            except TimeoutError:
                return


class Gateway:
    """The HTTP side of ``drvs_gateway``.

    :param drvs: the DRVS client.
    :param settings: the node's settings.
    :param tokens: the tokens; None: every client may do everything (loopback only).
    :param clock: monotonic seconds (the watches' renewals and linger, the rate limit).
    """

    def __init__(
        self,
        drvs: Drvs,
        settings: GatewaySettings,
        tokens: Tokens | None,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.drvs = drvs
        self.settings = settings
        self.tokens = tokens
        self.clock = clock
        self.hub = WatchHub(
            clock,
            settings.watch_duration,
            settings.watch_linger,
            settings.resume_buffer,
            settings.listener_queue,
        )
        self.limiter = RateLimiter(settings.max_requests_per_s, settings.burst, clock)
        self.counters = Counters(COUNTERS)
        self._pending: dict[str, _Collector] = {}
        self._ids = itertools.count(1)
        self._run = secrets.token_hex(3)  # request ids differ from a restarted gateway's
        self._executor = ThreadPoolExecutor(settings.ros_calls, thread_name_prefix='drvs-call')
        self._calls: asyncio.Semaphore | None = None
        self._tasks: set[asyncio.Task] = set()
        self.floor_plan = FloorPlan(self)

    # -- the application -----------------------------------------------------------------------
    def application(self) -> web.Application:
        """A new aiohttp application serving :data:`ROUTES` (add routes to it before it runs)."""
        app = web.Application(client_max_size=self.settings.max_body, middlewares=[self._errors])
        handlers: dict[str, Handler] = {
            'detect': self.detect,
            'open_watch': self.open_watch,
            'watch_events': self.watch_events,
            'close_watch': self.close_watch,
            'vision_systems': self.vision_systems,
            'coverage': self.coverage,
            'objects': self.objects,
            'health': self.health,
            'openapi': self.openapi,
            **self.floor_plan.handlers(),
        }
        for route in ROUTES:
            app.router.add_route(
                route.method, route.path, self._guarded(route, handlers[route.name]), name=route.name
            )
        app.on_startup.append(self._started)
        app.on_startup.append(self.floor_plan.started)
        app.on_shutdown.append(self._shutdown)
        return app

    async def _started(self, app: web.Application) -> None:
        self._calls = asyncio.Semaphore(self.settings.ros_calls)
        self._spawn(self._tick_forever())

    async def _shutdown(self, app: web.Application) -> None:
        """End every watch (its streams get ``end``); withdraw the DRVS watches, each within its deadline."""
        ended = [self.hub.end(watch.id, 'the gateway is shutting down') for watch in self.hub]
        await asyncio.gather(*(self._withdraw(watch) for watch in ended if watch), return_exceptions=True)
        for task in list(self._tasks):
            task.cancel()
        self._executor.shutdown(wait=False, cancel_futures=True)

    def _spawn(self, coroutine) -> None:
        task = asyncio.get_running_loop().create_task(coroutine)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    @web.middleware
    async def _errors(self, request: web.Request, handler) -> web.StreamResponse:
        try:
            return await handler(request)
        except BadRequest as error:
            return respond(answers.bad_request(error.field, str(error)))
        except Forbidden as error:
            return respond(answers.forbidden(str(error)))
        except web.HTTPException as error:  # aiohttp's own: 404, 405, 413
            if error.status < 400:
                raise
            code = error.reason.upper().replace(' ', '_')
            return respond(
                answers.error(
                    error.status, code, f'{error.status} {error.reason}: {request.method} {request.path}'
                )
            )
        except (asyncio.CancelledError, ConnectionResetError):
            raise
        except Exception as error:  # a bug: logged with its traceback, a clean 500 for the client
            self.counters.add(errors=1)
            logger.exception('%s %s failed', request.method, request.path)
            return respond(
                answers.error(500, 'INTERNAL', f'internal error ({type(error).__name__}); it is logged')
            )

    def _guarded(
        self, route: Route, handler: Handler
    ) -> Callable[[web.Request], Awaitable[web.StreamResponse]]:
        """``handler`` behind the token check and the per-token rate limit of ``route``."""

        async def guarded(request: web.Request) -> web.StreamResponse:
            self.counters.add(requests=1)
            if route.op is None:
                return await handler(request, OPEN)
            grant = OPEN
            if route.ticket:  # the rights of the token that asked for the ticket
                grant = self.floor_plan.tickets.redeem(request.query.get('ticket'))
                if grant is None:
                    return self._refused(
                        answers.unauthorized(
                            'no ticket, or one used or expired: POST /v1/tickets for a new one'
                        )
                    )
                grant.check(route.op)
            elif self.tokens is not None:
                try:
                    grant = self.tokens.authenticate(request.headers.get('Authorization'))
                except Unauthorized as error:
                    return self._refused(answers.unauthorized(str(error)))
                grant.check(route.op)
            wait = self.limiter.take(self._owner(request, grant))
            if wait:
                return self._refused(
                    answers.error(
                        429,
                        'RATE_LIMITED',
                        f'more than {self.settings.max_requests_per_s:g} requests/s '
                        f'(burst {self.settings.burst}) for this token',
                        wait,
                    )
                )
            return await handler(request, grant)

        return guarded

    def _refused(self, answer: HttpAnswer) -> web.Response:
        self.counters.add(refused=1)
        return respond(answer)

    @staticmethod
    def _owner(request: web.Request, grant: Grant) -> str:
        """Whose limits a request counts against: its token's name, or without tokens its address."""
        return grant.name or f'address {request.remote}'

    # -- calls to DRVS -------------------------------------------------------------------------
    def _request_id(self, kind: str) -> str:
        return f'gateway-{self._run}-{kind}{next(self._ids)}'

    async def _call(self, function: Callable[..., Ack], *args: Any) -> Ack:
        """``function(*args)`` on a worker thread, at most ``~ros_calls`` at once.

        :raises NoServer: from the call (its own deadline), or no worker free within ``~server_timeout``.
        """
        assert self._calls is not None, 'the application has not started'
        timeout = self.settings.server_timeout
        try:
            await asyncio.wait_for(self._calls.acquire(), timeout)
        except TimeoutError:
            raise NoServer(f'{self.settings.ros_calls} calls to DRVS in flight for {timeout:g} s') from None
        try:
            return await asyncio.get_running_loop().run_in_executor(self._executor, function, *args)
        finally:
            self._calls.release()

    def _no_server(self, error: NoServer) -> web.Response:
        self.counters.add(no_server=1)
        return self._refused(answers.no_server(str(error), self.settings.unavailable_retry_after))

    def _drvs_refusal(self, ack: Ack) -> web.Response:
        registry = self.drvs.registry() or []
        available = {algorithm for entry in registry for algorithm in entry['algorithms']}
        return self._refused(answers.refusal(ack.status, ack.message, ack.retry_after, available))

    def deliver(self, request_id: str, data: dict[str, Any]) -> None:
        """A callback to the gateway's callback service (call on the event loop's thread)."""
        self.counters.add(callbacks=1)
        collector = self._pending.get(request_id)
        if collector is not None:
            collector.add(data)
        elif self.hub.deliver(request_id, data):
            self.counters.add(events=1)

    # -- handlers ------------------------------------------------------------------------------
    async def _body(self, request: web.Request) -> dict[str, Any]:
        if request.content_length is not None and request.content_length > self.settings.max_body:
            raise web.HTTPRequestEntityTooLarge(
                max_size=self.settings.max_body, actual_size=request.content_length
            )
        try:
            data = await asyncio.wait_for(request.read(), self.settings.request_timeout)
        except TimeoutError:
            raise web.HTTPRequestTimeout(text='the body did not arrive within ~request_timeout') from None
        return json_body(data)

    async def detect(self, request: web.Request, grant: Grant) -> web.StreamResponse:
        body: DetectBody = detect_body(await self._body(request), self.settings.max_wait)
        grant.check('detect', body.algorithm)
        request_id = self._request_id('d')
        collector = self._pending[request_id] = _Collector()
        try:
            try:
                ack = await self._call(self.drvs.detect, body, request_id)
            except NoServer as error:
                return self._no_server(error)
            if ack.status != ACCEPTED:
                return self._drvs_refusal(ack)
            expected = 1 if body.fused else ack.vision_systems  # a fused request is answered once, always
            if expected:
                await collector.wait(expected, body.wait, self.clock)
            return web.json_response(
                {
                    'status': name(ack.status),
                    'message': ack.message,
                    'request_id': request_id,
                    'vision_systems': ack.vision_systems,
                    'callbacks': collector.callbacks,
                }
            )
        finally:
            del self._pending[request_id]

    async def open_watch(self, request: web.Request, grant: Grant) -> web.StreamResponse:
        body: WatchBody = watch_body(await self._body(request))
        grant.check('watch', body.algorithm)
        owner = self._owner(request, grant)
        if len(self.hub) >= self.settings.max_watches:
            return self._refused(
                answers.error(503, 'BUSY', f'{self.settings.max_watches} watches open (~max_watches)', 1.0)
            )
        if self.hub.owned_by(owner) >= self.settings.max_watches_per_token:
            return self._refused(
                answers.error(
                    429,
                    'TOO_MANY_WATCHES',
                    f'this token holds {self.settings.max_watches_per_token} watches open '
                    '(~max_watches_per_token): DELETE one first',
                    self.settings.watch_linger,
                )
            )
        watch_id = secrets.token_urlsafe(12)
        # Open before asking: the first callbacks may come before the acknowledgement is read.
        watch = self.hub.open(watch_id, self._request_id('w'), owner, body)
        try:
            ack = await self._call(self.drvs.watch, body, watch.request_id, self.settings.watch_duration)
        except NoServer as error:
            self.hub.end(watch_id, 'not opened')
            return self._no_server(error)
        if ack.status != ACCEPTED:
            self.hub.end(watch_id, 'not opened')
            return self._drvs_refusal(ack)
        self.hub.renewed(watch, self._granted(ack))
        events = f'/v1/watches/{watch_id}/events'
        return web.json_response(
            {'id': watch_id, 'events': events, 'vision_systems': ack.vision_systems, 'period': ack.period},
            status=201,
            headers={'Location': events},
        )

    @staticmethod
    def _granted(ack: Ack) -> dict[str, Any]:
        return {'period': ack.period, 'duration': ack.duration, 'vision_systems': ack.vision_systems}

    def _own_watch(self, request: web.Request, grant: Grant) -> GatewayWatch:
        """The watch of the path, if this token holds it (another token's is as good as absent)."""
        watch = self.hub.get(request.match_info['id'])
        if watch is None or watch.owner != self._owner(request, grant):
            raise web.HTTPNotFound()
        return watch

    async def watch_events(self, request: web.Request, grant: Grant) -> web.StreamResponse:
        watch = self._own_watch(request, grant)
        try:
            last = sse.last_event_id(request.headers.get('Last-Event-ID'))
        except ValueError as error:
            raise BadRequest('Last-Event-ID', str(error)) from None
        if len(watch.listeners) >= self.settings.max_listeners:
            return self._refused(
                answers.error(
                    429,
                    'TOO_MANY_LISTENERS',
                    f'{self.settings.max_listeners} streams are open on this watch (~max_listeners)',
                    self.settings.keep_alive,
                )
            )
        listener = self.hub.listen(watch.id, last)
        wake = asyncio.Event()
        listener.wake = wake.set
        stream = web.StreamResponse(
            headers={
                'Content-Type': 'text/event-stream',
                'Cache-Control': 'no-cache',
                'X-Accel-Buffering': 'no',
            }
        )
        try:
            await stream.prepare(request)
            await self._write(request, stream, sse.RETRY)
            await self._stream(request, stream, listener, wake)
        except ConnectionResetError:  # the client went away
            pass
        finally:
            self.hub.leave(listener)
        return stream

    async def _stream(
        self, request: web.Request, stream: web.StreamResponse, listener: Listener, wake: asyncio.Event
    ) -> None:
        """Write ``listener``'s events to ``stream`` until the watch ends; keep-alives when idle."""
        while True:
            wake.clear()
            dropped = listener.dropped
            for event in listener.take():
                await self._write(request, stream, sse.encode(event))
                if event.kind == END:
                    return
            self.counters.add(dropped=dropped)
            idle = self.clock()
            while not wake.is_set():
                if request.transport is None or request.transport.is_closing():
                    return  # the client went away (aiohttp 3.8 does not cancel the handler)
                if self.clock() - idle >= self.settings.keep_alive:
                    await self._write(request, stream, sse.KEEP_ALIVE)
                    idle = self.clock()
                try:
                    await asyncio.wait_for(wake.wait(), DISCONNECT_CHECK)
                except TimeoutError:
                    pass

    async def _write(self, request: web.Request, stream: web.StreamResponse, data: bytes) -> None:
        """Write to a stream; a client that takes none of it for two keep-alive periods is cut off."""
        try:
            await asyncio.wait_for(stream.write(data), 2 * self.settings.keep_alive)
        except TimeoutError:
            if request.transport is not None:
                request.transport.abort()
            raise ConnectionResetError('the client did not read its event stream') from None

    async def close_watch(self, request: web.Request, grant: Grant) -> web.StreamResponse:
        watch = self._own_watch(request, grant)
        ended = self.hub.end(watch.id, 'deleted')
        if ended is not None:
            self._spawn(self._withdraw(ended))
        return web.Response(status=204)

    def _registry(self) -> list[dict[str, Any]]:
        registry = self.drvs.registry()
        if registry is None:
            raise NoServer(f'no {self.settings.server}/registry heard yet: is drvs_server running?')
        return registry

    async def vision_systems(self, request: web.Request, grant: Grant) -> web.StreamResponse:
        try:
            return web.json_response({'vision_systems': self._registry()})
        except NoServer as error:
            return self._no_server(error)

    async def coverage(self, request: web.Request, grant: Grant) -> web.StreamResponse:
        region = region_query(request.query)
        try:
            registry = self._registry()
        except NoServer as error:
            return self._no_server(error)
        geometry = region_geometry(region)
        covering = [
            entry
            for entry in registry
            if len(entry['field_of_view']) >= 3
            and (field := Polygon(entry['field_of_view'])).intersects(geometry)
            and not field.touches(geometry)
        ]
        return web.json_response(
            {
                'region': dict(zip(('min_x', 'min_y', 'max_x', 'max_y'), region, strict=True)),
                'vision_systems': covering,
                'algorithms': sorted({algorithm for entry in covering for algorithm in entry['algorithms']}),
            }
        )

    async def objects(self, request: web.Request, grant: Grant) -> web.StreamResponse:
        return web.json_response(self.drvs.objects() or {'stamp': None, 'algorithms': [], 'objects': []})

    async def health(self, request: web.Request, grant: Grant) -> web.StreamResponse:
        statuses = self.drvs.diagnostics()
        server_name = f'drvs: {self.settings.server}'
        return web.json_response(
            {
                'gateway': {
                    'level': 'OK',
                    'watches': len(self.hub),
                    'listeners': sum(len(watch.listeners) for watch in self.hub),
                    **self.counters.snapshot(),
                },
                'server': next((status for status in statuses if status['name'] == server_name), None),
                'nodes': statuses,
            }
        )

    async def openapi(self, request: web.Request, grant: Grant) -> web.StreamResponse:
        return web.json_response(openapi(), dumps=lambda value: json.dumps(value, indent=1))

    # -- watches over time ---------------------------------------------------------------------
    async def _tick_forever(self) -> None:
        while True:
            await asyncio.sleep(TICK)
            self.tick()

    def tick(self) -> None:
        """Renew the DRVS watches due, withdraw those nobody listens to (call on the loop)."""
        renew, ended = self.hub.due()
        for watch in ended:
            self._spawn(self._withdraw(watch))
        for watch in renew:
            watch.renew_at = self.clock() + self.settings.server_timeout + TICK  # one renewal at a time
            self._spawn(self._renew(watch))

    async def _renew(self, watch: GatewayWatch) -> None:
        try:
            ack = await self._call(
                self.drvs.watch, watch.body, watch.request_id, self.settings.watch_duration
            )
        except NoServer as error:
            self.hub.retry_renewal(
                watch, self.settings.unavailable_retry_after, {'status': 'NO_SERVER', 'message': str(error)}
            )
            return
        if watch.ended:
            return
        if ack.status == ACCEPTED:
            self.hub.renewed(watch, self._granted(ack))
        elif ack.status in (INVALID, UNSUPPORTED):
            self.hub.end(watch.id, f'DRVS refused the renewal: {name(ack.status)}: {ack.message}')
        else:
            self.hub.retry_renewal(
                watch, ack.retry_after, {'status': name(ack.status), 'message': ack.message}
            )

    async def _withdraw(self, watch: GatewayWatch) -> None:
        """Withdraw the DRVS watch (duration 0), retrying a temporary refusal while it stands; a
        failure is logged: the DRVS watch then expires by itself within ``~watch_duration``."""
        give_up = self.clock() + self.settings.watch_duration
        while True:
            try:
                ack = await self._call(self.drvs.watch, watch.body, watch.request_id, 0.0)
            except NoServer as error:
                logger.warning(
                    'withdrawing the DRVS watch %s: %s (it expires by itself)', watch.request_id, error
                )
                return
            if ack.status == ACCEPTED:
                return
            if not is_temporary(ack.status) or self.clock() + ack.retry_after >= give_up:
                logger.warning(
                    'withdrawing the DRVS watch %s: %s: %s', watch.request_id, name(ack.status), ack.message
                )
                return
            await asyncio.sleep(max(ack.retry_after, 0.01))
