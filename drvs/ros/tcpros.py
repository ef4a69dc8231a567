"""The steps of a ROS service call over TCPROS, each against one deadline, each with its own error.

A master lookup (XML-RPC with a timeout), connecting, waiting on a non-blocking socket (one
``poll`` per wait), sending, receiving, framing and the handshake headers
(``rosgraph.network``); and :func:`probe_service`, which reads a service's handshake header
(type, md5sum, provider: what ``rosservice info`` shows) without calling it.
:class:`drvs.ros.service_client.ServiceClient` is built on them; why it speaks TCPROS itself is
in docs/design.md.
"""

from __future__ import annotations

import math
import select
import socket
import struct
import time
import xmlrpc.client
from dataclasses import dataclass

import rosgraph
import rosgraph.network
import rospy

__all__ = [
    'Deadline',
    'MasterUnreachable',
    'ServiceCallError',
    'ServiceInfo',
    'TimeoutTransport',
    'UnknownService',
    'connect',
    'framed',
    'handshake',
    'lookup_service',
    'probe_service',
    'recv_exactly',
    'recv_some',
    'send',
    'wait',
]

MAX_HEADER_BYTES = 1 << 16


class ServiceCallError(Exception):
    """A call that did not produce a response; the message says which service and what failed."""


class MasterUnreachable(ServiceCallError):
    """The ROS master did not answer in time (it may be restarting): a temporary condition."""


class UnknownService(ServiceCallError):
    """The master answered: it knows no such service."""


@dataclass(frozen=True)
class ServiceInfo:
    """What a service says about itself in its handshake header."""

    name: str
    uri: str  # rosrpc://host:port
    type: str  # e.g. drvs/DetectObjectBoundary
    md5sum: str
    provider: str  # caller id of the node that serves it


class TimeoutTransport(xmlrpc.client.Transport):
    """XML-RPC over HTTP with a socket timeout: a master that does not answer cannot hang a caller."""

    def __init__(self, timeout: float):
        super().__init__()
        self._timeout = timeout

    def make_connection(self, host):
        connection = super().make_connection(host)
        connection.timeout = self._timeout
        return connection


def lookup_service(
    name: str, timeout: float, master_uri: str | None = None, caller_id: str | None = None
) -> str:
    """The ``rosrpc://`` URI of ``name`` from the master.

    :raises UnknownService: the master knows no such service.
    :raises MasterUnreachable: the master did not answer in time.
    """
    uri = master_uri or rosgraph.get_master_uri()
    try:
        with xmlrpc.client.ServerProxy(uri, transport=TimeoutTransport(max(timeout, 0.001))) as master:
            code, message, value = master.lookupService(caller_id or rospy.get_caller_id(), name)
    except (OSError, xmlrpc.client.Error) as error:
        raise MasterUnreachable(f'service {name}: cannot ask the master at {uri}: {error}') from None
    if code != 1:
        raise UnknownService(f'service {name}: unknown service (the master says: {message})')
    return value


def _parse_rosrpc(name: str, uri: str) -> tuple[str, int]:
    if not uri.startswith('rosrpc://'):
        raise ServiceCallError(f'service {name}: the master gave an invalid URI {uri!r}')
    host, _, port = uri[len('rosrpc://') :].rstrip('/').rpartition(':')
    try:
        return host, int(port)
    except ValueError:
        raise ServiceCallError(f'service {name}: the master gave an invalid URI {uri!r}') from None


class Deadline:
    """The end of one call to service ``name``, ``timeout`` seconds from now, passed through every step."""

    def __init__(self, name: str, timeout: float):
        self.name = name
        self.timeout = timeout
        self.end = time.monotonic() + timeout

    def left(self) -> float:
        """Seconds left; :raises ServiceCallError: none left ("timed out after T s")."""
        left = self.end - time.monotonic()
        if left <= 0:
            raise ServiceCallError(f'service {self.name}: timed out after {self.timeout:g} s')
        return left


def connect(name: str, uri: str, deadline: Deadline) -> socket.socket:
    """A connected socket to ``uri``, non-blocking (every later step waits with :func:`wait`)."""
    host, port = _parse_rosrpc(name, uri)
    try:
        sock = socket.create_connection((host, port), timeout=deadline.left())
    except TimeoutError:
        raise ServiceCallError(
            f'service {name}: timed out after {deadline.timeout:g} s connecting to {uri}'
        ) from None
    except OSError as error:
        raise ServiceCallError(
            f'service {name}: cannot connect to {uri}: {error.strerror or error}'
        ) from None
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.setblocking(False)
    return sock


def wait(sock: socket.socket, event: int, deadline: Deadline, doing: str) -> None:
    """Wait until ``sock`` is ready for ``event`` (``select.POLLIN`` / ``POLLOUT``), or an error on it.

    One ``poll`` per wait: a socket with a timeout (``settimeout``) would cost a poll and
    an ioctl per operation, each a system call that lets go of the interpreter lock,
    which a busy server's other threads then fight over.

    :raises ServiceCallError: the deadline passed first ("timed out after T s ``doing``").
    """
    poller = select.poll()
    poller.register(sock, event)
    while True:
        left = deadline.end - time.monotonic()
        if left <= 0:
            break
        if poller.poll(math.ceil(left * 1000)):
            return
    raise ServiceCallError(f'service {deadline.name}: timed out after {deadline.timeout:g} s {doing}')


def recv_some(sock: socket.socket, count: int, deadline: Deadline, what: str) -> bytes:
    """At least one and at most ``count`` bytes, once they arrive."""
    while True:
        wait(sock, select.POLLIN, deadline, f'waiting for the {what}')
        try:
            chunk = sock.recv(count)
        except BlockingIOError:
            continue  # a spurious wake-up
        except OSError as error:
            raise ServiceCallError(
                f'service {deadline.name}: connection failed while reading the {what}: {error}'
            ) from None
        if not chunk:
            raise ServiceCallError(
                f'service {deadline.name}: connection closed by the service before the {what}'
            )
        return chunk


def recv_exactly(sock: socket.socket, count: int, deadline: Deadline, what: str) -> bytes:
    """Exactly ``count`` bytes, once they all arrived."""
    chunks = []
    while count > 0:
        chunk = recv_some(sock, min(count, 1 << 20), deadline, what)
        chunks.append(chunk)
        count -= len(chunk)
    return b''.join(chunks)


def framed(data: bytes) -> bytes:
    """A message's bytes as TCPROS sends them: their length first."""
    return struct.pack('<I', len(data)) + data


def send(sock: socket.socket, data: bytes, deadline: Deadline, what: str) -> None:
    """Send all of ``data``, waiting while the socket's buffer is full."""
    view = memoryview(data)
    while view:
        try:
            sent = sock.send(view)
        except BlockingIOError:
            wait(sock, select.POLLOUT, deadline, f'sending the {what}')
            continue
        except OSError as error:
            raise ServiceCallError(
                f'service {deadline.name}: connection failed sending the {what}: {error}'
            ) from None
        view = view[sent:]


def handshake(sock: socket.socket, fields: dict[str, str], deadline: Deadline) -> dict[str, str]:
    """Send our handshake header ``fields``; the service's header.

    :raises ServiceCallError: too large or invalid a header, or the service's ``error`` field.
    """
    send(sock, rosgraph.network.encode_ros_handshake_header(fields), deadline, 'handshake header')
    (size,) = struct.unpack('<I', recv_exactly(sock, 4, deadline, 'handshake header'))
    if size > MAX_HEADER_BYTES:
        raise ServiceCallError(f'service {deadline.name}: handshake header of {size} bytes is too large')
    body = recv_exactly(sock, size, deadline, 'handshake header')
    try:
        header = rosgraph.network.decode_ros_handshake_header(struct.pack('<I', size) + body)
    except (rosgraph.network.ROSHandshakeException, UnicodeDecodeError, struct.error) as error:
        raise ServiceCallError(f'service {deadline.name}: invalid handshake header: {error}') from None
    if 'error' in header:
        raise ServiceCallError(
            f'service {deadline.name}: the service refused the connection: {header["error"]}'
        )
    return header


def probe_service(
    name: str, timeout: float, master_uri: str | None = None, caller_id: str | None = None
) -> ServiceInfo:
    """Look ``name`` up and read its handshake header (type, md5sum, provider) without calling it.

    :raises ServiceCallError: unknown service, unreachable, timed out or no valid header.
    """
    deadline = Deadline(name, timeout)
    uri = lookup_service(name, deadline.left(), master_uri, caller_id)
    sock = connect(name, uri, deadline)
    try:
        fields = {
            'probe': '1',
            'md5sum': '*',
            'callerid': caller_id or rospy.get_caller_id(),
            'service': name,
        }
        header = handshake(sock, fields, deadline)
    finally:
        sock.close()
    return ServiceInfo(
        name=name,
        uri=uri,
        type=header.get('type', ''),
        md5sum=header.get('md5sum', ''),
        provider=header.get('callerid', ''),
    )
