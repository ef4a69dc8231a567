"""The rosbridge endpoint's ROS side (:class:`drvs.gateway.bridge.BridgeBackend`): calls to DRVS's
services with a deadline each (:class:`drvs.ros.service_client.ServiceClient`), a real ROS service
for each service a client hosts, and one subscriber per topic shared by every client that
subscribed. Messages <-> JSON by :mod:`drvs.gateway.rosjson`. The contract: docs/gateway.md
("rosbridge endpoint").
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import genpy
import rospy
from roslib.message import get_message_class
from visualization_msgs.msg import MarkerArray

from drvs.gateway.backend import NoServer
from drvs.gateway.params import GatewaySettings
from drvs.gateway.rosjson import FieldError, from_json, to_json
from drvs.msg import Registry, TrackedObjects
from drvs.ros.service_client import ServiceCallError, ServiceClient
from drvs.srv import CallbackCoordinates, DetectObjectBoundary, WatchObjectBoundary

__all__ = ['RosBridgeBackend']

_TIMES = {'time': genpy.Time, 'duration': genpy.Duration}


def resolve(type_name: str) -> Any:
    """A message type name -> its generated class (``Header`` is ``std_msgs/Header``).

    :raises FieldError: an unknown type.
    """
    if type_name in _TIMES:
        return _TIMES[type_name]
    found = get_message_class('std_msgs/Header' if type_name == 'Header' else type_name)
    if found is None:
        raise FieldError('type', f'unknown message type {type_name}')
    return found


class RosBridgeBackend:
    """ROS for the rosbridge endpoint of the gateway whose DRVS server lives at ``settings.server``."""

    hostable = ('drvs/CallbackCoordinates',)

    def __init__(self, settings: GatewaySettings):
        server = settings.server.rstrip('/')
        self._services = {
            f'{server}/detect_object_boundary': DetectObjectBoundary,
            f'{server}/watch_object_boundary': WatchObjectBoundary,
        }
        self.services = {
            f'{server}/detect_object_boundary': 'detect',
            f'{server}/watch_object_boundary': 'watch',
        }
        self._topic_classes = {
            f'{server}/registry': Registry,
            f'{server}/markers': MarkerArray,
            f'{server}/objects': TrackedObjects,
        }
        self.topics = {topic: message_class._type for topic, message_class in self._topic_classes.items()}
        self._local = threading.local()
        self._lock = threading.Lock()  # guards _clients, _subscribers and _newest
        self._clients: list[ServiceClient] = []
        self._subscribers: dict[str, tuple[rospy.Subscriber, set[Callable[[dict[str, Any]], None]]]] = {}
        self._newest: dict[str, dict[str, Any]] = {}  # each topic's newest message, as JSON

    def close(self) -> None:
        with self._lock:
            clients, self._clients = self._clients, []
            subscribers, self._subscribers = self._subscribers, {}
        for client in clients:
            client.close()
        for subscriber, _ in subscribers.values():
            subscriber.unregister()

    def call(self, service: str, args: dict[str, Any] | list[Any], timeout: float) -> dict[str, Any]:
        service_class = self._services[service]
        request_class = service_class._request_class
        if isinstance(args, list):  # rosbridge's positional form: the fields in order
            if len(args) > len(request_class.__slots__):
                raise FieldError('args', f'{len(args)} values for {len(request_class.__slots__)} fields')
            args = dict(zip(request_class.__slots__, args, strict=False))
        request = from_json(args, request_class, resolve)
        clients = self._local.__dict__.setdefault('clients', {})
        if service not in clients:
            clients[service] = ServiceClient(service, service_class, timeout)
            with self._lock:
                self._clients.append(clients[service])
        client = clients[service]
        client.timeout = timeout
        try:
            return to_json(client.call(request))
        except ServiceCallError as error:
            raise NoServer(str(error)) from None

    def host(
        self, graph_name: str, service_type: str, serve: Callable[[dict[str, Any]], dict[str, Any]]
    ) -> Callable[[], None]:
        assert service_type == CallbackCoordinates._type

        def handle(request):
            try:
                values = serve(to_json(request))
                return from_json(values, CallbackCoordinates._response_class, resolve)
            except Exception as error:  # the client refused, timed out or answered nonsense
                raise rospy.ServiceException(f'{type(error).__name__}: {error}') from None

        service = rospy.Service(graph_name, CallbackCoordinates, handle)
        return service.shutdown

    def subscribe(self, topic: str, deliver: Callable[[dict[str, Any]], None]) -> Callable[[], None]:
        """A new receiver gets the topic's newest message at once (as a new subscriber of a latched
        topic would), then every message."""
        with self._lock:
            entry = self._subscribers.get(topic)
            if entry is not None:
                entry[1].add(deliver)
            newest = self._newest.get(topic)
        if newest is not None:
            deliver(newest)
        if entry is None:
            # Outside the lock: rospy hands a latched message to the callback within this call.
            receivers = {deliver}
            subscriber = rospy.Subscriber(
                topic,
                self._topic_classes[topic],
                self._fan_out,
                callback_args=(topic, receivers),
                queue_size=4,
            )
            with self._lock:
                if topic in self._subscribers:  # another client subscribed meanwhile: one subscriber
                    self._subscribers[topic][1].add(deliver)
                    stale = subscriber
                else:
                    self._subscribers[topic] = (subscriber, receivers)
                    stale = None
            if stale is not None:
                stale.unregister()

        def stop() -> None:
            with self._lock:
                entry = self._subscribers.get(topic)
                if entry is None:
                    return
                entry[1].discard(deliver)
                if entry[1]:
                    return
                del self._subscribers[topic]
            entry[0].unregister()

        return stop

    def _fan_out(self, message, topic_and_receivers) -> None:
        topic, receivers = topic_and_receivers
        data = to_json(message)
        with self._lock:
            self._newest[topic] = data
            targets = list(receivers)
        for deliver in targets:
            deliver(data)
