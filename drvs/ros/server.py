"""The DRVS server node: registry of vision systems, Algorithm 1 matching, concurrent forwarding.

Services (in the node's namespace; run it as ``__name:=drvs``):

- ``~register_vision_service`` (drvs/RegisterVisionService): a vision system
  registers, moves (new field of view) or renews its entry; an empty field of
  view unregisters. Refused, with a message naming the problem, when the
  polygon is invalid (fewer than 3 vertices, a coordinate not finite, zero
  area, self-intersecting), the service is unknown to the master or not a
  drvs/DetectObjectBoundary, or the caller is not the node that provides it.
- ``~detect_object_boundary`` (drvs/DetectObjectBoundary): a robot's request.
  Validated (algorithm through :func:`drvs.algorithms.parse_algorithm`, region
  of interest, callback service: a global name, known to the master, of type
  drvs/CallbackCoordinates), matched against the registry, queued for every
  matching vision system, and acknowledged at once with ``vision_systems`` set.
  Forwards carry every field unchanged; they run on a bounded pool of workers,
  one persistent connection per vision system (:class:`ServiceClient`, re-created
  after a failure), each call limited to ``~forward_timeout``.

Topic: ``~registry`` (std_msgs/String, latched): JSON
``{"vision_systems": [{"service_name": ..., "provider": ..., "field_of_view": [[x, y], ...]}, ...]}``
sorted by name, republished after every change (registration, move,
unregistration, expiry, removal; not renewals), at most once per
``~registry_period``.

Parameters:

- ``~lease`` (s, default 10): a registration lasts this long unless renewed.
- ``~max_failures`` (default 3): consecutive failed forwards that remove a vision system.
- ``~forward_timeout`` (s, default 2): limit on one forward (connect, send, reply).
- ``~workers`` (default 8): forwarding threads; a hung vision system holds at most one.
- ``~max_pending`` (default 1000): forwards queued or running in all; a request
  that would pass it is refused ("busy: ...") instead of queued.
- ``~max_pending_per_vision_system`` (default 10): a vision system with this
  many forwards waiting is skipped by new requests (not counted in ``vision_systems``).
- ``~check_timeout`` (s, default 1): limit on each master lookup / service probe
  made to validate a registration or a callback service.
- ``~callback_cache`` (s, default 5): how long a verified callback service is
  trusted before it is checked again.
- ``~registry_period`` (s, default 0.2): minimum time between two ``~registry`` messages.

Logs: info for register, move, unregister, expiry and removal; debug per forward.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass

import rosgraph.names
import rospy
from std_msgs.msg import String

from drvs.algorithms import AlgorithmError
from drvs.dispatch import Busy, Dispatcher
from drvs.registry import MOVED, NOT_REGISTERED, REGISTERED, RENEWED, UNREGISTERED, Registry
from drvs.ros.conversions import msg_to_box, polygon_to_points
from drvs.ros.params import read_params
from drvs.ros.service_client import ServiceCallError, ServiceClient, probe_service
from drvs.srv import (
    CallbackCoordinates,
    DetectObjectBoundary,
    DetectObjectBoundaryRequest,
    DetectObjectBoundaryResponse,
    RegisterVisionService,
    RegisterVisionServiceResponse,
)
from drvs.validation import ValidationError, field_of_view_polygon, request_fields, ros_name

__all__ = ['ServerSettings', 'DrvsServer']


@dataclass(frozen=True)
class ServerSettings:
    lease: float = 10.0
    max_failures: int = 3
    forward_timeout: float = 2.0
    workers: int = 8
    max_pending: int = 1000
    max_pending_per_vision_system: int = 10
    check_timeout: float = 1.0
    callback_cache: float = 5.0
    registry_period: float = 0.2

    def __post_init__(self):
        for name in ('lease', 'forward_timeout', 'check_timeout'):
            if not getattr(self, name) > 0:
                raise ValueError(f'~{name}: must be positive, got {getattr(self, name)}')
        for name in ('max_failures', 'workers', 'max_pending', 'max_pending_per_vision_system'):
            if getattr(self, name) < 1:
                raise ValueError(f'~{name}: must be at least 1, got {getattr(self, name)}')
        for name in ('callback_cache', 'registry_period'):
            if getattr(self, name) < 0:
                raise ValueError(f'~{name}: must not be negative, got {getattr(self, name)}')

    @classmethod
    def from_params(cls) -> ServerSettings:
        """Read every field from the node's private parameters (``~lease`` ...), defaults as above."""
        return read_params(cls)


def _refuse_register(message: str) -> RegisterVisionServiceResponse:
    rospy.logwarn('registration refused: %s', message)
    return RegisterVisionServiceResponse(accepted=False, message=message)


class DrvsServer:
    """The server's ROS glue; :meth:`start` creates the services, topic and threads."""

    def __init__(self, settings: ServerSettings):
        self.settings = settings
        self.registry = Registry(lease=settings.lease, max_failures=settings.max_failures)
        self.dispatcher = Dispatcher(
            self._forward,
            workers=settings.workers,
            max_pending=settings.max_pending,
            max_per_destination=settings.max_pending_per_vision_system,
        )
        self._lock = threading.Lock()  # guards _clients, _providers, _callbacks
        self._clients: dict[str, ServiceClient] = {}
        self._providers: dict[str, str] = {}  # service name -> caller id that registered it
        self._callbacks: dict[str, float] = {}  # verified callback service -> when verified
        self._changed = threading.Condition()
        self._dirty = True
        self._stopping = threading.Event()
        self._threads: list[threading.Thread] = []
        self._registry_publisher = None

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> None:
        self._registry_publisher = rospy.Publisher('~registry', String, queue_size=1, latch=True)
        self.dispatcher.start()
        for target, name in ((self._expire_loop, 'lease-expiry'), (self._publish_loop, 'registry-publisher')):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)
        rospy.Service('~register_vision_service', RegisterVisionService, self.handle_register)
        rospy.Service('~detect_object_boundary', DetectObjectBoundary, self.handle_detect)
        rospy.loginfo(
            'DRVS server ready: lease %g s, max_failures %d, forward_timeout %g s, %d workers',
            self.settings.lease,
            self.settings.max_failures,
            self.settings.forward_timeout,
            self.settings.workers,
        )

    def stop(self) -> None:
        self._stopping.set()
        with self._changed:
            self._changed.notify_all()
        self.dispatcher.stop(timeout=self.settings.forward_timeout + 1.0)
        with self._lock:
            clients = list(self._clients.values())
            self._clients.clear()
        for client in clients:
            client.close()

    # -- registration ------------------------------------------------------------------------
    def handle_register(self, request) -> RegisterVisionServiceResponse:
        caller = request._connection_header.get('callerid', '')
        try:
            ros_name('service_name', request.service_name)
        except ValidationError as error:
            return _refuse_register(str(error))
        name = rosgraph.names.resolve_name(request.service_name, caller or '/')
        points = polygon_to_points(request.field_of_view)
        with self._lock:
            provider = self._providers.get(name)
        if not points:
            if provider is not None and provider != caller:
                return _refuse_register(
                    f'service_name: {name} was registered by {provider}; {caller} may not unregister it'
                )
            return self._apply(name, points, caller)
        try:
            field_of_view_polygon(points)
        except ValidationError as error:
            return _refuse_register(f'{error} (service_name {name})')
        entry = self.registry.get(name)
        if entry is None or provider != caller:  # a renewal or move by the verified provider skips this
            problem = self._check_service(
                'service_name', name, DetectObjectBoundary, provider_must_be=caller or '(no caller id)'
            )
            if problem:
                return _refuse_register(problem)
        return self._apply(name, points, caller)

    def _apply(self, name: str, points: list, caller: str) -> RegisterVisionServiceResponse:
        try:
            change = self.registry.register(name, points)
        except ValidationError as error:
            return _refuse_register(f'{error} (service_name {name})')
        if change == UNREGISTERED:
            self._forget(name)
            rospy.loginfo('unregistered %s (asked by %s)', name, caller)
        elif change == NOT_REGISTERED:
            return RegisterVisionServiceResponse(accepted=True, message=f'{name} was not registered')
        else:
            with self._lock:
                self._providers[name] = caller
                if name not in self._clients:
                    self._clients[name] = ServiceClient(
                        name, DetectObjectBoundary, self.settings.forward_timeout, caller_id=rospy.get_name()
                    )
            if change == REGISTERED:
                rospy.loginfo('registered %s by %s: field of view %s', name, caller, points)
            elif change == MOVED:
                rospy.loginfo('moved %s: field of view %s', name, points)
            else:
                rospy.logdebug('renewed %s', name)
        if change != RENEWED:
            self._mark_changed()
        lease = f'; lease {self.settings.lease:g} s' if change in (REGISTERED, MOVED, RENEWED) else ''
        return RegisterVisionServiceResponse(accepted=True, message=f'{change} {name}{lease}')

    def _forget(self, name: str) -> None:
        """Drop everything the server holds for ``name`` once it left the registry."""
        dropped = self.dispatcher.drop(name)
        if dropped:
            rospy.loginfo('dropped %d queued forwards to %s', dropped, name)
        with self._lock:
            self._providers.pop(name, None)
            client = self._clients.pop(name, None)
        if client is not None:
            client.close()

    def _check_service(self, field: str, name: str, service_class, provider_must_be: str | None = None):
        """None if ``name`` is known to the master and of the expected type (and provider); else why not."""
        try:
            info = probe_service(name, self.settings.check_timeout, caller_id=rospy.get_name())
        except ServiceCallError as error:
            if 'unknown service' in str(error):
                return f'{field}: {name} is not known to the ROS master'
            return f'{field}: {name} cannot be reached: {error}'
        if info.type != service_class._type or info.md5sum != service_class._md5sum:
            return f'{field}: {name} is of type {info.type or "(unknown)"}, expected {service_class._type}'
        if provider_must_be is not None and info.provider != provider_must_be:
            return (
                f'{field}: {name} is provided by {info.provider}, not by the caller {provider_must_be}; '
                'a node may register only its own service'
            )
        return None

    # -- requests ----------------------------------------------------------------------------
    def handle_detect(self, request) -> DetectObjectBoundaryResponse:
        try:
            _, region = request_fields(
                request.algorithm, msg_to_box(request.region_of_interest), request.callback_service
            )
        except (AlgorithmError, ValidationError) as error:
            return self._refuse_detect(request, str(error))
        problem = self._check_callback(request.callback_service)
        if problem:
            return self._refuse_detect(request, problem)
        names = self.registry.match(region)
        if not names:
            return DetectObjectBoundaryResponse(
                accepted=True, message='no vision system covers the region of interest', vision_systems=0
            )
        forward = DetectObjectBoundaryRequest(
            algorithm=request.algorithm,
            region_of_interest=request.region_of_interest,
            callback_service=request.callback_service,
            request_id=request.request_id,
        )
        try:
            accepted, skipped = self.dispatcher.submit(names, forward)
        except Busy as error:
            return self._refuse_detect(request, str(error))
        if skipped:
            rospy.logwarn('request %s: skipped busy vision systems %s', request.request_id, skipped)
        if not accepted:
            return self._refuse_detect(
                request,
                f'busy: all {len(names)} vision systems covering the region have '
                f'{self.settings.max_pending_per_vision_system} forwards pending; try again later',
            )
        message = f'forwarded to {len(accepted)} vision system{"s" if len(accepted) != 1 else ""}'
        if skipped:
            message += f'; {len(skipped)} busy vision system(s) skipped'
        return DetectObjectBoundaryResponse(accepted=True, message=message, vision_systems=len(accepted))

    def _refuse_detect(self, request, message: str) -> DetectObjectBoundaryResponse:
        rospy.loginfo(
            'request %r from %s refused: %s',
            request.request_id,
            request._connection_header.get('callerid', '?'),
            message,
        )
        return DetectObjectBoundaryResponse(accepted=False, message=message, vision_systems=0)

    def _check_callback(self, name: str) -> str | None:
        now = time.monotonic()
        with self._lock:
            verified = self._callbacks.get(name)
        if verified is not None and now - verified < self.settings.callback_cache:
            return None
        problem = self._check_service('callback_service', name, CallbackCoordinates)
        with self._lock:
            if problem:
                self._callbacks.pop(name, None)
            else:
                if len(self._callbacks) > 10000:
                    self._callbacks.clear()
                self._callbacks[name] = now
        return problem

    # -- forwarding (worker threads) ---------------------------------------------------------
    def _forward(self, name: str, request) -> None:
        with self._lock:
            client = self._clients.get(name)
        if client is None:  # removed while the forward was queued
            return
        started = time.monotonic()
        try:
            answer = client.call(request)
        except ServiceCallError as error:
            failures = self.registry.failures(name) + 1
            rospy.logwarn(
                'forward of %r to %s failed (%d in a row): %s', request.request_id, name, failures, error
            )
            if self.registry.record_failure(name):
                rospy.loginfo('removed %s after %d failed forwards in a row', name, failures)
                self._forget(name)
                self._mark_changed()
            return
        self.registry.record_success(name)
        rospy.logdebug(
            'forwarded %r to %s in %.1f ms: accepted=%s %s',
            request.request_id,
            name,
            (time.monotonic() - started) * 1000,
            answer.accepted,
            answer.message,
        )

    # -- background loops --------------------------------------------------------------------
    def _expire_loop(self) -> None:
        period = min(self.settings.lease / 4, 0.5)
        while not self._stopping.wait(period):
            for name in self.registry.expire():
                rospy.loginfo('lease of %s expired: removed', name)
                self._forget(name)
                self._mark_changed()

    def _mark_changed(self) -> None:
        with self._changed:
            self._dirty = True
            self._changed.notify()

    def _publish_loop(self) -> None:
        while not self._stopping.is_set():
            with self._changed:
                while not self._dirty and not self._stopping.is_set():
                    self._changed.wait()
                self._dirty = False
            if self._stopping.is_set():
                return
            self._registry_publisher.publish(String(data=self.registry_json()))
            self._stopping.wait(self.settings.registry_period)

    def registry_json(self) -> str:
        with self._lock:
            providers = dict(self._providers)
        return json.dumps(
            {
                'vision_systems': [
                    {
                        'service_name': entry.service_name,
                        'provider': providers.get(entry.service_name, ''),
                        'field_of_view': [list(point) for point in entry.field_of_view],
                    }
                    for entry in self.registry.entries()
                ]
            }
        )
