"""The floor-plan page of ``drvs_gateway``: ``GET /`` and its files, ``POST /v1/tickets`` and the live
event stream ``GET /v1/live`` the page draws from.

The page is plain HTML, JavaScript and SVG checked in under ``drvs/gateway/static/`` (no CDN: it
works with no internet). It asks for a token, keeps it in the tab's ``sessionStorage``, sends it as
``Authorization: Bearer`` to ``POST /v1/tickets`` and opens the stream with the ticket it gets:
never the token in a URL. The state comes from :class:`drvs.gateway.live.LiveFeed`. The page:
docs/gateway.md ("The floor-plan page").
"""

from __future__ import annotations

import asyncio
import itertools
from pathlib import Path
from typing import TYPE_CHECKING

from aiohttp import web

from drvs.gateway import answers, sse
from drvs.gateway.live import TICKET_LIFETIME, LiveFeed, Tickets
from drvs.gateway.tokens import Grant
from drvs.gateway.watches import Event

if TYPE_CHECKING:
    from drvs.gateway.app import Gateway

__all__ = ['MAX_LIVE', 'STATIC', 'FloorPlan']

STATIC = Path(__file__).with_name('static')
"""The page's files (installed with the package: setup.py's package_data)."""
CONTENT_TYPES = {
    '.html': 'text/html; charset=utf-8',
    '.js': 'text/javascript; charset=utf-8',
    '.css': 'text/css; charset=utf-8',
    '.svg': 'image/svg+xml',
}
HEADERS = {
    'Cache-Control': 'no-cache',
    'X-Content-Type-Options': 'nosniff',
    'Referrer-Policy': 'no-referrer',
    'X-Frame-Options': 'DENY',
    'Content-Security-Policy': "default-src 'self'; img-src 'self' data:; frame-ancestors 'none'",
}
MAX_LIVE = 64
"""Live streams open at once (all tokens); beyond: 429."""
POLL = 0.1
"""Seconds between two looks at the state while someone listens."""
MIN_INTERVAL = 0.1
"""Least seconds between two writes to one live stream (changes meanwhile are coalesced)."""


class FloorPlan:
    """The page's handlers, on a :class:`~drvs.gateway.app.Gateway` (its settings, clock, limits)."""

    def __init__(self, gateway: Gateway):
        self.gateway = gateway
        drvs = gateway.drvs
        self.feed = LiveFeed(lambda: drvs.registry(), lambda: drvs.objects(), lambda: drvs.robots())
        self.tickets = Tickets(gateway.clock)
        self.files = {
            path.name: (path.read_bytes(), CONTENT_TYPES[path.suffix])
            for path in sorted(STATIC.iterdir())
            if path.suffix in CONTENT_TYPES
        }

    def handlers(self) -> dict:
        return {'page': self.page, 'static': self.static, 'ticket': self.ticket, 'live': self.live}

    async def started(self, app: web.Application) -> None:
        self.gateway._spawn(self._poll_forever())

    async def _poll_forever(self) -> None:
        while True:
            await asyncio.sleep(POLL)
            if self.feed.listeners:
                self.feed.poll()

    def _file(self, name: str) -> web.Response:
        if name not in self.files:
            raise web.HTTPNotFound()
        body, content_type = self.files[name]
        return web.Response(body=body, headers={**HEADERS, 'Content-Type': content_type})

    async def page(self, request: web.Request, grant: Grant) -> web.StreamResponse:
        return self._file('index.html')

    async def static(self, request: web.Request, grant: Grant) -> web.StreamResponse:
        return self._file(request.match_info['name'])

    async def ticket(self, request: web.Request, grant: Grant) -> web.StreamResponse:
        ticket = self.tickets.issue(grant)
        return web.json_response(
            {'ticket': ticket, 'expires_in': TICKET_LIFETIME, 'live': f'/v1/live?ticket={ticket}'},
            status=201,
            headers={'Cache-Control': 'no-store'},
        )

    async def live(self, request: web.Request, grant: Grant) -> web.StreamResponse:
        gateway = self.gateway
        if len(self.feed.listeners) >= MAX_LIVE:
            return gateway._refused(
                answers.error(429, 'TOO_MANY_LISTENERS', f'{MAX_LIVE} live streams are open', 1.0)
            )
        listener = self.feed.listen()
        wake = asyncio.Event()
        listener.wake = wake.set
        wake.set()
        stream = web.StreamResponse(
            headers={
                'Content-Type': 'text/event-stream',
                'Cache-Control': 'no-cache',
                'X-Accel-Buffering': 'no',
            }
        )
        ids = itertools.count(1)
        try:
            await stream.prepare(request)
            while True:
                idle = gateway.clock()
                while not wake.is_set():
                    if request.transport is None or request.transport.is_closing():
                        return stream  # the client went away
                    if gateway.clock() - idle >= gateway.settings.keep_alive:
                        await gateway._write(request, stream, sse.KEEP_ALIVE)
                        idle = gateway.clock()
                    try:
                        await asyncio.wait_for(wake.wait(), 0.5)
                    except TimeoutError:
                        pass
                wake.clear()
                for key in listener.take():
                    kind, data = self.feed.event(key)
                    await gateway._write(request, stream, sse.encode(Event(next(ids), kind, data)))
                await asyncio.sleep(MIN_INTERVAL)
        except ConnectionResetError:
            return stream
        finally:
            self.feed.leave(listener)
