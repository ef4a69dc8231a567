"""The DRVS server's checks that ask the ROS master: is a service known, of the right type, and
provided by the right node. The ROS side of :mod:`drvs.ros.server`; which callback services are
trusted without asking is decided in :mod:`drvs.server.callback_check`. The refusals are listed
in docs/nodes/drvs_server.md.
"""

from __future__ import annotations

import rospy

from drvs.common.status import INVALID, UNAVAILABLE, Refusal
from drvs.ros.server_forwarding import watch_service_of
from drvs.ros.service_client import (
    MasterUnreachable,
    ServiceCallError,
    ServiceInfo,
    UnknownService,
    probe_service,
)
from drvs.server.callback_check import CallbackCheck
from drvs.srv import CallbackCoordinates, DetectObjectBoundary, WatchObjectBoundary

__all__ = ['MasterChecks', 'caller_of']


def caller_of(request) -> str:
    """The caller id a service request came with (its connection header), '' without one."""
    return request._connection_header.get('callerid', '')


class MasterChecks:
    """Checks of services against the ROS master, each limited to ``timeout`` seconds.

    :param timeout: limit on each master lookup and probe.
    :param retry_after: the ``retry_after`` of an ``UNAVAILABLE`` refusal (the master did not answer).
    :param callback_cache: seconds a verified callback service is trusted without asking.
    :param callback_memory: seconds a verified callback service is remembered (see
        :class:`~drvs.server.callback_check.CallbackCheck`).
    """

    def __init__(self, timeout: float, retry_after: float, callback_cache: float, callback_memory: float):
        self.timeout = timeout
        self.retry_after = retry_after
        self.callbacks = CallbackCheck(self._probe_callback, callback_cache, callback_memory, retry_after)

    def service(
        self, field: str, service: str, service_class, provider_must_be: str | None = None
    ) -> ServiceInfo:
        """Check that ``service`` is known to the master and of the expected type (and provider).

        :raises Refusal: ``INVALID`` naming ``field`` and the problem; ``UNAVAILABLE`` when the
            master or the service did not answer in time.
        """
        try:
            info = probe_service(service, self.timeout, caller_id=rospy.get_name())
        except UnknownService:
            raise Refusal(INVALID, f'{field}: {service} is not known to the ROS master') from None
        except MasterUnreachable as error:
            raise Refusal(
                UNAVAILABLE, f'{field}: cannot check {service}: {error}; retry later', self.retry_after
            ) from None
        except ServiceCallError as error:
            raise Refusal(INVALID, f'{field}: {service} cannot be reached: {error}') from None
        if info.type != service_class._type or info.md5sum != service_class._md5sum:
            raise Refusal(
                INVALID,
                f'{field}: {service} is of type {info.type or "(unknown)"}, expected {service_class._type}',
            )
        if provider_must_be is not None and info.provider != provider_must_be:
            raise Refusal(
                INVALID,
                f'{field}: {service} is provided by {info.provider}, not by the caller {provider_must_be}; '
                'a node may register only its own service',
            )
        return info

    def vision_system(self, service: str, provider: str) -> tuple[str, bool]:
        """A registering vision system's ``service``: its instance (``rosrpc://`` URI), and whether
        it serves watches (:meth:`has_watch_service`).

        :raises Refusal: as :meth:`service`, ``provider`` being the caller.
        """
        instance = self.service('service_name', service, DetectObjectBoundary, provider_must_be=provider).uri
        return instance, self.has_watch_service(service, provider)

    def has_watch_service(self, service: str, provider: str) -> bool:
        """Whether the vision system of ``service`` serves watches: its sibling
        ``watch_object_boundary`` is a drvs/WatchObjectBoundary of the same node.

        :raises Refusal: ``UNAVAILABLE`` when the master did not answer.
        """
        try:
            self.service(
                'watch service', watch_service_of(service), WatchObjectBoundary, provider_must_be=provider
            )
        except Refusal as refusal:
            if refusal.status != INVALID:
                raise
            rospy.logdebug('%s: %s', service, refusal.message)
            return False
        return True

    def callback(self, service: str) -> str:
        """Check a request's callback service, unless verified lately (:class:`CallbackCheck`); its
        ``rosrpc://`` address on this server's master (as found within ``~callback_cache``).

        :raises Refusal: as :meth:`service`, or ``UNAVAILABLE`` for one verified lately and now unknown.
        """
        return self.callbacks.check(service)

    def _probe_callback(self, service: str) -> str:
        return self.service('callback_service', service, CallbackCoordinates).uri
