"""When the blind robot asks DRVS for which role: rounds, periods, retries after refusals (no ROS).

The robot's control loop never calls DRVS itself. Each tick it *posts* a round,
the region of interest of every role it wants asked now
(:meth:`RequestSchedule.post`); a requester thread takes one request at a time
(:meth:`RequestSchedule.next_request`), sends it and reports how it went
(:meth:`RequestSchedule.on_response`, :meth:`RequestSchedule.on_failure`).
The rules:

- Latest only: a round replaces the one before, and a role is sent at most once
  per round, so a slow requester never builds a backlog and always asks with the
  newest regions. Of the roles ready, the one sent least recently goes first, so
  a server that acknowledges slowly delays every role alike and starves none.
- Periods: a role in ``periods`` (the station) is asked every round until it is
  *found* (the caller says so when it posts), then once per period.
- Temporary refusals (``BUSY``, ``RATE_LIMITED``, ``UNAVAILABLE``, and codes this
  module does not know, with a warning once per code) and failed calls put the
  role aside for :func:`drvs.retry.retry_delay` seconds: never earlier than the
  server's ``retry_after``, doubling from ``base`` to ``cap`` while the role keeps
  failing, plus jitter; an accepted request resets the count. None of these ends
  the mission; the robot's own deadlines (no fix for ``fix_timeout``) do.
- ``INVALID`` (the request itself is wrong) and ``UNSUPPORTED`` (no registered
  vision system runs its algorithm) stop the schedule for good and keep the
  server's message in :attr:`RequestSchedule.invalid`: asking again cannot help.
- Rate: requests leave at least ``1 / max_rate`` seconds apart, whatever the
  rounds and the retries, so the robot stays under the server's per-caller rate
  limit (50 requests/s with bursts of 100 by default). With the robot's defaults
  (5 rounds/s, 4 roles) the rounds alone allow at most 20/s.

Not thread-safe: the robot node holds a lock (:mod:`drvs.ros.robot`). The clock
(monotonic seconds) and the random source of the jitter are injected, so tests
run a simulated minute in milliseconds.

>>> from drvs.status import BUSY
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

from drvs.retry import retry_delay
from drvs.status import ACCEPTED, INVALID, TEMPORARY, UNSUPPORTED, name

logger = logging.getLogger('rosout.' + __name__)

__all__ = ['ACCEPT', 'GIVE_UP', 'RETRY', 'Outcome', 'Request', 'RequestSchedule']

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


@dataclass
class _Role:
    attempt: int = 0  # failed calls or temporary refusals in a row
    not_before: float = -math.inf  # no retry before this time
    last_sent: float = -math.inf
    sent_in_round: int = 0  # number of the round it was last sent in
    in_flight: bool = False


class RequestSchedule:
    """Decides which role the requester asks next; see the module docstring.

    :param periods: role -> seconds between requests once the role's object is found.
    :param max_rate: requests per second, at most, over all roles.
    :param base: first retry delay, seconds (:func:`drvs.retry.retry_delay`).
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
        if not max_rate > 0:
            raise ValueError(f'max_rate: must be positive, got {max_rate}')
        for role, period in periods.items():
            if not period > 0:
                raise ValueError(f'periods[{role!r}]: must be positive, got {period}')
        retry_delay(0.0, 0, base=base, cap=cap, jitter=jitter)  # raises for a negative one
        self.periods = periods
        self.min_interval = 1.0 / max_rate
        self.base, self.cap, self.jitter = base, cap, jitter
        self.clock = clock
        self.rng = rng
        self.sent = 0  # requests handed out
        self.failed = 0  # calls that got no response
        self.refused: Counter[str] = Counter()  # status name -> refusals
        self.invalid: tuple[str, str] | None = None  # (role, the server's message) after INVALID
        self.stopped = False
        self._roles: dict[str, _Role] = {}
        self._round: dict[str, Box] = {}
        self._round_number = 0
        self._found: frozenset[str] = frozenset()
        self._last_sent = -math.inf
        self._warned: set[tuple[str, int]] = set()

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
        return Request(role, self._round[role], state.attempt)

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
        state = self._roles[role]
        state.in_flight = False
        if status == ACCEPTED:
            state.attempt = 0
            state.not_before = -math.inf
            return Outcome(ACCEPT)
        self.refused[name(status)] += 1
        if status in (INVALID, UNSUPPORTED):
            self.invalid = (role, message)
            return Outcome(GIVE_UP)
        if status not in TEMPORARY:
            self._warn_once(
                ('unknown', status), 'DRVS answered with unknown status %d; retrying it later', status
            )
        return Outcome(RETRY, self._back_off(state, retry_after))

    def on_failure(self, role: str) -> Outcome:
        """Record that the request for ``role`` got no response (server down, timeout, ...)."""
        state = self._roles[role]
        state.in_flight = False
        self.failed += 1
        return Outcome(RETRY, self._back_off(state, 0.0))

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
        ready = state.not_before
        if role in self.periods and role in self._found:
            ready = max(ready, state.last_sent + self.periods[role])
        return ready

    def _back_off(self, state: _Role, retry_after: float) -> float:
        delay = retry_delay(
            retry_after, state.attempt, base=self.base, cap=self.cap, jitter=self.jitter, rng=self.rng
        )
        state.attempt += 1
        state.not_before = self.clock() + delay
        return delay

    def _warn_once(self, key: tuple[str, int], text: str, *args) -> None:
        if key not in self._warned:
            self._warned.add(key)
            logger.warning(text, *args)
