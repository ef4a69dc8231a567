"""Who may register, move, renew or unregister which vision system with the server.

A vision system registers its own DetectObjectBoundary service; the node that registered a
service is the only one that may change or unregister it, and the server never registers a
service of its own (forwarding to it would loop). Asking the master who provides a service is
the ROS glue's part (``verify``); the refusals are listed in docs/nodes/drvs_server.md. No ROS here.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from drvs.common.status import INVALID, Refusal
from drvs.common.validation import ValidationError, field_of_view_polygon
from drvs.server.registry import (
    CHANGED,
    MOVED,
    NOT_REGISTERED,
    REGISTERED,
    RENEWED,
    Client,
    Registration,
    Registry,
)
from drvs.server.registry import algorithm_names as registered_algorithms

logger = logging.getLogger('rosout.' + __name__)

__all__ = ['Registered', 'Registrar']

Point = tuple[float, float]


@dataclass(frozen=True)
class Registered:
    """What a registration call did: ``message`` for the caller, and the ``lease`` it grants (0
    for an unregistration)."""

    message: str
    lease: float = 0.0


class Registrar:
    """Registers the calls of ``~register_vision_service`` in ``registry``.

    :param registry: the registry of vision systems.
    :param server: the server's own node name (it may not register).
    :param verify: ``verify(service, provider)``: the service's instance (its URI) and whether it
        serves watches, once the master says ``provider`` provides it; or raises
        :class:`~drvs.common.status.Refusal`. Not asked again when the provider that registered a
        service renews or moves it.
    :param make_client: makes the connection to a newly registered service (no I/O).
    :param on_change: ``on_change(change, service)`` after a registration, move or change of
        algorithms (not a renewal).
    :param on_removed: called with the entry of an unregistered vision system.
    """

    def __init__(
        self,
        registry: Registry,
        server: str,
        verify: Callable[[str, str], tuple[str, bool]],
        make_client: Callable[[str, str | None], Client],
        on_change: Callable[[str, str], None],
        on_removed: Callable[[Registration], None],
    ):
        self.registry = registry
        self.server = server
        self.verify = verify
        self.make_client = make_client
        self.on_change = on_change
        self.on_removed = on_removed

    def register(
        self, service: str, points: Sequence[Point], algorithms: Sequence[str], caller: str
    ) -> Registered:
        """Register, move, change or renew ``service`` (its global name) for ``caller``; no points
        unregister it.

        :raises Refusal: ``INVALID`` naming the field; the registry's and ``verify``'s refusals.
        """
        if caller == self.server:
            raise Refusal(
                INVALID,
                f'service_name: the caller {caller} is the DRVS server itself; forwarding to it would loop',
            )
        entry = self.registry.get(service)
        if not points:
            return self._unregister(service, entry, caller)
        try:
            field_of_view_polygon(points)
            names = sorted(registered_algorithms(algorithms))
        except ValidationError as error:
            raise Refusal(INVALID, f'{error} (service_name {service})') from None
        if entry is not None and entry.provider == caller:  # a renewal or move by the verified provider
            instance, watch_service = entry.instance, entry.watch_service
        else:
            instance, watch_service = self.verify(service, caller or '(no caller id)')
        try:
            change = self.registry.register(
                service,
                points,
                provider=caller,
                make_client=self.make_client,
                instance=instance,
                algorithms=names,
                watch_service=watch_service,
            )
        except ValidationError as error:
            raise Refusal(INVALID, f'{error} (service_name {service})') from None
        _log(change, service, caller, points, names, watch_service)
        if change != RENEWED:
            self.on_change(change, service)
        return Registered(f'{change} {service}; lease {self.registry.lease:g} s', self.registry.lease)

    def _unregister(self, service: str, entry: Registration | None, caller: str) -> Registered:
        if entry is not None and entry.site != self.registry.site:
            raise Refusal(
                INVALID,
                f'service_name: {service} is registered at site {entry.site or "(unnamed)"}; '
                'only a server of that site may unregister it',
            )
        if entry is not None and entry.provider != caller:
            raise Refusal(
                INVALID,
                f'service_name: {service} was registered by {entry.provider}; {caller} may not unregister it',
            )
        removed = self.registry.unregister(service)
        if removed is None:
            return Registered(f'{NOT_REGISTERED}: {service}')
        self.on_removed(removed)
        logger.info('unregistered %s (asked by %s)', service, caller)
        return Registered(f'unregistered {service}')


def _log(change: str, service: str, caller: str, points, names: list[str], watch_service: bool) -> None:
    if change == REGISTERED:
        logger.info(
            'registered %s by %s: field of view %s, algorithms %s; %s',
            service,
            caller,
            points,
            ', '.join(names),
            'a watch service' if watch_service else 'no watch service (watches by one-shot requests)',
        )
    elif change == MOVED:
        logger.info('moved %s: field of view %s, algorithms %s', service, points, ', '.join(names))
    elif change == CHANGED:
        logger.info('changed %s: algorithms %s', service, ', '.join(names))
    else:
        logger.debug('renewed %s', service)
