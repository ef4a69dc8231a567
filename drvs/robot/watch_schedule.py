"""When the blind robot sends which watch (drvs/WatchObjectBoundary) for which role (no ROS).

One watch per role; a call is due when the role has none (``new``), when the region it
needs leaves the standing one or shrank (``region``), at half the granted duration or as a
keep-alive (``renew``), and once per watch when the mission is over (``cancel``). Answers
go as for one-shot requests. The clock (ROS time in the node) and the jitter are
injected; not thread-safe. The rules and why: docs/design.md ("The blind robot").

>>> from drvs.robot.perception import Region
>>> from drvs.common.status import ACCEPTED
>>> now = [0.0]
>>> schedule = WatchSchedule({'self': 0.2}, duration=10.0, clock=lambda: now[0], rng=lambda: 0.0)
>>> floor = (0.0, 0.0, 7.0, 5.5)
>>> schedule.post({'self': Region(floor, floor)})
>>> schedule.next_request()
WatchCall(role='self', region_of_interest=(0.0, 0.0, 7.0, 5.5), period=0.2, duration=10.0, reason='new')
>>> schedule.on_response('self', ACCEPTED, duration=8.0)
Outcome(action='accepted', delay=0.0)
>>> now[0] = 1.0
>>> schedule.next_request() is None, schedule.wait_time()  # renewed at half the granted 8 s
(True, 3.0)
"""

from __future__ import annotations

import math
import random
import time
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass

from drvs.common.status import ACCEPTED, name
from drvs.robot.perception import Box, Region
from drvs.robot.poll_schedule import ACCEPT, GIVE_UP, Outcome, Retries, Scheduled, min_interval

__all__ = ['CANCEL', 'NEW', 'REGION', 'RENEW', 'SHRINK', 'WatchCall', 'WatchSchedule']

NEW, REGION, RENEW, CANCEL = 'new', 'region', 'renew', 'cancel'

SHRINK = 0.5
"""A watch moves to a posted box smaller than this fraction of its own area (unless ``shrink`` says)."""


@dataclass(frozen=True)
class WatchCall:
    """What to send now: the role's watch with this region, period and duration (0: cancel)."""

    role: str
    region_of_interest: Box
    period: float
    duration: float
    reason: str  # NEW, REGION, RENEW or CANCEL


@dataclass
class _Watch:
    region: Box | None = None  # of the standing watch, as granted
    asked: Box | None = None  # of the last call
    expires: float = -math.inf
    renew_at: float = math.inf
    call: WatchCall | None = None  # in flight
    sent_at: float = -math.inf
    unsure: bool = False  # a call got no response: the watch may stand although none was granted


def _area(box: Box) -> float:
    return max(box[2] - box[0], 0.0) * max(box[3] - box[1], 0.0)


def _inside(inner: Box, outer: Box) -> bool:
    return outer[0] <= inner[0] and outer[1] <= inner[1] and inner[2] <= outer[2] and inner[3] <= outer[3]


class WatchSchedule(Scheduled):
    """Decides which watch call the requester sends next; see the module docstring.

    :param periods: role -> seconds between evaluations to ask for.
    :param duration: seconds each watch should stand unless renewed.
    :param keep_alive: role -> seconds without an answer or a call after which it is renewed.
    :param shrink: role -> the fraction of its area below which a posted box moves the watch
        (default :data:`SHRINK`).
    :param max_rate: calls per second, at most, over all roles.
    :param base: first retry delay, seconds (:func:`drvs.common.retry.retry_delay`).
    :param cap: longest retry delay before jitter, unless the server's ``retry_after`` is longer.
    :param jitter: retry delays are multiplied by a random factor in ``[1, 1 + jitter]``.
    :param clock: seconds (ROS time in the node).
    :param rng: uniform random numbers in [0, 1), for the jitter.
    """

    def __init__(
        self,
        periods: Mapping[str, float],
        duration: float,
        keep_alive: Mapping[str, float] | None = None,
        shrink: Mapping[str, float] | None = None,
        max_rate: float = 40.0,
        base: float = 0.1,
        cap: float = 1.0,
        jitter: float = 0.5,
        clock: Callable[[], float] = time.monotonic,
        rng: Callable[[], float] = random.random,
    ):
        keep_alive = dict(keep_alive or {})
        times = [(f'periods[{r!r}]', t) for r, t in periods.items()] + [('duration', duration)]
        times += [(f'keep_alive[{r!r}]', t) for r, t in keep_alive.items()]
        for what, seconds in times:
            if not (seconds > 0 and math.isfinite(seconds)):
                raise ValueError(f'{what}: must be a positive number of seconds, got {seconds}')
        if not set(keep_alive) <= set(periods):
            raise ValueError(f'keep_alive: expected roles of periods ({", ".join(periods)})')
        shrink = dict(shrink or {})
        for role, fraction in shrink.items():
            if not 0 < fraction <= 1:
                raise ValueError(f'shrink[{role!r}]: must be in (0, 1], got {fraction}')
        self.shrink = shrink
        self.periods = dict(periods)
        self.duration = duration
        self.keep_alive = keep_alive
        self.min_interval = min_interval(max_rate)
        self.retries = Retries(base, cap, jitter, clock, rng)
        self.clock = clock
        self.sent = 0  # calls handed out, cancels included
        self.stopped = False
        self._watches = {role: _Watch() for role in self.periods}
        self._wanted: dict[str, Region] = {}
        self._heard: dict[str, float] = {}
        self._fresh: dict[str, float] = {}  # role -> since when it wants a full report
        self._last_sent = -math.inf

    # -- the control loop's side ---------------------------------------------------------------
    def post(
        self,
        regions: Mapping[str, Region],
        heard: Mapping[str, float] | None = None,
        fresh: Collection[str] = (),
    ) -> None:
        """The region each role needs now (a role left out keeps its watch until it expires), when
        the newest answer of each role found was heard (for the keep-alive; clock time), and the
        roles that want a full report taken from now on."""
        unknown = set(regions) - set(self.periods)
        if unknown:
            raise ValueError(f'regions: no period for role(s) {", ".join(sorted(unknown))}')
        self._wanted = dict(regions)
        self._heard = dict(heard or {})
        now = self.clock()
        self._fresh = {role: self._fresh.get(role, now) for role in fresh}

    def stop(self) -> None:
        """The mission is over: cancel every watch that may stand, then send nothing more."""
        self.stopped = True

    def reissue(self) -> None:
        """The robot moved to another server (``~servers``): every standing watch is renewed now,
        there (a role whose call failed keeps its retry delay)."""
        for watch in self._watches.values():
            watch.renew_at = -math.inf

    # -- the requester's side ----------------------------------------------------------------
    @property
    def standing(self) -> int:
        """Watches granted and not expired (nor cancelled)."""
        now = self.clock()
        return sum(1 for watch in self._watches.values() if watch.expires > now)

    @property
    def done(self) -> bool:
        """Whether, after :meth:`stop`, every cancel went out and got its answer (or none)."""
        now = self.clock()
        return self.stopped and all(
            watch.call is None and self._due_at(role, now)[0] == math.inf
            for role, watch in self._watches.items()
        )

    def next_request(self) -> WatchCall | None:
        """The call to send now, or None (then :meth:`wait_time` says for how long)."""
        now = self.clock()
        if now < self._last_sent + self.min_interval:
            return None
        due: dict[str, str] = {}
        for role in self._watches:
            at, reason = self._due_at(role, now)
            if at <= now and reason is not None:  # a time is due with its reason
                due[role] = reason
        if not due:
            return None
        role = min(due, key=lambda r: self._watches[r].sent_at)  # stable: ties keep the roles' order
        watch = self._watches[role]
        if due[role] == CANCEL:
            region, duration = watch.region or watch.asked, 0.0
            assert region is not None  # a watch to cancel was asked for
        else:
            region, duration = self._wanted[role].box, self.duration
        watch.call = WatchCall(role, region, self.periods[role], duration, due[role])
        watch.asked = region
        watch.sent_at = self._last_sent = now
        self.sent += 1
        return watch.call

    def in_flight(self, role: str) -> bool:
        """Whether a call for ``role`` was handed out and its outcome not reported yet."""
        return role in self._watches and self._watches[role].call is not None

    def wait_time(self) -> float | None:
        """Seconds until :meth:`next_request` may return a call; None: not before the next post."""
        now = self.clock()
        times = [at for role in self._watches if (at := self._due_at(role, now)[0]) < math.inf]
        if not times:
            return None
        return max(0.0, min(times) - now, self._last_sent + self.min_interval - now)

    def on_response(
        self,
        role: str,
        status: int,
        duration: float = 0.0,
        retry_after: float = 0.0,
        message: str = '',
    ) -> Outcome:
        """Record DRVS's answer to the call for ``role`` (with the granted ``duration``)."""
        watch = self._watches[role]
        call, watch.call, watch.unsure = watch.call, None, False
        assert call is not None, f'no call for {role!r} in flight'
        if call.duration == 0:
            return self._cancelled(watch, status)
        outcome = self.retries.on_response(role, status, retry_after, message)
        if status == ACCEPTED:
            granted = duration if duration > 0 and math.isfinite(duration) else call.duration
            watch.region = call.region_of_interest
            watch.expires = watch.sent_at + granted
            watch.renew_at = watch.sent_at + granted / 2
        return outcome

    def on_failure(self, role: str) -> Outcome:
        """Record that the call for ``role`` got no response (server down, timeout, ...)."""
        watch = self._watches[role]
        call, watch.call = watch.call, None
        assert call is not None, f'no call for {role!r} in flight'
        if call.duration == 0:
            self.retries.failed += 1
            return self._cancelled(watch, None)
        watch.unsure = True
        return self.retries.on_failure(role)

    # -- internals -----------------------------------------------------------------------------
    def _due_at(self, role: str, now: float) -> tuple[float, str | None]:
        """When ``role``'s next call is due and why (inf, None: none is, until something changes)."""
        watch = self._watches[role]
        if watch.call is not None:
            return math.inf, None
        if self.stopped:
            return (now, CANCEL) if watch.expires > now or watch.unsure else (math.inf, None)
        if self.invalid is not None or role not in self._wanted:
            return math.inf, None
        wanted = self._wanted[role]
        if watch.expires <= now or watch.region is None:  # (no region: never granted, so expired)
            at, reason = now, NEW
        elif not _inside(wanted.needed, watch.region) or _area(wanted.box) < self.shrink.get(
            role, SHRINK
        ) * _area(watch.region):
            at, reason = now, REGION
        else:
            at, reason = watch.renew_at, RENEW
            if role in self._fresh and watch.sent_at < self._fresh[role]:
                at = now
            elif role in self.keep_alive and role in self._heard:
                at = min(at, max(self._heard[role], watch.sent_at) + self.keep_alive[role])
        return max(at, self.retries.ready_at(role)), reason

    def _cancelled(self, watch: _Watch, status: int | None) -> Outcome:
        watch.expires, watch.region, watch.unsure = -math.inf, None, False
        if status is not None and status != ACCEPTED:
            self.retries.refused[name(status)] += 1
        return Outcome(ACCEPT if status == ACCEPTED else GIVE_UP)
