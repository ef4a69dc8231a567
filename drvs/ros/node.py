"""The scaffold every DRVS node is built on: stop event, guarded loops, diagnostics, counters,
throttled logs, and one way to answer a refusal or an internal error.

A node class owns a :class:`NodeScaffold` (``self.node``) and gives it its health; the
threads of each node are listed in docs/architecture.md.
"""

from __future__ import annotations

import logging
import socket
import threading
import traceback
from collections.abc import Callable, Hashable

import rospy

from drvs.common.counters import Counters, PeriodCounts
from drvs.common.guard import RESTART, LoopGuard
from drvs.common.health import Health
from drvs.common.log_throttle import LogThrottle, not_logged
from drvs.common.status import UNAVAILABLE, Refusal, name
from drvs.ros.diagnostics import DiagnosticsPublisher

__all__ = ['NodeScaffold', 'debug_logged', 'internal_error', 'refusal_response']

LOG_PERIOD = 1.0
"""Seconds between two throttled log lines of one kind."""


class NodeScaffold:
    """What every node has, wired once.

    - :attr:`stopping`: set when the node stops; every loop ends on it.
    - :attr:`guard`: a :class:`~drvs.common.guard.LoopGuard` whose fatal failure shuts the node
      down (``rospy.signal_shutdown``) and sets :attr:`stopping`; :meth:`spawn` and
      :meth:`every` start loops under it.
    - :attr:`counters`: the node's ``~stats`` counters under their lock; :attr:`refusals`:
      refusals by status name, for the health report.
    - :attr:`diagnostics`: ``/diagnostics`` once a second from ``health()`` (None without it).
    - :meth:`log_throttled`: at most one line per kind and :data:`LOG_PERIOD`.

    :param health: the node's health now (called on the diagnostics thread); None for a node
        that publishes none (the simulation nodes and the scenario recorder: no part of DRVS).
    :param counters: the names of the node's counters.
    :param hardware_id: what the diagnostics status is about (default: the host name).
    """

    def __init__(
        self,
        health: Callable[[], Health] | None,
        counters: tuple[str, ...] | list[str] = (),
        hardware_id: str | None = None,
        log_period: float = LOG_PERIOD,
    ):
        self.stopping = threading.Event()
        self.guard = LoopGuard(on_fatal=lambda reason: rospy.signal_shutdown(reason), stop=self.stopping)
        self.counters = Counters(counters)
        self.refusals = PeriodCounts()
        self.log_period = log_period
        self._log_throttle = LogThrottle(log_period)
        self.diagnostics = None
        if health is not None:
            self.diagnostics = DiagnosticsPublisher(
                f'drvs: {rospy.get_name()}', hardware_id or socket.gethostname(), health, guard=self.guard
            )

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> None:
        """Start publishing diagnostics (the node's own loops are spawned by the node)."""
        if self.diagnostics is not None:
            self.diagnostics.start()

    def stop(self, join: float | None = None) -> None:
        """Set :attr:`stopping`, stop diagnostics and, with ``join``, wait that long for each loop."""
        self.stopping.set()
        if self.diagnostics is not None:
            self.diagnostics.stop()
        if join is not None:
            self.join(join)

    def join(self, timeout: float) -> None:
        """Wait up to ``timeout`` seconds for each loop (not the calling thread's own)."""
        for thread in self.guard.threads:
            if thread is not threading.current_thread():
                thread.join(timeout)

    @property
    def stopped(self) -> bool:
        return self.stopping.is_set()

    @property
    def failure(self) -> str | None:
        """Why a loop took the node down, or None."""
        return self.guard.failure

    def wait(self, seconds: float) -> bool:
        """Sleep up to ``seconds``; True if the node is stopping."""
        return self.stopping.wait(seconds)

    # -- loops -------------------------------------------------------------------------------
    def spawn(self, target: Callable[[], None], name: str, policy: str = RESTART) -> threading.Thread:
        """Run ``target`` on a guarded daemon thread (restarted, or fatal, as ``policy`` says)."""
        return self.guard.spawn(target, name, policy)

    def every(self, period: float, action: Callable[[], None], name: str, policy: str = RESTART):
        """Run ``action`` every ``period`` seconds until the node stops, on a guarded thread."""

        def loop() -> None:
            while not self.stopping.wait(period):
                action()

        return self.spawn(loop, name, policy)

    # -- logs --------------------------------------------------------------------------------
    def log_throttled(self, kind: Hashable, log: Callable, text: str, *args) -> None:
        """``log(text, *args)`` unless a line of ``kind`` went out within :data:`LOG_PERIOD`; the
        next line that goes out says how many were left out."""
        unlogged = self._log_throttle.allow(kind)
        if unlogged is None:
            return
        log(text + '%s', *args, not_logged(unlogged, self.log_period))

    def refused(self, refusal: Refusal) -> None:
        """Count ``refusal`` for the health report (by its status name)."""
        self.refusals.add(name(refusal.status))


def refusal_response(response_class, refusal: Refusal, **fields):
    """A service response (any drvs response with ``accepted``, ``status``, ``message`` and
    ``retry_after``) that refuses with ``refusal``; ``fields`` fill the rest."""
    return response_class(
        accepted=False,
        status=refusal.status,
        message=refusal.message,
        retry_after=refusal.retry_after,
        **fields,
    )


def internal_error(node: str, what: str, error: Exception, retry_after: float) -> Refusal:
    """Log a bug with its traceback and turn it into an ``UNAVAILABLE`` refusal for the caller,
    never rospy's bare error reply. Call it from the ``except`` block that caught ``error``."""
    rospy.logerr('%s failed unexpectedly:\n%s', what, traceback.format_exc())
    return Refusal(
        UNAVAILABLE,
        f'internal error in {node} ({type(error).__name__}: {error}); it is logged there; retry later',
        retry_after,
    )


def debug_logged() -> bool:
    """Whether a debug line would be logged: rospy formats and dispatches one before it knows, so a
    hot path asks first."""
    return logging.getLogger('rosout').isEnabledFor(logging.DEBUG)
