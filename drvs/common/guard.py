"""Background loops that never leave a node half alive: :class:`LoopGuard` and its policies.

A loop runs under ``RESTART`` (logged, restarted, fatal when it keeps failing) or
``SHUTDOWN`` (fatal at once); a fatal failure stops the other loops and calls
``on_fatal``, so the node exits 1. No ROS here; the clock is injectable. The rules and
why: docs/reliability.md ("No half-alive nodes").
"""

from __future__ import annotations

import logging
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable

logger = logging.getLogger('rosout.' + __name__)

__all__ = ['RESTART', 'SHUTDOWN', 'LoopGuard']

RESTART = 'restart'
SHUTDOWN = 'shutdown'
_POLICIES = (RESTART, SHUTDOWN)


class LoopGuard:
    """Runs background loops on daemon threads; restarts them or fails the node.

    :param on_fatal: called once, with the reason, on the first fatal failure.
    :param stop: set when the node stops; interrupts restart delays (one is made if None).
    :param restart_delay: seconds between a failure and the restart.
    :param max_restarts: failures within ``window`` a ``RESTART`` loop may have;
        one more is fatal.
    :param window: seconds over which failures are counted.
    :param clock: monotonic seconds (injectable for tests).
    """

    def __init__(
        self,
        on_fatal: Callable[[str], None],
        stop: threading.Event | None = None,
        restart_delay: float = 1.0,
        max_restarts: int = 5,
        window: float = 60.0,
        clock: Callable[[], float] = time.monotonic,
    ):
        if not restart_delay >= 0:
            raise ValueError(f'restart_delay: must not be negative, got {restart_delay}')
        if max_restarts < 0:
            raise ValueError(f'max_restarts: must not be negative, got {max_restarts}')
        if not window > 0:
            raise ValueError(f'window: must be positive, got {window}')
        self.on_fatal = on_fatal
        self.stop = stop if stop is not None else threading.Event()
        self.restart_delay = float(restart_delay)
        self.max_restarts = int(max_restarts)
        self.window = float(window)
        self.clock = clock
        self._lock = threading.Lock()  # guards failure and restarts
        self.failure: str | None = None  # the first fatal reason; None while healthy
        self.restarts: dict[str, int] = {}  # restarts so far, per loop name
        self.threads: list[threading.Thread] = []

    def spawn(self, target: Callable[[], None], name: str, policy: str) -> threading.Thread:
        """Start a daemon thread ``name`` that runs ``target()`` under ``policy``.

        ``target`` is a whole loop: it returns when the node stops.
        """
        if policy not in _POLICIES:
            raise ValueError(f'policy: must be {RESTART!r} or {SHUTDOWN!r}, got {policy!r}')
        with self._lock:
            self.restarts.setdefault(name, 0)
        thread = threading.Thread(target=self._run, args=(target, name, policy), name=name, daemon=True)
        self.threads.append(thread)
        thread.start()
        return thread

    def _run(self, target: Callable[[], None], name: str, policy: str) -> None:
        failures: deque[float] = deque()  # times of recent failures, within the window
        while True:
            try:
                target()
                return
            except Exception as error:
                logger.error('background loop %s failed:\n%s', name, traceback.format_exc())
                reason = f'background loop {name} failed: {type(error).__name__}: {error}'
            except BaseException as error:
                logger.error('background loop %s failed:\n%s', name, traceback.format_exc())
                self._fatal(f'background loop {name} failed: {type(error).__name__}: {error}')
                raise
            if self.stop.is_set():
                return  # the node is stopping anyway
            if policy == SHUTDOWN:
                self._fatal(reason)
                return
            now = self.clock()
            failures.append(now)
            while failures[0] <= now - self.window:
                failures.popleft()
            if len(failures) > self.max_restarts:
                self._fatal(f'{reason} ({len(failures)} failures within {self.window:g} s)')
                return
            if self.stop.wait(self.restart_delay):
                return
            with self._lock:
                self.restarts[name] += 1
            logger.warning('restarting background loop %s', name)

    def _fatal(self, reason: str) -> None:
        with self._lock:
            if self.failure is not None:
                return
            self.failure = reason
        logger.critical('%s; stopping the node', reason)
        self.stop.set()
        try:
            self.on_fatal(reason)
        except Exception:
            logger.exception('on_fatal failed for: %s', reason)
