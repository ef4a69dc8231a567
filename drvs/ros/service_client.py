"""A ROS service client with a timeout on every call and a persistent connection that heals.

rospy's ``ServiceProxy`` has no call timeout (ros/ros_comm#152) and a persistent proxy never
reconnects after the far side restarts. :class:`ServiceClient` speaks TCPROS itself
(:mod:`drvs.ros.tcpros`, every step against the call's deadline) and reconnects after any
failure; :meth:`ServiceClient.start` sends without waiting and leaves the reply to a
:class:`ReplyLoop`, one thread for every call in flight. Why, and what it costs: docs/design.md.

>>> from drvs.srv import DetectObjectBoundary
>>> client = ServiceClient('/vs1/detect_object_boundary', DetectObjectBoundary, timeout=2.0)
>>> client.close()  # nothing connected yet: constructing does no I/O
"""

from __future__ import annotations

import heapq
import io
import itertools
import logging
import math
import select
import socket
import struct
import threading
import time
from collections.abc import Callable

import rospy

from drvs.ros.tcpros import (
    Deadline,
    MasterUnreachable,
    ServiceCallError,
    ServiceInfo,
    TimeoutTransport,
    UnknownService,
    connect,
    framed,
    handshake,
    lookup_service,
    probe_service,
    recv_exactly,
    recv_some,
    send,
)

logger = logging.getLogger('rosout.' + __name__)

__all__ = [  # the wire steps' names too, so that callers need one import
    'MasterUnreachable',
    'ReplyLoop',
    'ServiceCallError',
    'ServiceClient',
    'ServiceInfo',
    'TimeoutTransport',
    'UnknownService',
    'lookup_service',
    'probe_service',
]

MAX_RESPONSE_BYTES = 1 << 30
REPLY_CHUNK = 1 << 16
"""Bytes asked for by the first read of a reply (a DRVS reply is a few dozen)."""


class ServiceClient:
    """Calls one service over a persistent TCPROS connection, with a timeout per call.

    :param service: the service's global name.
    :param service_class: its generated class (e.g. ``drvs.srv.DetectObjectBoundary``).
    :param timeout: seconds one :meth:`call` may take in all: waiting for another
        thread's call on this client, master lookup, connecting, sending, waiting
        for the reply.
    :param master_uri: the master to ask (default: ROS_MASTER_URI).
    :param caller_id: the id sent in the handshake (default: this node's name).
    :param uri: the service's ``rosrpc://host:port`` address, to connect to without asking a
        master (a service at another site, which our master does not know); default: look
        ``service`` up on the master at every connection.

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
        uri: str | None = None,
    ):
        if timeout <= 0:
            raise ValueError(f'timeout: must be positive, got {timeout}')
        self.service = service
        self.service_class = service_class
        self.timeout = float(timeout)
        self.master_uri = master_uri
        self.caller_id = caller_id
        self.uri = uri
        self.header: dict[str, str] = {}  # the service's handshake header on the current connection
        self._lock = threading.Lock()
        self._sock: socket.socket | None = None
        self._connections = 0

    @property
    def connections(self) -> int:
        """How many connections this client has opened (1 while all goes well)."""
        return self._connections

    def call(self, request, serialized: bytes | None = None):
        """Send ``request``; return the response. ``serialized``: the request's bytes, if the
        caller has them already (e.g. to count them), sent as they are.

        :raises ServiceCallError: naming the service and what failed (unknown
            service, connection refused, timed out after X s, the service's error
            message, ...). The connection is dropped; the next call reconnects.
        """
        deadline = Deadline(self.service, self.timeout)
        if not self._lock.acquire(timeout=deadline.left()):
            raise ServiceCallError(
                f'service {self.service}: timed out after {self.timeout:g} s waiting for an earlier call'
            )
        try:
            try:
                return self._call(request, deadline, serialized)
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
        poller = select.poll()
        poller.register(self._sock, select.POLLIN)
        return bool(poller.poll(0))

    def _open(self, deadline: Deadline) -> None:
        uri = self.uri or lookup_service(self.service, deadline.left(), self.master_uri, self.caller_id)
        sock = connect(self.service, uri, deadline)
        try:
            fields = {
                'callerid': self.caller_id or rospy.get_caller_id(),
                'service': self.service,
                'md5sum': self.service_class._md5sum,
                'type': self.service_class._type,
                'persistent': '1',
            }
            header = handshake(sock, fields, deadline)
        except BaseException:
            sock.close()
            raise
        self._sock = sock
        self.header = header
        self._connections += 1

    def _call(self, request, deadline: Deadline, serialized: bytes | None = None):
        if self._sock is not None and self._stale():
            self._disconnect()
        if self._sock is None:
            self._open(deadline)
        data = self._serialize(request) if serialized is None else framed(serialized)
        send(self._sock, data, deadline, 'request')
        # Usually the whole reply comes in one piece: read what is there, then the rest.
        received = recv_some(self._sock, REPLY_CHUNK, deadline, 'reply')
        if len(received) < 5:
            received += recv_exactly(self._sock, 5 - len(received), deadline, 'reply')
        size = self._reply_size(received)
        if len(received) < 5 + size:
            received += recv_exactly(self._sock, 5 + size - len(received), deadline, 'reply')
        return self._response(received)

    def _serialize(self, request) -> bytes:
        """The request as TCPROS sends it: its length, then its bytes."""
        buffer = io.BytesIO()
        buffer.write(b'\0\0\0\0')
        try:
            request.serialize(buffer)
        except (struct.error, TypeError, ValueError, AttributeError, OverflowError) as error:
            raise ServiceCallError(f'service {self.service}: cannot serialise the request: {error}') from None
        data = buffer.getbuffer()
        struct.pack_into('<I', data, 0, len(data) - 4)
        return bytes(data)

    def _reply_size(self, received) -> int:
        """The size of the reply whose first 5 bytes (ok byte, length) are ``received``'s.

        :raises ServiceCallError: too large, or more bytes than the reply (the connection is out of step).
        """
        (size,) = struct.unpack_from('<I', received, 1)
        if size > MAX_RESPONSE_BYTES:
            raise ServiceCallError(f'service {self.service}: reply of {size} bytes is too large')
        if len(received) > 5 + size:
            raise ServiceCallError(
                f'service {self.service}: {len(received) - 5 - size} bytes after the reply of {size} bytes'
            )
        return size

    def _response(self, received):
        """The response in a complete reply (ok byte, length, payload).

        :raises ServiceCallError: the service answered with an error, or the payload does not deserialise.
        """
        payload = bytes(received[5:])
        if not received[0]:
            text = payload.decode('utf-8', errors='replace')
            raise ServiceCallError(f'service {self.service}: the service answered with an error: {text}')
        response = self.service_class._response_class()
        try:
            response.deserialize(payload)
        except Exception as error:  # genpy raises DeserializationError, struct.error, ...
            raise ServiceCallError(f'service {self.service}: cannot deserialise the reply: {error}') from None
        return response

    # -- calls that do not wait ----------------------------------------------------------------
    def start(
        self,
        request,
        loop: ReplyLoop,
        done: Callable[[object, ServiceCallError | None], None],
        serialized: bytes | None = None,
    ) -> bool:
        """Send ``request`` (``serialized``: its bytes, if known) without waiting for the reply:
        ``loop`` waits and calls ``done(response, None)``, or ``done(None, error)`` with the error
        :meth:`call` would raise, once (on its thread), within ``timeout`` seconds of now.

        Only on an open connection that no other call uses: returns False, having sent
        nothing and with ``done`` never to be called, when the client has no connection
        (or a stale one, now closed), another call is in flight, ``loop`` is not running or
        the request could not be sent at once; :meth:`call` then does it all, blocking.
        """
        if not loop.running or not self._lock.acquire(blocking=False):
            return False
        try:
            if self._sock is not None and self._stale():
                self._disconnect()
            if self._sock is None:
                self._lock.release()
                return False
            deadline = Deadline(self.service, self.timeout)
            data = self._serialize(request) if serialized is None else framed(serialized)
            sent = self._sock.send(data)
        except (ServiceCallError, OSError):  # nothing went out (or a part: the connection is unusable)
            self._disconnect()
            self._lock.release()
            return False
        except BaseException:
            self._disconnect()
            self._lock.release()
            raise
        loop.add(_InFlight(self, memoryview(data)[sent:], deadline, done))
        return True


class _InFlight:
    """A call sent by :meth:`ServiceClient.start`: what is left to send, what came back, when it ends.

    It holds its client's lock until it is over; :meth:`finish` releases it.
    """

    __slots__ = ('client', 'sock', 'unsent', 'received', 'deadline', 'done', 'over')

    def __init__(self, client: ServiceClient, unsent: memoryview, deadline: Deadline, done):
        self.client = client
        self.sock = client._sock
        self.unsent = unsent
        self.received = bytearray()
        self.deadline = deadline
        self.done = done
        self.over = False

    def events(self) -> int:
        return select.POLLIN | (select.POLLOUT if self.unsent else 0)

    def step(self):
        """Send or read what the socket allows: the response once the reply is complete, else None.

        :raises ServiceCallError: as :meth:`ServiceClient.call` would.
        """
        name = self.client.service
        if self.unsent:
            try:
                self.unsent = self.unsent[self.sock.send(self.unsent) :]
            except BlockingIOError:
                pass
            except OSError as error:
                raise ServiceCallError(
                    f'service {name}: connection failed sending the request: {error}'
                ) from None
        try:
            chunk = self.sock.recv(REPLY_CHUNK)
        except BlockingIOError:
            return None
        except OSError as error:
            raise ServiceCallError(
                f'service {name}: connection failed while reading the reply: {error}'
            ) from None
        if not chunk:
            raise ServiceCallError(f'service {name}: connection closed by the service before the reply')
        if self.unsent:
            raise ServiceCallError(f'service {name}: the service answered before the whole request was sent')
        self.received += chunk
        if len(self.received) < 5 or len(self.received) < 5 + self.client._reply_size(self.received):
            return None
        return self.client._response(self.received)

    def finish(self, response, error: ServiceCallError | None) -> None:
        """The call is over: free the client (closing its connection after an error), then ``done``."""
        self.over = True
        if error is not None:
            self.client._disconnect()
        self.client._lock.release()
        try:
            self.done(response, error)
        except Exception:
            logger.exception('the callback of a call to %s failed', self.client.service)


class ReplyLoop:
    """One thread that waits for the replies of the calls :meth:`ServiceClient.start` sent.

    It polls their sockets (and one of its own, to hear of new calls), reads each reply
    as it comes, fails a call whose deadline passed, and runs each call's callback on its
    thread: callbacks should be short and must not wait for a call this loop carries. (A
    thread per call in flight, each waking for its reply and fighting the others for the
    interpreter lock, cost the DRVS server more than the calls themselves.)
    """

    def __init__(self, name: str = 'service-replies'):
        self.name = name
        self._lock = threading.Lock()  # guards _added, _polling, _stopping
        self._added: list[_InFlight] = []
        self._polling = False  # the thread is in poll(): new calls must wake it
        self._stopping = False
        self._wake_read, self._wake_write = socket.socketpair()
        self._wake_read.setblocking(False)
        self._wake_write.setblocking(False)
        self._thread: threading.Thread | None = None

    @property
    def running(self) -> bool:
        return self._thread is not None and not self._stopping

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        """Fail every call still in flight ("shutting down") and stop the thread."""
        with self._lock:
            self._stopping = True
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():  # stuck in a callback: it closes nothing under the thread's feet
                logger.warning('the reply loop %s did not stop within %g s', self.name, timeout)
                return
        self._wake_read.close()
        self._wake_write.close()

    def add(self, call: _InFlight) -> None:
        with self._lock:
            self._added.append(call)
            polling = self._polling
        if polling:
            self._wake()

    def _wake(self) -> None:
        try:
            self._wake_write.send(b'.')
        except (BlockingIOError, OSError):
            pass  # full: it will wake anyway; closed: it has stopped

    def _run(self) -> None:
        self._poller = select.poll()
        self._poller.register(self._wake_read, select.POLLIN)
        self._calls: dict[int, _InFlight] = {}  # by socket
        self._deadlines: list[tuple[float, int, _InFlight]] = []  # heap; calls that are over are skipped
        self._order = itertools.count()
        while True:
            try:
                if not self._turn():
                    return
            except Exception as error:  # a bug: fail what is in flight rather than hang it
                logger.exception('the reply loop %s failed; the calls in flight fail, it goes on', self.name)
                for call in list(self._calls.values()):
                    self._end(call, None, ServiceCallError(f'service {call.client.service}: {error!r}'))
                if self._stopping:
                    return

    def _turn(self) -> bool:
        """Take the new calls, wait for one of them to be ready, read what came; False once stopped."""
        with self._lock:
            added, self._added = self._added, []
            stopping = self._stopping
            self._polling = not stopping  # from here a new call wakes the poll below
        for call in added:
            self._calls[call.sock.fileno()] = call
            self._poller.register(call.sock, call.events())
            heapq.heappush(self._deadlines, (call.deadline.end, next(self._order), call))
        if stopping:
            for call in list(self._calls.values()):
                self._end(call, None, ServiceCallError(f'service {call.client.service}: shutting down'))
            return False
        deadlines = self._deadlines
        while deadlines and deadlines[0][2].over:
            heapq.heappop(deadlines)
        timeout = -1 if not deadlines else max(0, math.ceil((deadlines[0][0] - time.monotonic()) * 1000))
        events = self._poller.poll(timeout)
        with self._lock:
            self._polling = False
        wake = self._wake_read.fileno()
        for fd, _ in events:
            if fd == wake:
                self._drain()
                continue
            call = self._calls.get(fd)
            if call is None:
                continue
            try:
                response = call.step()
            except ServiceCallError as error:
                self._end(call, None, error)
                continue
            if response is not None:
                self._end(call, response, None)
            elif not call.unsent:
                self._poller.modify(call.sock, select.POLLIN)
        now = time.monotonic()
        while deadlines and (deadlines[0][2].over or deadlines[0][0] <= now):
            _, _, call = heapq.heappop(deadlines)
            if not call.over:
                self._end(
                    call,
                    None,
                    ServiceCallError(
                        f'service {call.client.service}: timed out after {call.deadline.timeout:g} s '
                        'waiting for the reply'
                    ),
                )
        return True

    def _end(self, call: _InFlight, response, error) -> None:
        if call.over:
            return
        fd = call.sock.fileno()
        if self._calls.pop(fd, None) is not None:
            self._poller.unregister(fd)
        call.finish(response, error)

    def _drain(self) -> None:
        try:
            while self._wake_read.recv(4096):
                pass
        except BlockingIOError:
            pass
