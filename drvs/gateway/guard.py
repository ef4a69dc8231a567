"""Slow senders and connection floods on the gateway's listening sockets: aiohttp 3.8 (Debian
bookworm) reads a request's head with no deadline, so :class:`GuardedRunner` (an
``aiohttp.web.AppRunner``) gives every connection one: the head of its first request within
``head_timeout``, or it is closed (later requests on a kept-alive connection: aiohttp's own
``keepalive_timeout``, counted from the previous answer). It also caps the connections one client
address holds at once; beyond, a new one is closed at once. docs/gateway.md, "Limits", has the rest.
"""

from __future__ import annotations

import asyncio
from typing import Any

from aiohttp import web
from aiohttp.web_protocol import RequestHandler
from aiohttp.web_server import Server

__all__ = ['GuardedRunner']


class _Peers:
    """Connections open per client address."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.open: dict[str, int] = {}

    def admit(self, address: str) -> bool:
        count = self.open.get(address, 0)
        if count >= self.limit:
            return False
        self.open[address] = count + 1
        return True

    def release(self, address: str) -> None:
        count = self.open.get(address, 0) - 1
        if count > 0:
            self.open[address] = count
        else:
            self.open.pop(address, None)


class _GuardedHandler(RequestHandler):
    """aiohttp's connection handler with a deadline on the first request's head and a place in
    :class:`_Peers`."""

    def __init__(self, manager: Server, *, peers: _Peers, head_timeout: float, **kwargs: Any) -> None:
        super().__init__(manager, **kwargs)
        self._peers = peers
        self._head_timeout = head_timeout
        self._head_timer: asyncio.TimerHandle | None = None
        self._address: str | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)
        peer = transport.get_extra_info('peername')
        address = str(peer[0]) if peer else ''
        if not self._peers.admit(address):
            self.force_close()
            return
        self._address = address
        self._head_timer = self._loop.call_later(self._head_timeout, self._head_late)

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self._head_timer is not None and self._request_count:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_late(self) -> None:
        self._head_timer = None
        if not self._request_count:
            self.force_close()

    def connection_lost(self, exc: BaseException | None) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None
        if self._address is not None:
            self._peers.release(self._address)
            self._address = None
        super().connection_lost(exc)


class _GuardedServer(Server):
    def __init__(self, server: Server, peers: _Peers, head_timeout: float) -> None:
        super().__init__(server.request_handler, request_factory=server.request_factory, **server._kwargs)
        self._peers = peers
        self._head_timeout = head_timeout

    def __call__(self) -> RequestHandler:
        return _GuardedHandler(
            self, loop=self._loop, peers=self._peers, head_timeout=self._head_timeout, **self._kwargs
        )


class GuardedRunner(web.AppRunner):
    """``web.AppRunner(app, ...)`` whose connections get :class:`_GuardedHandler`.

    :param head_timeout: seconds a new connection has to send its first request's head.
    :param max_per_address: connections one client address may hold open at once.
    """

    def __init__(
        self, app: web.Application, *, head_timeout: float, max_per_address: int, **kwargs: Any
    ) -> None:
        super().__init__(app, **kwargs)
        self.peers = _Peers(max_per_address)
        self.head_timeout = head_timeout

    async def _make_server(self) -> Server:
        server = await super()._make_server()
        return _GuardedServer(server, self.peers, self.head_timeout)
