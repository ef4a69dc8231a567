"""When the blind robot asks DRVS for which role: rounds, periods, retries after refusals (no ROS).

The control loop posts a round each tick (:meth:`RequestSchedule.post`); a requester
thread takes one request at a time and reports how it went. Latest round only, the
station once found only once per period, retries after jittered backoff, ``INVALID`` and
``UNSUPPORTED`` final, calls spaced by ``max_rate``. The clock and the jitter are
injected; not thread-safe (the node holds a lock). The rules: docs/nodes/blind_robot.md
and docs/design.md ("The blind robot").

>>> from drvs.common.status import BUSY
>>> now = [0.0]
>>> schedule = RequestSchedule(clock=lambda: now[0], rng=lambda: 0.0)
>>> schedule.post({'self': (0, 0, 3, 3), 'station': (0, 0, 3, 3)})
>>> schedule.next_request()
Request(role='self', region_of_interest=(0, 0, 3, 3), attempt=0)
>>> schedule.on_response('self', BUSY, retry_after=0.3)
Outcome(action='retry', delay=0.3)
>>> now[0] = 0.1
>>> schedule.next_request().role  # self waits until 0.3 s; the station may go now
'station'
"""

from __future__ import annotations

import logging
import math
import random
import time
from collections import Counter
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass

from drvs.common.retry import retry_delay
from drvs.common.status import ACCEPTED, INVALID, TEMPORARY, UNSUPPORTED, name

logger = logging.getLogger('rosout.' + __name__)

__all__ = [
    'ACCEPT',
    'GIVE_UP',
    'RETRY',
    'Outcome',
    'Request',
    'RequestSchedule',
    'Retries',
    'Scheduled',
    'min_interval',
]

Box = tuple[float, float, float, float]

ACCEPT, RETRY, GIVE_UP = 'accepted', 'retry', 'give up'


@dataclass(frozen=True)
class Request:
    """What to send now: a role, its region of interest, and how many tries of it failed in a row."""

    role: str
    region_of_interest: Box
    attempt: int


@dataclass(frozen=True)
class Outcome:
    """What a response means for the robot: ``action`` is ACCEPT, RETRY (after ``delay`` s) or GIVE_UP."""

    action: str
    delay: float = 0.0


class Retries:
    """How DRVS's answers per role go: backoff after temporary refusals and failed calls, the
    refusal counters, and the final refusal (see the module docstring; shared with
    :class:`drvs.robot.watch_schedule.WatchSchedule`).

    :param base: first retry delay, seconds (:func:`drvs.common.retry.retry_delay`).
    :param cap: longest retry delay before jitter, unless the server's ``retry_after`` is longer.
    :param jitter: retry delays are multiplied by a random factor in ``[1, 1 + jitter]``.
    :param clock: monotonic seconds.
    :param rng: uniform random numbers in [0, 1), for the jitter.
    """

    def __init__(
        self,
        base: float,
        cap: float,
        jitter: float,
        clock: Callable[[], float],
        rng: Callable[[], float],
    ):
        retry_delay(0.0, 0, base=base, cap=cap, jitter=jitter)  # raises for a negative one
        self.base, self.cap, self.jitter = base, cap, jitter
        self.clock = clock
        self.rng = rng
        self.failed = 0  # calls that got no response
        self.refused: Counter[str] = Counter()  # status name -> refusals
        self.invalid: tuple[str, str] | None = None  # (role, the server's message) after INVALID
        self._attempts: Counter[str] = Counter()  # role -> failed calls or temporary refusals in a row
        self._not_before: dict[str, float] = {}  # role -> no retry before this time
        self._warned: set[int] = set()

    def attempt(self, role: str) -> int:
        """Failed calls or temporary refusals of ``role`` in a row."""
        return self._attempts[role]

    def ready_at(self, role: str) -> float:
        """When ``role`` may be sent again (-inf: at once)."""
        return self._not_before.get(role, -math.inf)

    def on_response(self, role: str, status: int, retry_after: float = 0.0, message: str = '') -> Outcome:
        """Record DRVS's answer (its ``status``) to a call for ``role``; say what it means."""
        if status == ACCEPTED:
            self._attempts.pop(role, None)
            self._not_before.pop(role, None)
            return Outcome(ACCEPT)
        self.refused[name(status)] += 1
        if status in (INVALID, UNSUPPORTED):
            self.invalid = (role, message)
            return Outcome(GIVE_UP)
        if status not in TEMPORARY and status not in self._warned:
            self._warned.add(status)
            logger.warning('DRVS answered with unknown status %d; retrying it later', status)
        return Outcome(RETRY, self._back_off(role, retry_after))

    def on_failure(self, role: str) -> Outcome:
        """Record that a call for ``role`` got no response (server down, timeout, ...)."""
        self.failed += 1
        return Outcome(RETRY, self._back_off(role, 0.0))

    def _back_off(self, role: str, retry_after: float) -> float:
        delay = retry_delay(
            retry_after, self._attempts[role], base=self.base, cap=self.cap, jitter=self.jitter, rng=self.rng
        )
        self._attempts[role] += 1
        self._not_before[role] = self.clock() + delay
        return delay


class Scheduled:
    """What a schedule's :class:`Retries` counted, for the robot's status."""

    retries: Retries

    @property
    def failed(self) -> int:
        """Calls that got no response."""
        return self.retries.failed

    @property
    def refused(self) -> Counter[str]:
        """Status name -> refusals."""
        return self.retries.refused

    @property
    def invalid(self) -> tuple[str, str] | None:
        """(role, the server's message) after INVALID or UNSUPPORTED; None before."""
        return self.retries.invalid


@dataclass
class _Role:
    last_sent: float = -math.inf
    sent_in_round: int = 0  # number of the round it was last sent in
    in_flight: bool = False


class RequestSchedule(Scheduled):
    """Decides which role the requester asks next; see the module docstring.

    :param periods: role -> seconds between requests once the role's object is found.
    :param max_rate: requests per second, at most, over all roles.
    :param base: first retry delay, seconds (:func:`drvs.common.retry.retry_delay`).
    :param cap: longest retry delay before jitter, unless the server's ``retry_after`` is longer.
    :param jitter: retry delays are multiplied by a random factor in ``[1, 1 + jitter]``.
    :param clock: monotonic seconds.
    :param rng: uniform random numbers in [0, 1), for the jitter.
    """

    def __init__(
        self,
        periods: Mapping[str, float] | None = None,
        max_rate: float = 40.0,
        base: float = 0.1,
        cap: float = 1.0,
        jitter: float = 0.5,
        clock: Callable[[], float] = time.monotonic,
        rng: Callable[[], float] = random.random,
    ):
        periods = dict(periods or {})
        for role, period in periods.items():
            if not period > 0:
                raise ValueError(f'periods[{role!r}]: must be positive, got {period}')
        self.periods = periods
        self.min_interval = min_interval(max_rate)
        self.retries = Retries(base, cap, jitter, clock, rng)
        self.clock = clock
        self.sent = 0  # requests handed out
        self.stopped = False
        self._roles: dict[str, _Role] = {}
        self._round: dict[str, Box] = {}
        self._round_number = 0
        self._found: frozenset[str] = frozenset()
        self._last_sent = -math.inf

    @property
    def done(self) -> bool:
        """Whether nothing is left to send after :meth:`stop` (one-shot requests need no cancel)."""
        return self.stopped

    # -- the control loop's side ---------------------------------------------------------------
    def post(self, regions: Mapping[str, Box], found: Collection[str] = ()) -> None:
        """A new round: ask each role of ``regions`` once, with that region of interest.

        :param found: roles whose object is known; those with a period are then asked once per period.
        """
        self._round = dict(regions)
        self._round_number += 1
        self._found = frozenset(found)
        for role in self._round:
            self._roles.setdefault(role, _Role())

    def stop(self) -> None:
        """The mission is over: no more requests."""
        self.stopped = True

    # -- the requester's side ----------------------------------------------------------------
    def next_request(self) -> Request | None:
        """The request to send now, or None (then :meth:`wait_time` says for how long)."""
        now = self.clock()
        if now < self._last_sent + self.min_interval:
            return None
        ready = [role for role in self._round if self._ready_at(role) <= now]
        if not ready:
            return None
        role = min(ready, key=lambda r: self._roles[r].last_sent)  # stable: ties keep the round's order
        state = self._roles[role]
        state.in_flight = True
        state.last_sent = self._last_sent = now
        state.sent_in_round = self._round_number
        self.sent += 1
        return Request(role, self._round[role], self.retries.attempt(role))

    def in_flight(self, role: str) -> bool:
        """Whether ``role`` was handed out and its outcome not reported yet."""
        return role in self._roles and self._roles[role].in_flight

    def wait_time(self) -> float | None:
        """Seconds until :meth:`next_request` may return a request; None: not before the next round."""
        times = [self._ready_at(role) for role in self._round]
        times = [t for t in times if t < math.inf]
        if not times:
            return None
        return max(0.0, min(times) - self.clock(), self._last_sent + self.min_interval - self.clock())

    def on_response(self, role: str, status: int, retry_after: float = 0.0, message: str = '') -> Outcome:
        """Record DRVS's answer (its ``status``) to the request for ``role``; say what it means."""
        self._roles[role].in_flight = False
        return self.retries.on_response(role, status, retry_after, message)

    def on_failure(self, role: str) -> Outcome:
        """Record that the request for ``role`` got no response (server down, timeout, ...)."""
        self._roles[role].in_flight = False
        return self.retries.on_failure(role)

    # -- internals -----------------------------------------------------------------------------
    def _ready_at(self, role: str) -> float:
        """When ``role`` of the current round may be sent (inf: not in this round)."""
        state = self._roles[role]
        if (
            self.stopped
            or self.invalid is not None
            or state.in_flight
            or state.sent_in_round == self._round_number
        ):
            return math.inf
        ready = self.retries.ready_at(role)
        if role in self.periods and role in self._found:
            ready = max(ready, state.last_sent + self.periods[role])
        return ready


def min_interval(max_rate: float) -> float:
    """Seconds between two calls at ``max_rate`` calls per second.

    :raises ValueError: ``max_rate`` is not positive.
    """
    if not max_rate > 0:
        raise ValueError(f'max_rate: must be positive, got {max_rate}')
    return 1.0 / max_rate
