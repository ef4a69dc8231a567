"""Which callback services the server trusts without asking the ROS master again.

A request names its callback service; checking it (a master lookup and a probe, done by the
ROS glue) costs more than the rest of the request. :class:`CallbackCheck` trusts a service
verified within ``cache`` seconds, and remembers it for ``memory`` seconds: a check that then
finds it unknown says ``UNAVAILABLE`` (a restarted master), not ``INVALID``. What the probe found
(the service's ``rosrpc://`` address, which forwards to other sites carry) is kept with it. No ROS here; the
parameters are described in docs/nodes/drvs_server.md.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable

from drvs.common.status import INVALID, UNAVAILABLE, Refusal

__all__ = ['MAX_CALLBACKS_REMEMBERED', 'CallbackCheck']

MAX_CALLBACKS_REMEMBERED = 10_000
"""Verified callback services kept; callers choose the names, so the memory is capped."""


class CallbackCheck:
    """Checks a callback service with ``probe``, unless it was verified within ``cache`` seconds.

    :param probe: ``probe(service)`` checks the service (known to the master, of the right type)
        and returns its address, or raises :class:`~drvs.common.status.Refusal`.
    :param cache: seconds a verified service is trusted without a probe.
    :param memory: seconds a verified service is remembered (at least ``cache``): a probe that
        finds it unknown within them is ``UNAVAILABLE`` with ``retry_after``, not ``INVALID``.
    :param retry_after: the ``retry_after`` of that ``UNAVAILABLE``.
    :param max_services: services remembered at most (the oldest verified go first).
    :param clock: monotonic seconds (injectable for tests).

    Thread-safe: one lock, ``CallbackCheck._lock``, guards the services remembered (not held
    while probing).
    """

    def __init__(
        self,
        probe: Callable[[str], str],
        cache: float,
        memory: float,
        retry_after: float,
        max_services: int = MAX_CALLBACKS_REMEMBERED,
        clock: Callable[[], float] = time.monotonic,
    ):
        if max_services < 1:
            raise ValueError(f'max_services: must be at least 1, got {max_services}')
        self.probe = probe
        self.cache = float(cache)
        self.remembered = max(float(memory), self.cache, 1e-3)
        self.retry_after = float(retry_after)
        self.max_services = int(max_services)
        self.clock = clock
        self._lock = threading.Lock()  # guards _verified
        # Verified service -> when verified, oldest first; bounded in size and age. Not a
        # cachetools.TTLCache: every request looks here, and its reads cost more than the rest.
        self._verified: OrderedDict[str, tuple[float, str]] = OrderedDict()  # -> (when, address)

    def __len__(self) -> int:
        """Services remembered now (some perhaps too old, forgotten at the next verification)."""
        with self._lock:
            return len(self._verified)

    def check(self, service: str) -> str:
        """Trust ``service`` if verified within ``cache`` seconds, else probe it and remember it;
        its address as the probe found it (within ``cache`` seconds).

        :raises Refusal: the probe's; ``UNAVAILABLE`` instead of its ``INVALID`` for a service
            verified within ``memory`` seconds.
        """
        now = self.clock()
        with self._lock:
            verified, address = self._verified.get(service, (None, ''))
        if verified is not None and now - verified >= self.remembered:
            verified = None  # forgotten
        if verified is not None and now - verified < self.cache:
            return address
        try:
            address = self.probe(service)
        except Refusal as refusal:
            if verified is not None and refusal.status == INVALID:
                raise Refusal(
                    UNAVAILABLE,
                    f'{refusal.message} now, though it was {now - verified:.1f} s ago '
                    '(a restarted master?); retry later',
                    self.retry_after,
                ) from None
            raise
        with self._lock:
            services = self._verified
            services[service] = (now, address)
            services.move_to_end(service)
            while services and (
                len(services) > self.max_services or now - next(iter(services.values()))[0] >= self.remembered
            ):
                services.popitem(last=False)
        return address
