"""The bytes that cross TCP on loopback, per connection, counted from a raw capture ("on the wire").

Every IPv4/TCP packet on ``lo`` is read from an AF_PACKET socket (root only) by a
thread, and its TCP payload is counted per connection and direction. Nothing is
estimated from message sizes: TCPROS connection headers, length prefixes, the
service response's ok byte and the bodies are all bytes seen in packets. A
connection's byte count in one direction is the span of TCP sequence numbers its
payload covered (so a retransmission counts once; a packet the capture missed is
still counted, and reported as a gap and in :attr:`Capture.drops`).

Each connection's payload is also followed as TCPROS (:class:`Framer`): the first
message each side sends is its connection header (``callerid``, ``service`` or
``topic``, ...), parsed, so a connection is attributed to the node that opened it
and to the service or topic it carries; then every message is counted (a service
response is ``ok`` + length + body; a request or a topic message is length + body).
Connections that start with HTTP are XML-RPC (the master, lookups, topic
negotiation): :attr:`Connection.protocol` ``'http'``, counted but not framed.
Which node listens on a port: :func:`node_ports` asks the master.

On ``lo`` each packet is seen twice (outgoing, then incoming): only the incoming
copy (``PACKET_HOST``) is kept. :meth:`Capture.flush` makes sure every packet sent
before it has been counted (it sends a UDP marker to itself and waits until the
thread saw it), and raises :class:`CaptureError` if the thread died: a broken
capture fails loudly instead of reporting zero.

>>> framer = Framer()
>>> framer.feed(b'\\x0c\\x00\\x00\\x00\\x08\\x00\\x00\\x00topic=/a' + b'\\x02\\x00\\x00\\x00hi')
>>> framer.fields, framer.header_bytes, framer.messages, framer.message_bytes
({'topic': '/a'}, 16, 1, 6)
"""

from __future__ import annotations

import itertools
import os
import socket
import struct
import threading
import time
import xmlrpc.client
from collections.abc import Collection
from dataclasses import dataclass, field

__all__ = [
    'Capture',
    'CaptureError',
    'Connection',
    'Direction',
    'Framer',
    'available',
    'delta',
    'node_ports',
    'parse_header',
]

ETH_P_ALL = 0x0003
SO_RCVBUFFORCE = 33
SOL_PACKET = 263
PACKET_STATISTICS = 6
PACKET_HOST = 0
HEADER_LIMIT = 1 << 16
"""A TCPROS connection header longer than this is not TCPROS (the framer gives up)."""
HTTP_STARTS = (b'POST', b'HTTP', b'GET ', b'PUT ')


class CaptureError(RuntimeError):
    """The capture cannot be trusted: its thread died, or a marker never came back."""


def available(interface: str = 'lo') -> tuple[bool, str]:
    """(True, '') if a raw AF_PACKET socket can be opened on ``interface``, else (False, why)."""
    if not hasattr(socket, 'AF_PACKET'):
        return False, 'AF_PACKET sockets do not exist on this platform'
    try:
        with socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.ntohs(ETH_P_ALL)) as sock:
            sock.bind((interface, 0))
    except PermissionError:
        return False, f'AF_PACKET capture needs root (uid {os.getuid()}) or CAP_NET_RAW'
    except OSError as error:
        return False, f'AF_PACKET capture on {interface!r}: {error.strerror or error}'
    return True, ''


def parse_header(data: bytes) -> dict[str, str]:
    """The fields of a TCPROS connection header body (without its 4-byte length).

    >>> parse_header(b'\\x0b\\x00\\x00\\x00callerid=/r' + b'\\x05\\x00\\x00\\x00a=b=c')
    {'callerid': '/r', 'a': 'b=c'}

    :raises ValueError: if the lengths do not add up.
    """
    fields = {}
    offset = 0
    while offset < len(data):
        if offset + 4 > len(data):
            raise ValueError('truncated field length')
        (size,) = struct.unpack_from('<I', data, offset)
        offset += 4
        if offset + size > len(data):
            raise ValueError('truncated field')
        key, sep, value = bytes(data[offset : offset + size]).decode('utf-8', 'replace').partition('=')
        if not sep:
            raise ValueError(f'field without "=": {key!r}')
        fields[key] = value
        offset += size
    return fields


def _clone(value):
    """A shallow copy of a plain object, faster than copy.copy (snapshots copy thousands)."""
    clone = object.__new__(type(value))
    clone.__dict__.update(value.__dict__)
    return clone


class Framer:
    """Follows one direction of a TCPROS connection: its header, then its messages.

    ``response``: this direction carries service responses (``ok`` byte + length + body);
    else each message is length + body. It can be set after the header (the server's
    direction learns it from the client's header). A stream that is not TCPROS (HTTP,
    a header that does not parse) or that has a gap stops being framed: ``state``
    says why, and only the byte counts (kept by :class:`Direction`) go on.
    """

    def __init__(self, response: bool = False):
        self.response = response
        self.state = 'header-length'
        self.fields: dict[str, str] = {}
        self.header_bytes = 0
        self.messages = 0
        self.message_bytes = 0
        self.errors = 0  # service responses with ok = 0
        self._buffer = bytearray()
        self._need = 4
        self._current = 0  # bytes of the message being read

    @property
    def framing(self) -> bool:
        return self.state in ('header-length', 'header', 'prefix', 'body')

    def stop(self, why: str) -> None:
        self.state = why

    def feed(self, data) -> None:
        view = memoryview(data)
        i, n = 0, len(view)
        if self.state == 'header-length' and not self._buffer and n >= 4 and bytes(view[:4]) in HTTP_STARTS:
            self.state = 'http'
        while i < n and self.framing:
            take = min(self._need, n - i)
            if self.state == 'body':
                self._need -= take
                self._current += take
                i += take
                if self._need == 0:
                    self._end_message()
                continue
            self._buffer += view[i : i + take]
            self._need -= take
            i += take
            if self._need == 0:
                self._collected()

    def _collected(self) -> None:
        data = bytes(self._buffer)
        self._buffer.clear()
        if self.state == 'header-length':
            (size,) = struct.unpack('<I', data)
            if size > HEADER_LIMIT:
                self.stop('not-tcpros')
                return
            self.header_bytes = 4
            self.state, self._need = 'header', size
            if size == 0:
                self._collected()
        elif self.state == 'header':
            self.header_bytes += len(data)
            try:
                self.fields = parse_header(data)
            except ValueError:
                self.stop('not-tcpros')
                return
            self._start_message()
        elif self.state == 'prefix':
            if self.response:
                ok, size = struct.unpack('<BI', data)
                self.errors += ok == 0
            else:
                (size,) = struct.unpack('<I', data)
            self._current = len(data)
            self.state, self._need = 'body', size
            if size == 0:
                self._end_message()

    def _start_message(self) -> None:
        self.state, self._need = 'prefix', 5 if self.response else 4

    def _end_message(self) -> None:
        self.messages += 1
        self.message_bytes += self._current
        self._current = 0
        self._start_message()

    def frozen(self) -> Framer:
        """A copy of the counts (``fields`` shared: it is never changed once parsed)."""
        clone = _clone(self)
        clone._buffer = bytearray(self._buffer)
        return clone


@dataclass
class Direction:
    """One direction of a connection: TCP payload bytes (by sequence span), packets, gaps, its framer."""

    bytes: int = 0
    """TCP payload bytes: the sequence-number span covered, each byte once."""
    packets: int = 0
    """TCP packets (data or not: ACKs, SYN, FIN) seen going this way."""
    ip_bytes: int = 0
    """IPv4 total length of those packets (IP and TCP headers included)."""
    retransmitted: int = 0
    gaps: int = 0
    """Times the payload jumped ahead (a packet the capture missed): framing stops."""
    framer: Framer = field(default_factory=Framer)
    _next: int | None = None  # next expected sequence number

    def syn(self, seq: int) -> None:
        self._next = (seq + 1) & 0xFFFFFFFF

    def data(self, seq: int, payload) -> None:
        size = len(payload)
        if self._next is None:  # the connection began before the capture
            self._next = seq
            self.framer.stop('joined-late')
        ahead = (seq - self._next) & 0xFFFFFFFF
        if ahead == 0:
            self._take(payload)
        elif ahead >= 1 << 31:  # behind: all or part of it was seen already
            behind = (1 << 32) - ahead
            self.retransmitted += min(behind, size)
            if behind < size:
                self._take(payload[behind:])
        else:
            self.gaps += 1
            self.framer.stop('gap')
            self.bytes += ahead
            self._next = seq
            self._take(payload)

    def frozen(self) -> Direction:
        clone = _clone(self)
        clone.framer = self.framer.frozen()
        return clone

    def _take(self, payload) -> None:
        self.bytes += len(payload)
        self._next = (self._next + len(payload)) & 0xFFFFFFFF
        if self.framer.framing:
            self.framer.feed(payload)


_ids = itertools.count(1)


@dataclass
class Connection:
    """One TCP connection: ``client`` opened it (sent the SYN) to ``server``; ``up`` is client to server."""

    client: tuple[str, int]
    server: tuple[str, int]
    id: int = field(default_factory=lambda: next(_ids))
    syn_seen: bool = True
    closed: bool = False
    version: int = 0
    """Packets seen: a snapshot copies the connection again only when this changed."""
    opened: float = field(default_factory=time.time)
    up: Direction = field(default_factory=Direction)
    down: Direction = field(default_factory=Direction)

    def frozen(self) -> Connection:
        """A copy that the capture thread will not change (what :meth:`Capture.snapshot` returns)."""
        clone = _clone(self)
        clone.up, clone.down = self.up.frozen(), self.down.frozen()
        return clone

    @property
    def protocol(self) -> str:
        """``tcpros``, ``http`` (XML-RPC) or ``unknown`` (not framed from its start)."""
        state = self.up.framer.state
        if state == 'http':
            return 'http'
        if self.up.framer.fields:
            return 'tcpros'
        return 'unknown'

    @property
    def fields(self) -> dict[str, str]:
        """The client's TCPROS connection header (``callerid``, ``service`` or ``topic``, ...)."""
        return self.up.framer.fields

    @property
    def kind(self) -> str:
        """``service``, ``topic``, ``http`` or ``unknown``."""
        if self.protocol == 'http':
            return 'http'
        if 'service' in self.fields:
            return 'service'
        if 'topic' in self.fields:
            return 'topic'
        return 'unknown'

    @property
    def name(self) -> str:
        """The service or topic it carries ('' if not TCPROS)."""
        return self.fields.get('service') or self.fields.get('topic') or ''

    @property
    def caller(self) -> str:
        return self.fields.get('callerid', '')

    @property
    def bytes(self) -> int:
        return self.up.bytes + self.down.bytes

    @property
    def header_bytes(self) -> int:
        """Both connection headers' bytes (length prefixes included)."""
        return self.up.framer.header_bytes + self.down.framer.header_bytes


def delta(before: dict[int, Connection], after: dict[int, Connection]) -> list[tuple[Connection, int, int]]:
    """(connection, up bytes, down bytes) sent between two :meth:`Capture.snapshot` s, for every
    connection that carried any (connections new since ``before`` count from zero)."""
    changed = []
    for key, connection in after.items():
        old = before.get(key)
        up = connection.up.bytes - (old.up.bytes if old else 0)
        down = connection.down.bytes - (old.down.bytes if old else 0)
        if up or down:
            changed.append((connection, up, down))
    return changed


class Capture:
    """A thread counting every TCP connection on ``interface`` that touches one of ``ports``.

    :param ports: the ports of interest (a set the caller may grow while capturing: ports
        of nodes started later), or None for every connection.
    :param buffer_bytes: the socket's receive buffer (SO_RCVBUFFORCE, as root): bursts of
        frames must not overflow it (overflows are counted in :attr:`drops`).

    Use as a context manager; :meth:`flush` before :meth:`snapshot`.
    """

    def __init__(self, ports: set[int] | None = None, interface: str = 'lo', buffer_bytes: int = 128 << 20):
        self.ports = ports
        self.interface = interface
        self.buffer_bytes = buffer_bytes
        self.drops = 0
        """Packets the kernel dropped because the capture fell behind (PACKET_STATISTICS)."""
        self.ignored = 0
        """IPv4/TCP packets on ports not of interest."""
        self.error: BaseException | None = None
        self._active: dict[tuple, Connection] = {}
        self._all: dict[int, Connection] = {}
        self._frozen: dict[int, Connection] = {}  # the last snapshot's copies, reused while unchanged
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._markers_seen: set[bytes] = set()
        self._marker_event = threading.Condition(self._lock)
        self._sock: socket.socket | None = None
        self._marker: socket.socket | None = None
        self._thread: threading.Thread | None = None

    # -- lifecycle -------------------------------------------------------------------------------
    def start(self) -> Capture:
        sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.ntohs(ETH_P_ALL))
        try:
            try:
                sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, self.buffer_bytes)
            except PermissionError:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.buffer_bytes)
            sock.bind((self.interface, 0))
            sock.settimeout(0.1)
            self._packet_statistics(sock)  # reading resets the kernel's counters
            marker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            marker.bind(('127.0.0.1', 0))
        except BaseException:
            sock.close()
            raise
        self._sock, self._marker = sock, marker
        self._thread = threading.Thread(target=self._run, name='wire-capture', daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        for sock in (self._sock, self._marker):
            if sock is not None:
                sock.close()
        self._sock = self._marker = None

    def __enter__(self) -> Capture:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # -- reading -------------------------------------------------------------------------------
    def check(self) -> None:
        """:raises CaptureError: if the capture thread has died (with its exception) or stopped."""
        if self.error is not None:
            raise CaptureError(
                f'capture thread died: {type(self.error).__name__}: {self.error}'
            ) from self.error
        if self._thread is None or not self._thread.is_alive():
            raise CaptureError('capture is not running')

    def flush(self, timeout: float = 10.0) -> None:
        """Return once every packet sent before this call has been counted.

        :raises CaptureError: if the thread died, or the marker was not seen within ``timeout``.
        """
        self.check()
        token = os.urandom(8)
        self._marker.sendto(b'drvs-wire-marker' + token, self._marker.getsockname())
        deadline = time.monotonic() + timeout
        with self._marker_event:
            while token not in self._markers_seen:
                left = deadline - time.monotonic()
                if self.error is not None or left <= 0:
                    break
                self._marker_event.wait(min(left, 0.2))
            seen = token in self._markers_seen
            self._markers_seen.discard(token)
        self._marker.setblocking(False)
        try:
            while True:
                self._marker.recv(64)
        except BlockingIOError:
            pass
        self.check()
        if not seen:
            raise CaptureError(f'capture did not see its own marker within {timeout:g} s')

    def snapshot(self, ports: Collection[int] | None = None) -> dict[int, Connection]:
        """A copy of every connection seen so far, by id (call :meth:`flush` first); with ``ports``,
        of those whose client or server port is one of them (lo carries others' traffic). The copies
        are shared between snapshots while their connection is unchanged: do not modify them."""
        self.check()
        with self._lock:
            copies = {}
            for key, connection in self._all.items():
                if (
                    ports is not None
                    and connection.server[1] not in ports
                    and connection.client[1] not in ports
                ):
                    continue
                cached = self._frozen.get(key)
                if cached is None or cached.version != connection.version:  # changed since the last one
                    cached = self._frozen[key] = connection.frozen()
                copies[key] = cached
            return copies

    @property
    def tracked(self) -> int:
        """How many connections the capture has seen."""
        return len(self._all)

    # -- the thread --------------------------------------------------------------------------------
    @staticmethod
    def _packet_statistics(sock: socket.socket) -> int:
        _, drops = struct.unpack('II', sock.getsockopt(SOL_PACKET, PACKET_STATISTICS, 8))
        return drops

    def _run(self) -> None:
        buffer = bytearray(1 << 18)
        view = memoryview(buffer)
        sock = self._sock
        last_stats = time.monotonic()
        try:
            while not self._stop.is_set():
                try:
                    size, address = sock.recvfrom_into(buffer)
                except TimeoutError:
                    size = 0
                if size and address[2] == PACKET_HOST:
                    with self._lock:
                        self._packet(view[:size])
                now = time.monotonic()
                if now - last_stats > 0.5:
                    last_stats = now
                    self.drops += self._packet_statistics(sock)
            self.drops += self._packet_statistics(sock)
        except BaseException as error:  # noqa: BLE001 - kept and raised by check()
            self.error = error
        finally:
            with self._marker_event:
                self._marker_event.notify_all()

    def _packet(self, frame: memoryview) -> None:
        if len(frame) < 34 or frame[12] != 0x08 or frame[13] != 0x00:  # not IPv4
            return
        ip = frame[14:]
        ihl = (ip[0] & 0x0F) * 4
        total = (ip[2] << 8) | ip[3]
        protocol = ip[9]
        src = socket.inet_ntoa(ip[12:16])
        dst = socket.inet_ntoa(ip[16:20])
        segment = ip[ihl:total]
        if protocol == socket.IPPROTO_UDP:
            self._udp(segment)
            return
        if protocol != socket.IPPROTO_TCP or len(segment) < 20:
            return
        sport, dport, seq = struct.unpack_from('!HHI', segment)
        offset = (segment[12] >> 4) * 4
        flags = segment[13]
        if self.ports is not None and sport not in self.ports and dport not in self.ports:
            self.ignored += 1
            return
        payload = segment[offset:]
        a, b = (src, sport), (dst, dport)
        key = (a, b) if a < b else (b, a)
        connection = self._active.get(key)
        syn, ack, fin, rst = flags & 0x02, flags & 0x10, flags & 0x01, flags & 0x04
        if syn and not ack:  # a new connection: the sender is its client
            connection = Connection(client=a, server=b)
            connection.up.syn(seq)
            self._active[key] = connection
            self._all[connection.id] = connection
        elif connection is None:  # began before the capture: guess the client by the port of interest
            server_first = self.ports is not None and sport in self.ports and dport not in self.ports
            client, server = (b, a) if server_first else (a, b)
            connection = Connection(client=client, server=server, syn_seen=False)
            self._active[key] = connection
            self._all[connection.id] = connection
        direction = connection.up if a == connection.client else connection.down
        connection.version += 1
        direction.packets += 1
        direction.ip_bytes += total
        if syn and ack:
            direction.syn(seq)
        if payload:
            direction.data(seq, payload)
            if direction is connection.up and connection.up.framer.fields:
                connection.down.framer.response = 'service' in connection.up.framer.fields
        if fin or rst:
            connection.closed = True

    def _udp(self, segment: memoryview) -> None:
        if self._marker is None or len(segment) < 8:
            return
        (dport,) = struct.unpack_from('!H', segment, 2)
        if dport != self._marker.getsockname()[1]:
            return
        data = bytes(segment[8:])
        if data.startswith(b'drvs-wire-marker'):
            self._markers_seen.add(data[len(b'drvs-wire-marker') :])
            self._marker_event.notify_all()


def node_ports(
    master_uri: str, caller_id: str = '/drvs_wire_bench', known: Collection[str] = ()
) -> dict[str, dict[str, int]]:
    """Each node's listening ports, from the master: ``{node: {'xmlrpc': port, 'tcpros': port}}``.

    rospy serves every service and topic of a node on one TCPROS port: the port of any
    of its services (every rospy node has ``~get_loggers``). The master itself is
    ``{'/master': {'xmlrpc': port}}``. Nodes in ``known`` are not looked up (nor listed).
    """
    from urllib.parse import urlparse

    with xmlrpc.client.ServerProxy(master_uri) as master:
        _, _, state = master.getSystemState(caller_id)
        nodes = {node for group in state for _, members in group for node in members}
        services = {node: name for name, members in state[2] for node in members}
        ports = {'/master': {'xmlrpc': urlparse(master_uri).port}}
        for node in sorted(nodes - set(known)):
            code, _, uri = master.lookupNode(caller_id, node)
            if code != 1:
                continue
            entry = {'xmlrpc': urlparse(uri).port}
            if node in services:
                code, _, service_uri = master.lookupService(caller_id, services[node])
                if code == 1:
                    entry['tcpros'] = urlparse(service_uri.replace('rosrpc://', 'http://')).port
            ports[node] = entry
    return ports
