"""How the DRVS server's forwards reach the vision systems: the ROS side of :mod:`drvs.ros.server`.

A robot's request leaves once its acknowledgement is written (:class:`ReplyFirstService`),
serialised once for every vision system of a site (:class:`Outgoing`); :class:`Forwarder` sends
what the dispatcher hands it and settles each outcome against the registry. A vision system of
another site is called at its address, and told the callback service's (:mod:`drvs.server.sites`).
The life of a request and of a watch is in docs/architecture.md; sites in docs/registry.md.
"""

from __future__ import annotations

import copy
import io
import time
from collections.abc import Callable

import rosgraph.names
import rospy

from drvs.common.client_cache import ClosingCache
from drvs.common.counters import Counters
from drvs.common.status import Refusal, name
from drvs.ros.conversions import box_to_msg
from drvs.ros.node import debug_logged
from drvs.ros.service_client import ReplyLoop, ServiceCallError, ServiceClient
from drvs.server.fusion import Delivery
from drvs.server.registry import Registration, Registry
from drvs.server.sites import callback_uri, direct_uri
from drvs.server.watch_table import ONE_SHOT, WITHDRAWAL, Forward, Watch
from drvs.srv import (
    DetectObjectBoundary,
    DetectObjectBoundaryRequest,
    WatchObjectBoundary,
    WatchObjectBoundaryRequest,
)

__all__ = [
    'Forwarder',
    'Outgoing',
    'ReplyFirstService',
    'one_shot_request',
    'watch_request',
    'watch_service_of',
]

MAX_WATCH_CLIENTS = 4096
"""Connections to vision systems' watch services kept open (one per vision system)."""
WATCH_CLIENT_IDLE = 120.0
"""Seconds a watch service connection may stay unused before it is closed."""


class ReplyFirstService(rospy.Service):
    """A ``rospy.Service`` that calls ``after_reply()`` once each reply is written.

    rospy writes a handler's reply when the handler returns. Work the handler starts
    at once (the server's forwards) would compete with that write for the
    interpreter, and the caller would wait longer for its acknowledgement; so the
    handler only queues, and ``after_reply``, run on the same thread once the reply
    is out (or failed), sends. This overrides ``ServiceImpl._handle_request``,
    rospy's per-request step (ROS 1 Noetic's rospy, the last ROS 1 release).
    """

    def __init__(self, name: str, service_class, handler, after_reply):
        self._after_reply = after_reply  # before rospy.Service registers: a call may come at once
        super().__init__(name, service_class, handler)

    def _handle_request(self, transport, request) -> None:
        try:
            super()._handle_request(transport, request)
        finally:
            self._after_reply()


class Outgoing:
    """A robot's request on its way to the vision systems: serialised once for those of this site,
    once for those of other sites (with ``callback_uri``, the address of its callback service)."""

    __slots__ = ('request', 'on_answer', 'callback_uri', '_data', '_remote_data')

    def __init__(self, request: DetectObjectBoundaryRequest, on_answer=None, callback_uri: str = ''):
        self.request = request
        self.on_answer = on_answer  # called with (vision system, its answer or None) when settled
        self.callback_uri = callback_uri
        self._data: bytes | None = None
        self._remote_data: bytes | None = None

    def serialized(self, remote: bool = False) -> bytes:
        """The request's bytes, for a vision system of another site with ``callback_uri`` filled
        in (two threads may make them at once: the same bytes)."""
        if not remote:
            if self._data is None:
                self._data = _serialized(self.request)
            return self._data
        if self._remote_data is None:
            request = copy.copy(self.request)
            request.callback_uri = self.callback_uri
            self._remote_data = _serialized(request)
        return self._remote_data


def _serialized(request) -> bytes:
    buffer = io.BytesIO()
    request.serialize(buffer)
    return buffer.getvalue()


class Forwarder:
    """Sends the dispatcher's items — a robot's request (:class:`Outgoing`) or a watch's
    :class:`~drvs.server.watch_table.Forward` — and settles each outcome against the registry.

    :param forward_timeout: seconds one forward may take (connect, send, reply).
    :param counters: the server's counters (``forwards``, ``watch_forwards``,
        ``fallback_forwards``, ``forward_failures``).
    :param on_removed: called with the entry of a vision system removed after failed forwards.
    :param on_undelivered: called with a watch forward that failed (the watch table sends it again).
    :param deliver: sends the fusion stage's callback to a robot (items of type
        :class:`~drvs.server.fusion.Delivery`, queued for the robot's callback service).
    :param on_refused: called with a fused watch's forward and the vision system's refusal.
    :param site: this server's site (:mod:`drvs.server.sites`).
    :param resolve_callback: ``resolve_callback(service)``: the ``rosrpc://`` address of a callback
        service on this server's master, for a watch's forward to a vision system of another site;
        raises :class:`~drvs.common.status.Refusal` when it cannot.
    """

    def __init__(
        self,
        forward_timeout: float,
        registry: Registry,
        counters: Counters,
        on_removed: Callable[[Registration], None],
        on_undelivered: Callable[[Forward], None],
        deliver: Callable[[Delivery], None] | None = None,
        on_refused: Callable[[Forward, object], None] | None = None,
        site: str = '',
        resolve_callback: Callable[[str], str] | None = None,
    ):
        self.site = site
        self.resolve_callback = resolve_callback
        self.deliver = deliver
        self.on_refused = on_refused
        self.forward_timeout = forward_timeout
        self.registry = registry
        self.counters = counters
        self.on_removed = on_removed
        self.on_undelivered = on_undelivered
        self.replies = ReplyLoop('forward-replies')  # waits for the replies of forwards in flight
        self.watch_clients = ClosingCache(self._make_watch_client, MAX_WATCH_CLIENTS, WATCH_CLIENT_IDLE)

    def start(self) -> None:
        self.replies.start()

    def stop(self, timeout: float) -> None:
        """Fail the forwards in flight and close the watch services' connections."""
        self.replies.stop(timeout=timeout)
        self.watch_clients.clear()

    def make_client(self, service: str, uri: str | None = None) -> ServiceClient:
        """The connection to a vision system's DetectObjectBoundary (no I/O until used); ``uri``: its
        address, for one of another site (our master does not know it)."""
        return ServiceClient(
            service, DetectObjectBoundary, self.forward_timeout, caller_id=rospy.get_name(), uri=uri
        )

    def _make_watch_client(self, key: tuple[str, str | None]) -> ServiceClient:
        """The connection to a watch service (its name, and its address at another site: the address
        of the vision system's DetectObjectBoundary, as a ROS node serves all its services on one port)."""
        service, uri = key
        return ServiceClient(
            service, WatchObjectBoundary, self.forward_timeout, caller_id=rospy.get_name(), uri=uri
        )

    def _callback_uri(self, entry: Registration, callback_service: str) -> str | None:
        """The ``callback_uri`` of a watch's forward to ``entry``: '' at this site, the callback
        service's address at another; None when it cannot be resolved (the forward waits)."""
        if direct_uri(self.site, entry.site, entry.instance) is None or self.resolve_callback is None:
            return ''
        try:
            return callback_uri(self.site, entry.site, self.resolve_callback(callback_service))
        except Refusal as refusal:
            rospy.logwarn(
                'cannot forward to %s at site %s: its callback %s: %s',
                entry.service_name,
                entry.site,
                callback_service,
                refusal.message,
            )
            return None

    def begin(self, destination: str, item, done) -> bool:
        """Send a robot's request without waiting (the dispatcher's ``begin``, on whichever thread
        has it: the handler's after its reply, or the one that saw the previous forward end); the
        reply loop settles it. False for what a worker must do: watch forwards, one-shots, and a
        request to a vision system without an open connection."""
        if isinstance(item, Forward | Delivery):
            return False
        entry = self.registry.get(destination)
        if entry is None or entry.client is None:
            return False  # removed while queued: the worker drops it
        client, started = entry.client, time.monotonic()

        def settled(answer, error) -> None:
            answer = self._settle(
                destination, client, f'forward of {item.request.request_id!r}', started, answer, error
            )
            if item.on_answer is not None:
                item.on_answer(destination, answer)
            done()

        remote = direct_uri(self.site, entry.site, entry.instance) is not None
        if not client.start(item.request, self.replies, settled, serialized=item.serialized(remote)):
            return False
        self.counters.add(forwards=1)
        return True

    def send(self, destination: str, item) -> None:
        """Send one queued item on a worker, blocking: a robot's request, a watch's :class:`Forward`,
        or a fused callback to a robot (:class:`~drvs.server.fusion.Delivery`)."""
        if isinstance(item, Delivery):
            if self.deliver is not None:
                self.deliver(item)
            return
        if isinstance(item, Forward) and item.kind != ONE_SHOT:
            self._send_watch(destination, item)
            return
        entry = self.registry.get(destination)
        if entry is None or entry.client is None:  # removed while the forward was queued
            return
        if isinstance(item, Forward):
            uri = self._callback_uri(entry, item.watch.forwarded()[0])
            if uri is None:
                return  # the watch table sends the next one-shot when it is due
            self.counters.add(forwards=1, fallback_forwards=1)
            what = f'one-shot of watch {item.watch.request_id!r}'
            answer = self._call(destination, entry.client, one_shot_request(item.watch, uri), what)
            if answer is not None and not answer.accepted and item.watch.forward_as and self.on_refused:
                self.on_refused(item, answer)
        else:
            self.counters.add(forwards=1)
            what = f'forward of {item.request.request_id!r}'
            remote = direct_uri(self.site, entry.site, entry.instance) is not None
            answer = self._call(destination, entry.client, item.request, what, item.serialized(remote))
            if item.on_answer is not None:
                item.on_answer(destination, answer)

    def _send_watch(self, destination: str, forward: Forward) -> None:
        service = forward.vision_system
        entry = self.registry.get(service)
        if entry is None and forward.kind != WITHDRAWAL:  # removed while queued
            return
        uri, route = '', None
        if entry is not None:
            route = direct_uri(self.site, entry.site, entry.instance)
        if entry is not None:
            resolved = self._callback_uri(entry, forward.watch.forwarded()[0])
            if resolved is None and forward.kind != WITHDRAWAL:
                self.on_undelivered(forward)
                return
            uri = resolved or ''  # a withdrawal names the watch as it stands (its watch ends anyway)
        self.counters.add(watch_forwards=1)
        what = f'{forward.kind} of watch {forward.watch.request_id!r}'
        client = self.watch_clients.get((destination, route))
        answer = self._call(service, client, watch_request(forward, uri), what)
        if answer is None:
            self.on_undelivered(forward)
        elif not answer.accepted:
            rospy.logwarn('%s refused by %s (%s): %s', what, destination, name(answer.status), answer.message)
            if forward.watch.forward_as and self.on_refused is not None:
                self.on_refused(forward, answer)

    def _call(self, service: str, client: ServiceClient, request, what: str, serialized: bytes | None = None):
        """Send ``request`` (its bytes ``serialized`` if known) through ``client``, blocking; its answer,
        or None when it failed (:meth:`_settle`)."""
        started = time.monotonic()
        try:
            answer = client.call(request, serialized)
        except ServiceCallError as error:
            return self._settle(service, client, what, started, None, error)
        return self._settle(service, client, what, started, answer, None)

    def _settle(self, service: str, client: ServiceClient, what: str, started: float, answer, error):
        """The outcome of a call to the vision system ``service``: ``answer``, or None after ``error``.

        A failure counts against the registered vision system ``service`` (and may remove
        and eject it, :meth:`Registry.record_failure`); a success clears its failures. A
        call to a vision system no longer registered (a withdrawal) counts for neither.
        """
        if error is not None:
            self.counters.add(forward_failures=1)
            if service not in self.registry:
                rospy.loginfo('%s to %s failed (no longer registered): %s', what, client.service, error)
                return None
            failures = self.registry.failures(service) + 1
            rospy.logwarn('%s to %s failed (%d in a row): %s', what, client.service, failures, error)
            removed = self.registry.record_failure(service)
            if removed is not None:
                rospy.logwarn(
                    'removed %s after %d failed forwards in a row; ejected for %.0f s',
                    service,
                    failures,
                    (self.registry.ejected_until(service) or time.monotonic()) - time.monotonic(),
                )
                self.on_removed(removed)
            return None
        if service in self.registry:
            self.registry.record_success(service)
        if debug_logged():
            rospy.logdebug(
                '%s to %s in %.1f ms: status %s %s',
                what,
                client.service,
                (time.monotonic() - started) * 1000,
                name(answer.status),
                answer.message,
            )
        return answer


def watch_service_of(service: str) -> str:
    """The watch service of the vision system whose DetectObjectBoundary is ``service``: its sibling.

    >>> watch_service_of('/cam1/detect_object_boundary')
    '/cam1/watch_object_boundary'
    """
    return rosgraph.names.ns_join(rosgraph.names.namespace(service), 'watch_object_boundary')


def one_shot_request(watch: Watch, callback_uri: str = '') -> DetectObjectBoundaryRequest:
    """The DetectObjectBoundary request that serves ``watch`` once, to a vision system without watches
    (``callback_uri``: the callback service's address, for one of another site)."""
    callback_service, request_id = watch.forwarded()
    return DetectObjectBoundaryRequest(
        algorithm=watch.algorithm,
        region_of_interest=box_to_msg(watch.region),
        callback_service=callback_service,
        request_id=request_id,
        fused=watch.forward_as is not None,
        callback_uri=callback_uri,
    )


def watch_request(forward: Forward, callback_uri: str = '') -> WatchObjectBoundaryRequest:
    """The WatchObjectBoundary forward of ``forward`` (a new watch, a renewal or a withdrawal;
    ``callback_uri``: the callback service's address, for a vision system of another site)."""
    watch = forward.watch
    callback_service, request_id = watch.forwarded()
    return WatchObjectBoundaryRequest(
        algorithm=watch.algorithm,
        region_of_interest=box_to_msg(watch.region),
        callback_service=callback_service,
        request_id=request_id,
        period=watch.period,
        duration=forward.duration,
        changes_only=watch.changes_only and watch.forward_as is None,  # fusion wants every frame
        fused=watch.forward_as is not None,
        callback_uri=callback_uri,
    )
