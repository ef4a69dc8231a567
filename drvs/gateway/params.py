"""The gateway's settings: every parameter with its default, meaning, unit and range.

Read from the node's private parameters by :func:`drvs.ros.params.read_params`;
docs/nodes/drvs_gateway.md's parameter table is generated from these declarations. No ROS here.
"""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass

from drvs.common.settings import POSITIVE, ParamError, Settings, at_least, param

__all__ = ['GatewaySettings', 'split_bind']


def split_bind(name: str, text: str) -> tuple[str, int]:
    """``HOST:PORT`` -> (host, port); ``[::1]:8080`` for IPv6.

    :raises ParamError: ``~name: expected HOST:PORT ...``.
    """
    host, colon, port = text.rpartition(':')
    host = host.removeprefix('[').removesuffix(']')
    if not colon or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ParamError(
            name, f'expected HOST:PORT with a port 0 to 65535, e.g. 127.0.0.1:8080, got {text!r}'
        )
    return host, int(port)


def is_loopback(host: str) -> bool:
    """Whether ``host`` names this machine only (``localhost``, 127.0.0.0/8, ``::1``)."""
    if host == 'localhost':
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@dataclass(frozen=True)
class GatewaySettings(Settings):
    bind: str = param(
        '127.0.0.1:8080',
        'HOST:PORT the HTTP API listens on; anything but loopback needs `~tokens`',
    )
    tokens: str = param(
        '',
        'the tokens file (`drvs_token add`); empty: no tokens asked for, and only loopback allowed',
    )
    server: str = param('/drvs', "the DRVS server's namespace (its services and topics)")
    server_timeout: float = param(
        2.0,
        'limit on each call to the DRVS server; none answering: `503` within this',
        unit='s',
        check=POSITIVE,
    )
    unavailable_retry_after: float = param(
        1.0, '`Retry-After` of a `503` when no DRVS server answered', unit='s', check=POSITIVE
    )
    ros_calls: int = param(4, 'calls to the DRVS server in flight at once', check=at_least(1))
    max_body: int = param(16384, 'largest request body; beyond: `413`', unit='bytes', check=at_least(64))
    request_timeout: float = param(
        10.0,
        "a request's head, and then its body, must arrive within this (a kept-alive connection's next "
        'head: from the previous answer); beyond, the connection is closed (the body: `408`)',
        unit='s',
        check=POSITIVE,
    )
    max_connections_per_address: int = param(
        256,
        'connections one client address holds open at once, on each endpoint; beyond, a new one is closed',
        check=at_least(1),
    )
    max_wait: float = param(30.0, 'the longest `wait` of `POST /v1/detect`', unit='s', check=POSITIVE)
    max_requests_per_s: float = param(
        20.0,
        'requests per second per token (per client without tokens); beyond: `429`',
        unit='/s',
        check=POSITIVE,
    )
    burst: int = param(40, 'requests a token may send at once before the rate applies', check=at_least(1))
    max_watches: int = param(200, 'watches open at once; beyond: `503`', check=at_least(1))
    max_watches_per_token: int = param(
        10, 'watches one token may hold open; beyond: `429`', check=at_least(1)
    )
    max_listeners: int = param(4, 'event streams open at once on one watch; beyond: `429`', check=at_least(1))
    listener_queue: int = param(
        256, 'events waiting for one slow listener; beyond, the oldest are dropped', check=at_least(1)
    )
    resume_buffer: int = param(256, "a watch's newest events kept for `Last-Event-ID`", check=at_least(1))
    watch_duration: float = param(
        10.0, 'duration asked of the DRVS watch; the gateway renews it at half', unit='s', check=POSITIVE
    )
    watch_linger: float = param(
        30.0,
        'a watch nobody listens to is withdrawn after this long (also from its creation)',
        unit='s',
        check=POSITIVE,
    )
    keep_alive: float = param(15.0, 'a comment on an idle event stream this often', unit='s', check=POSITIVE)
    rosbridge_bind: str = param(
        '127.0.0.1:9090',
        'HOST:PORT of the rosbridge v2 WebSocket (at `/`); `none`: none; beyond loopback it needs `~tokens`',
    )
    rosbridge_call_timeout: float = param(
        1.5,
        "limit on DRVS's call to a service a rosbridge client hosts (below a vision system's "
        '`~callback_timeout`, 2 s)',
        unit='s',
        check=POSITIVE,
    )
    rosbridge_queue: int = param(
        256,
        'messages waiting for one slow rosbridge client; beyond, the oldest are dropped',
        check=at_least(1),
    )
    rosbridge_heartbeat: float = param(
        10.0,
        'a WebSocket ping this often; a client that answers none within half of it is closed',
        unit='s',
        check=POSITIVE,
    )
    rosbridge_max_frame: int = param(
        65536,
        'largest rosbridge frame; beyond, the connection is closed (1009)',
        unit='bytes',
        check=at_least(1024),
    )
    rosbridge_max_clients: int = param(
        8, 'rosbridge connections per token (per client address without tokens)', check=at_least(1)
    )

    def __post_init__(self) -> None:
        super().__post_init__()
        split_bind('bind', self.bind)
        if self.rosbridge_on:
            split_bind('rosbridge_bind', self.rosbridge_bind)

    @property
    def rosbridge_on(self) -> bool:
        """Whether the rosbridge endpoint listens (``~rosbridge_bind`` not ``none``)."""
        return self.rosbridge_bind not in ('', 'none')
