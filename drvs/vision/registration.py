"""When a vision system registers its field of view with the DRVS server: the registration state
machine, without ROS.

:class:`Registration` decides, on an injected clock, when to register, renew, re-register after
a move and unregister, how long to back off after a refusal or no answer, and what the health
report says; the node (:mod:`drvs.ros.vision_system`) makes the calls and reports each answer
back. The rules are described in docs/nodes/vision_system.md.
"""

from __future__ import annotations

import random
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from drvs.common.retry import retry_delay
from drvs.common.status import is_temporary
from drvs.common.status import name as status_name

__all__ = [
    'DEFAULT_LEASE',
    'MOVE',
    'REGISTER',
    'RENEW',
    'UNREGISTER',
    'Attempt',
    'Registration',
    'RegistrationReport',
    'moved',
    'why_not_registering',
]

DEFAULT_LEASE = 10.0
"""Seconds assumed when a server grants no lease (0): renew every 5 s."""

REGISTER, MOVE, RENEW, UNREGISTER = 'register', 'move', 'renew', 'unregister'
"""What an attempt does: the first registration (or the first after unregistering), one with a
field of view that moved, a renewal of the same, and taking it back (an empty field of view)."""

Footprint = Sequence[tuple[float, float]]
"""A field of view: the floor polygon's vertices (x, y) in metres; empty for none."""


@dataclass(frozen=True)
class Attempt:
    """One call to make to the server: ``footprint`` ([] unregisters), decided at ``at``."""

    what: str
    footprint: Footprint
    at: float


@dataclass(frozen=True)
class RegistrationReport:
    """For the health report: whether a lease is held now, and why not or what went wrong.

    :param status: the status name of the last refusal; '' when the server did not answer or
        nothing was refused since the last success.
    :param error: why the last attempt failed, or why there is nothing to register.
    """

    registered: bool
    status: str
    error: str


class Registration:
    """A vision system's registration: call :meth:`due` with the field of view now, make the
    call it returns, and report the answer with :meth:`accepted`, :meth:`refused` or
    :meth:`unanswered`; :meth:`farewell` is the last call, on a clean stop.

    - register as soon as the field of view is known; renew at half the lease the server
      granted (:data:`DEFAULT_LEASE` when it grants none); register again at once when a
      vertex moved by more than ``move_threshold`` metres; unregister when the field of view
      becomes empty (a stale feed) and register again when it returns;
    - after a refusal or no answer, retry no earlier than the server's ``retry_after`` (0 for
      no answer, ``retry_period`` after a permanent refusal such as ``INVALID``), with growing
      backoff and jitter (:func:`drvs.common.retry.retry_delay`, capped at ``retry_period``);
      a lease granted before runs its course meanwhile.

    Thread-safe: ``Registration._lock`` guards the state (one thread decides, the diagnostics
    thread reads :meth:`report`).

    :param clock: monotonic seconds (``time.monotonic``; a ``ManualClock`` in tests).
    :param rng: the retry jitter's random source, in [0, 1].
    """

    def __init__(
        self,
        move_threshold: float,
        retry_period: float,
        clock: Callable[[], float] = time.monotonic,
        rng: Callable[[], float] = random.random,
    ):
        self.move_threshold = move_threshold
        self.retry_period = retry_period
        self.clock = clock
        self.rng = rng
        self._lock = threading.Lock()  # guards every field below
        self.lease: float | None = None  # granted by the server at the last registration
        self._registered: Footprint | None = None  # what the server holds ([]: unregistered; None: never)
        self._last_ok: float | None = None  # when the last successful attempt was decided
        self._retry_at = -float('inf')  # no attempt before then (after a failure)
        self._failures = 0  # failed attempts in a row, for the backoff
        self._until: float | None = None  # when the lease granted last ends
        self._status = ''
        self._error = ''

    def due(self, footprint: Footprint | None) -> Attempt | None:
        """The call to make now, given the field of view now (None while it is not known yet,
        [] for none), or None to wait."""
        with self._lock:
            registered = self._registered
            if footprint is None or (not footprint and not registered):
                if not registered:  # nothing to renew: say why
                    self._hold(None, why_not_registering(footprint))
                return None  # not known yet, or nothing to unregister
            now = self.clock()
            has_moved = registered is None or moved(registered, footprint, self.move_threshold)
            renew = bool(footprint) and (
                self._last_ok is None or now - self._last_ok >= (self.lease or DEFAULT_LEASE) / 2.0
            )
            if not (has_moved or renew) or now < self._retry_at:
                return None
            if not footprint:
                what = UNREGISTER  # the camera feed went stale
            elif not registered:
                what = REGISTER
            else:
                what = MOVE if has_moved else RENEW
            return Attempt(what, list(footprint), now)

    def farewell(self) -> Attempt | None:
        """The call to make on a clean stop: unregister, if registered."""
        with self._lock:
            return Attempt(UNREGISTER, [], self.clock()) if self._registered else None

    def accepted(self, attempt: Attempt, lease: float) -> None:
        """The server accepted ``attempt`` and granted ``lease`` seconds (0: none said)."""
        with self._lock:
            if lease > 0:
                self.lease = float(lease)
            if attempt.what == UNREGISTER:
                self._hold(None, why_not_registering(attempt.footprint))
            else:
                self._hold(self.clock() + (self.lease or DEFAULT_LEASE))
            self._registered = attempt.footprint
            self._last_ok = attempt.at
            self._failures = 0

    def refused(self, attempt: Attempt, status: int, message: str, retry_after: float) -> None:
        """The server refused ``attempt`` with ``status`` because ``message``."""
        wait = max(float(retry_after), 0.0) if is_temporary(status) else self.retry_period
        with self._lock:
            self._status, self._error = status_name(status), message
            self._back_off(attempt, wait)

    def unanswered(self, attempt: Attempt, error: str) -> None:
        """The call for ``attempt`` failed (no server, a timeout): ``error`` says how."""
        with self._lock:
            self._status, self._error = '', error
            self._back_off(attempt, 0.0)

    def report(self) -> RegistrationReport:
        """Whether a lease is held now, and the last problem (for the health report)."""
        with self._lock:
            registered = self._until is not None and self.clock() < self._until
            return RegistrationReport(registered, self._status, self._error)

    def _hold(self, until: float | None, why_not: str = '') -> None:
        """A lease held until ``until``, or none because ``why_not``; no refusal since."""
        self._until = until
        self._status, self._error = '', why_not

    def _back_off(self, attempt: Attempt, wait: float) -> None:
        self._retry_at = attempt.at + retry_delay(wait, self._failures, cap=self.retry_period, rng=self.rng)
        self._failures += 1


def why_not_registering(footprint: Footprint | None) -> str:
    """Why a vision system holds no registration it could renew: its field of view is unknown
    (None) or empty (a stale feed, or no floor in sight)."""
    if footprint is None:
        return 'waiting for the field of view (CameraInfo, tf and a frame)'
    return 'no field of view to register: the camera feed is stale or it sees no floor'


def moved(old: Footprint, new: Footprint, threshold: float) -> bool:
    """Whether a field of view changed by more than ``threshold`` metres at any vertex.

    >>> moved([(0, 0), (1, 0), (0, 1)], [(0, 0), (1.02, 0), (0, 1)], 0.01)
    True
    >>> moved([(0, 0), (1, 0), (0, 1)], [(0, 0), (1.005, 0), (0, 1)], 0.01)
    False
    """
    if len(old) != len(new):
        return True
    if not new:
        return False
    return float(np.max(np.abs(np.asarray(old) - np.asarray(new)))) > threshold
