"""A ROS service client with a timeout on every call and a persistent connection that heals.

rospy's ``ServiceProxy`` has no call timeout (ros/ros_comm#152) and a persistent
proxy never reconnects after the far side restarts. :class:`ServiceClient`
speaks TCPROS itself: it looks the service up on the master (XML-RPC with a
timeout), connects a socket, exchanges the handshake headers
(``rosgraph.network``), and sends genpy-serialised requests over that one
connection. Every step runs against the call's deadline, so a hung or dead
service costs at most ``timeout`` seconds and never blocks the caller forever.
After any failure the connection is dropped and the next call builds a new one
(looking the service up again, since its provider may have moved).

:func:`probe_service` asks a service for its handshake header without calling it:
the service's type, md5sum and the node that provides it (what ``rosservice
info`` shows), which the DRVS server uses to check registrations and callbacks.

>>> from drvs.srv import DetectObjectBoundary
>>> client = ServiceClient('/vs1/detect_object_boundary', DetectObjectBoundary, timeout=2.0)
>>> client.close()  # nothing connected yet: constructing does no I/O
"""

from __future__ import annotations

import io
import select
import socket
import struct
import threading
import time
import xmlrpc.client
from dataclasses import dataclass

import rosgraph
import rosgraph.network
import rospy

__all__ = [
    'MasterUnreachable',
    'ServiceCallError',
    'ServiceClient',
    'ServiceInfo',
    'UnknownService',
    'lookup_service',
    'probe_service',
]

MAX_HEADER_BYTES = 1 << 16
MAX_RESPONSE_BYTES = 1 << 30


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


def _caller_id() -> str:
    return rospy.get_caller_id()


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
            code, message, value = master.lookupService(caller_id or _caller_id(), name)
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


class _Deadline:
    def __init__(self, name: str, timeout: float):
        self.name = name
        self.timeout = timeout
        self.end = time.monotonic() + timeout

    def left(self) -> float:
        left = self.end - time.monotonic()
        if left <= 0:
            raise ServiceCallError(f'service {self.name}: timed out after {self.timeout:g} s')
        return left


def _connect(name: str, uri: str, deadline: _Deadline) -> socket.socket:
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
    return sock


def _recv_exactly(sock: socket.socket, count: int, deadline: _Deadline, what: str) -> bytes:
    chunks = []
    while count > 0:
        sock.settimeout(deadline.left())
        try:
            chunk = sock.recv(min(count, 1 << 20))
        except TimeoutError:
            raise ServiceCallError(
                f'service {deadline.name}: timed out after {deadline.timeout:g} s waiting for the {what}'
            ) from None
        except OSError as error:
            raise ServiceCallError(
                f'service {deadline.name}: connection failed while reading the {what}: {error}'
            ) from None
        if not chunk:
            raise ServiceCallError(
                f'service {deadline.name}: connection closed by the service before the {what}'
            )
        chunks.append(chunk)
        count -= len(chunk)
    return b''.join(chunks)


def _send(sock: socket.socket, data: bytes, deadline: _Deadline, what: str) -> None:
    sock.settimeout(deadline.left())
    try:
        sock.sendall(data)
    except TimeoutError:
        raise ServiceCallError(
            f'service {deadline.name}: timed out after {deadline.timeout:g} s sending the {what}'
        ) from None
    except OSError as error:
        raise ServiceCallError(
            f'service {deadline.name}: connection failed sending the {what}: {error}'
        ) from None


def _handshake(sock: socket.socket, fields: dict[str, str], deadline: _Deadline) -> dict[str, str]:
    _send(sock, rosgraph.network.encode_ros_handshake_header(fields), deadline, 'handshake header')
    (size,) = struct.unpack('<I', _recv_exactly(sock, 4, deadline, 'handshake header'))
    if size > MAX_HEADER_BYTES:
        raise ServiceCallError(f'service {deadline.name}: handshake header of {size} bytes is too large')
    body = _recv_exactly(sock, size, deadline, 'handshake header')
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
    deadline = _Deadline(name, timeout)
    uri = lookup_service(name, deadline.left(), master_uri, caller_id)
    sock = _connect(name, uri, deadline)
    try:
        fields = {'probe': '1', 'md5sum': '*', 'callerid': caller_id or _caller_id(), 'service': name}
        header = _handshake(sock, fields, deadline)
    finally:
        sock.close()
    return ServiceInfo(
        name=name,
        uri=uri,
        type=header.get('type', ''),
        md5sum=header.get('md5sum', ''),
        provider=header.get('callerid', ''),
    )


class ServiceClient:
    """Calls one service over a persistent TCPROS connection, with a timeout per call.

    :param service: the service's global name.
    :param service_class: its generated class (e.g. ``drvs.srv.DetectObjectBoundary``).
    :param timeout: seconds one :meth:`call` may take in all: waiting for another
        thread's call on this client, master lookup, connecting, sending, waiting
        for the reply.
    :param master_uri: the master to ask (default: ROS_MASTER_URI).
    :param caller_id: the id sent in the handshake (default: this node's name).

    Thread-safe: calls on one client run one at a time (TCPROS carries one call
    at a time per connection).
    """

    def __init__(
        self,
        service: str,
        service_class,
        timeout: float,
        master_uri: str | None = None,
        caller_id: str | None = None,
    ):
        if timeout <= 0:
            raise ValueError(f'timeout: must be positive, got {timeout}')
        self.service = service
        self.service_class = service_class
        self.timeout = float(timeout)
        self.master_uri = master_uri
        self.caller_id = caller_id
        self.header: dict[str, str] = {}  # the service's handshake header on the current connection
        self._lock = threading.Lock()
        self._sock: socket.socket | None = None
        self._connections = 0

    @property
    def connections(self) -> int:
        """How many connections this client has opened (1 while all goes well)."""
        return self._connections

    def call(self, request):
        """Send ``request``; return the response.

        :raises ServiceCallError: naming the service and what failed (unknown
            service, connection refused, timed out after X s, the service's error
            message, ...). The connection is dropped; the next call reconnects.
        """
        deadline = _Deadline(self.service, self.timeout)
        if not self._lock.acquire(timeout=deadline.left()):
            raise ServiceCallError(
                f'service {self.service}: timed out after {self.timeout:g} s waiting for an earlier call'
            )
        try:
            try:
                return self._call(request, deadline)
            except BaseException:
                self._disconnect()
                raise
        finally:
            self._lock.release()

    __call__ = call

    def close(self) -> None:
        """Close the connection (a later call opens a new one)."""
        with self._lock:
            self._disconnect()

    def _disconnect(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
            self.header = {}

    def _stale(self) -> bool:
        """True if the far side closed the idle connection (readable before we asked anything)."""
        readable, _, _ = select.select([self._sock], [], [], 0)
        return bool(readable)

    def _open(self, deadline: _Deadline) -> None:
        uri = lookup_service(self.service, deadline.left(), self.master_uri, self.caller_id)
        sock = _connect(self.service, uri, deadline)
        try:
            fields = {
                'callerid': self.caller_id or _caller_id(),
                'service': self.service,
                'md5sum': self.service_class._md5sum,
                'type': self.service_class._type,
                'persistent': '1',
            }
            header = _handshake(sock, fields, deadline)
        except BaseException:
            sock.close()
            raise
        self._sock = sock
        self.header = header
        self._connections += 1

    def _call(self, request, deadline: _Deadline):
        if self._sock is not None and self._stale():
            self._disconnect()
        if self._sock is None:
            self._open(deadline)
        buffer = io.BytesIO()
        try:
            request.serialize(buffer)
        except (struct.error, TypeError, ValueError, AttributeError, OverflowError) as error:
            raise ServiceCallError(f'service {self.service}: cannot serialise the request: {error}') from None
        data = buffer.getvalue()
        _send(self._sock, struct.pack('<I', len(data)) + data, deadline, 'request')
        ok, size = struct.unpack('<BI', _recv_exactly(self._sock, 5, deadline, 'reply'))
        if size > MAX_RESPONSE_BYTES:
            raise ServiceCallError(f'service {self.service}: reply of {size} bytes is too large')
        payload = _recv_exactly(self._sock, size, deadline, 'reply')
        if not ok:
            text = payload.decode('utf-8', errors='replace')
            raise ServiceCallError(f'service {self.service}: the service answered with an error: {text}')
        response = self.service_class._response_class()
        try:
            response.deserialize(payload)
        except Exception as error:  # genpy raises DeserializationError, struct.error, ...
            raise ServiceCallError(f'service {self.service}: cannot deserialise the reply: {error}') from None
        return response
