"""The server's standing requests ("watches"): which vision systems serve each, and what to send them.

Watches keyed by (caller id, ``request_id``), granted and expired; who serves each is
worked out again whenever the registry changes, and the difference becomes
:class:`Forward` items (new, renewal, withdrawal, one-shot). No ROS here; the clock is
injected; not thread-safe (the server holds one lock). The rules: docs/nodes/drvs_server.md;
how and why: docs/design.md ("Watches: the server's side").

>>> from drvs.testing import ManualClock
>>> registry = Registry()
>>> registry.register('/vs1/detect_object_boundary', [(0, 0), (2, 0), (2, 2)], watch_service=True)
'registered'
>>> clock = ManualClock(100.0)
>>> table = WatchTable(registry, clock)
>>> answer = table.request('/robot', 'crate', 'colour:0,0,0,9,9,9', 'colour', (0.5, 0.2, 1.0, 0.4),
...                        '/robot/callback_coordinates', 0.5, 10.0, False)
>>> answer.change, [(f.kind, f.vision_system, f.duration) for f in answer.forwards]
('started', [('new', '/vs1/detect_object_boundary', 10.0)])
>>> clock.now += 10.0
>>> [(f.kind, f.vision_system, f.duration) for f in table.sync()]
[('withdrawal', '/vs1/detect_object_boundary', 0.0)]
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

from drvs.common.validation import ValidationError, watch_terms
from drvs.server.dispatch import Busy
from drvs.server.registry import Registry

logger = logging.getLogger('rosout.' + __name__)

__all__ = [
    'CANCELLED',
    'NEW',
    'NOT_STANDING',
    'ONE_SHOT',
    'RENEWAL',
    'RENEWED',
    'STARTED',
    'WITHDRAWAL',
    'Answer',
    'Forward',
    'Watch',
    'WatchTable',
    'watch_terms',
]

NEW, RENEWAL, WITHDRAWAL, ONE_SHOT = 'new', 'renewal', 'withdrawal', 'one-shot'
STARTED, RENEWED, CANCELLED, NOT_STANDING = 'started', 'renewed', 'cancelled', 'not standing'

Box = tuple[float, float, float, float]
Key = tuple[str, str]  # (caller id, request_id)


@dataclass(frozen=True)
class Watch:
    """One standing watch as granted. Immutable: a renewal replaces it whole."""

    caller: str
    request_id: str
    algorithm: str  # as asked, NAME[:PARAMS]: forwarded unchanged
    algorithm_name: str  # its NAME, for matching
    region: Box
    callback_service: str
    period: float  # granted, seconds
    duration: float  # granted, seconds
    changes_only: bool
    expires_at: float  # on the table's clock
    forward_as: tuple[str, str] | None = (
        None  # a fused watch: (callback_service, request_id) of the fusion stage
    )

    @property
    def key(self) -> Key:
        return (self.caller, self.request_id)

    def forwarded(self) -> tuple[str, str]:
        """The (callback_service, request_id) the vision systems are asked to call back with."""
        return self.forward_as or (self.callback_service, self.request_id)


@dataclass(frozen=True)
class Forward:
    """One thing to send to one vision system for one watch.

    :param kind: ``NEW``, ``RENEWAL``, ``WITHDRAWAL`` (a WatchObjectBoundary forward)
        or ``ONE_SHOT`` (a DetectObjectBoundary request).
    :param vision_system: its DetectObjectBoundary service name, as registered.
    :param duration: the duration to forward: the watch's time left, 0 for a
        withdrawal (and unused by a one-shot).
    """

    kind: str
    vision_system: str
    watch: Watch
    duration: float = 0.0


@dataclass(frozen=True)
class Answer:
    """What :meth:`WatchTable.request` did: ``STARTED``, ``RENEWED``, ``CANCELLED`` or
    ``NOT_STANDING`` (a cancel of an unknown watch), the granted terms, and what to send."""

    change: str
    period: float
    duration: float
    forwards: list[Forward]


class WatchTable:
    """The watches standing on the server and the vision systems serving each.

    :param registry: the vision systems (matching, and whether each has a watch service).
    :param clock: seconds (the server passes ROS time).
    :param min_period: shortest period granted, seconds.
    :param max_duration: longest duration granted, seconds.
    :param max_watches: watches that may stand at once.
    :param busy_retry_after: ``retry_after`` of the ``BUSY`` refusal beyond ``max_watches``.
    :param retry_delay: seconds before a forward that did not get through is sent again.
    """

    def __init__(
        self,
        registry: Registry,
        clock: Callable[[], float],
        min_period: float = 0.1,
        max_duration: float = 60.0,
        max_watches: int = 1000,
        busy_retry_after: float = 0.5,
        retry_delay: float = 1.0,
    ):
        if not (min_period > 0 and max_duration > 0 and max_watches >= 1):
            raise ValueError('min_period and max_duration must be positive, max_watches at least 1')
        self.registry = registry
        self.clock = clock
        self.min_period = float(min_period)
        self.max_duration = float(max_duration)
        self.max_watches = int(max_watches)
        self.busy_retry_after = float(busy_retry_after)
        self.retry_delay = float(retry_delay)
        self._watches: dict[Key, Watch] = {}
        # Per watch, the vision systems serving it -> when its next one-shot is due
        # (None: it has a watch service and holds the watch itself).
        self._serving: dict[Key, dict[str, float | None]] = {}
        self._owners: dict[tuple[str, str], str] = {}  # (callback_service, request_id) -> caller
        self._matched: int | None = None  # the registry version last matched against; None: match again
        self._retry_at: float | None = None  # when to match again for undelivered forwards

    def __len__(self) -> int:
        return len(self._watches)

    def get(self, key: Key) -> Watch | None:
        return self._watches.get(key)

    def standing(self) -> list[Watch]:
        """Every watch standing now."""
        return list(self._watches.values())

    def serving(self, key: Key) -> list[str]:
        """The vision systems serving the watch ``key`` now (none if it does not stand), sorted."""
        return sorted(self._serving.get(key, ()))

    def request(
        self,
        caller: str,
        request_id: str,
        algorithm: str,
        algorithm_name: str,
        region: Box,
        callback_service: str,
        period: float,
        duration: float,
        changes_only: bool,
        forward_as: tuple[str, str] | None = None,
    ) -> Answer:
        """Start, renew or (``duration`` 0) cancel the watch (``caller``, ``request_id``).

        The fields are checked already (:func:`watch_terms`, the server's request checks).
        ``forward_as``: a fused watch, forwarded with the fusion stage's callback service and
        request id instead of the caller's (:mod:`drvs.server.fusion`).

        :raises ValidationError: ``request_id``: another caller's watch has the same
            ``callback_service`` and ``request_id``.
        :raises Busy: a new watch beyond ``max_watches``.
        """
        now = self.clock()
        key = (caller, request_id)
        old = self._watches.get(key)
        if duration == 0:
            if old is None:
                return Answer(NOT_STANDING, 0.0, 0.0, [])
            served = len(self._serving[key])
            forwards = self._drop(key)
            logger.info('watch %r of %s cancelled; %d vision systems served it', request_id, caller, served)
            return Answer(CANCELLED, old.period, 0.0, forwards)
        owner = self._owners.get((callback_service, request_id))
        if owner is not None and owner != caller:
            raise ValidationError(
                f'request_id: {request_id!r} with callback_service {callback_service} already names a watch '
                f'of {owner}; vision systems could not tell the two apart: choose another request_id'
            )
        if old is None and len(self._watches) >= self.max_watches:
            raise Busy(
                f'busy: {len(self._watches)} watches stand, the most this server keeps; try again later',
                self.busy_retry_after,
            )
        granted = min(duration, self.max_duration)
        watch = Watch(
            caller,
            request_id,
            algorithm,
            algorithm_name,
            (float(region[0]), float(region[1]), float(region[2]), float(region[3])),
            callback_service,
            max(period, self.min_period),
            granted,
            bool(changes_only),
            now + granted,
            forward_as,
        )
        forwards = []
        renewal = old is not None and old.forwarded() == watch.forwarded()
        if old is not None and not renewal:  # known to the vision systems under its old callback
            forwards += self._drop(key)
        self._watches[key] = watch
        self._owners[(callback_service, request_id)] = caller
        serving = self._serving.setdefault(key, {})
        forwards += self._match(watch, serving, now, renewal)
        forwards += self._one_shots(watch, serving, now)
        if old is None:
            logger.info(
                'watch %r of %s: %s in %s to %s, every %g s for %g s; %d vision systems serve it',
                request_id,
                caller,
                algorithm,
                watch.region,
                callback_service,
                watch.period,
                watch.duration,
                len(serving),
            )
        else:
            logger.debug('watch %r of %s renewed (%d vision systems)', request_id, caller, len(serving))
        return Answer(RENEWED if old is not None else STARTED, watch.period, watch.duration, forwards)

    def sync(self) -> list[Forward]:
        """Expire watches, follow the registry's changes, and send the one-shots that are due."""
        now = self.clock()
        forwards = []
        for key, watch in list(self._watches.items()):
            if watch.expires_at <= now:
                served = len(self._serving[key])
                forwards += self._drop(key)
                logger.info(
                    'watch %r of %s expired (not renewed within %g s); %d vision systems served it',
                    watch.request_id,
                    watch.caller,
                    watch.duration,
                    served,
                )
        version = self.registry.version
        retry = self._retry_at is not None and self._retry_at <= now
        rematch, self._matched = version != self._matched or retry, version
        if retry:
            self._retry_at = None
        for key, watch in self._watches.items():
            serving = self._serving[key]
            if rematch:
                forwards += self._match(watch, serving, now, renewal=False)
            forwards += self._one_shots(watch, serving, now)
        return forwards

    def next_due(self) -> float | None:
        """When :meth:`sync` next has something to do by the clock (an expiry, a one-shot); None: nothing."""
        times = [watch.expires_at for watch in self._watches.values()]
        times += [due for serving in self._serving.values() for due in serving.values() if due is not None]
        if self._retry_at is not None:
            times.append(self._retry_at)
        return min(times, default=None)

    def adopt(self, watch: Watch) -> bool:
        """Take over ``watch`` from a replica gone silent (docs/registry.md): it stands here from
        now on, and the next :meth:`sync` forwards it to the vision systems that serve it. False
        (nothing done) if a watch of the same key stands here already, or its callback is taken."""
        owner = self._owners.get((watch.callback_service, watch.request_id))
        if watch.key in self._watches or (owner is not None and owner != watch.caller):
            return False
        if len(self._watches) >= self.max_watches:
            return False
        self._watches[watch.key] = watch
        self._serving[watch.key] = {}
        self._owners[(watch.callback_service, watch.request_id)] = watch.caller
        self._matched = None
        return True

    def forget(self, vision_system: str) -> None:
        """``vision_system`` registered anew and holds no watches: forward them again at the next sync."""
        for serving in self._serving.values():
            serving.pop(vision_system, None)
        self._matched = None

    def undelivered(self, forward: Forward) -> None:
        """``forward`` did not get through (not queued, or it failed): a new or renewed watch is
        forwarded again ``retry_delay`` seconds later; a lost withdrawal or one-shot is not sent again."""
        if forward.kind not in (NEW, RENEWAL):
            return
        watch = self._watches.get(forward.watch.key)
        if watch is not None and watch.callback_service == forward.watch.callback_service:
            self._serving[watch.key].pop(forward.vision_system, None)
            retry_at = self.clock() + self.retry_delay
            self._retry_at = retry_at if self._retry_at is None else min(self._retry_at, retry_at)

    def _drop(self, key: Key) -> list[Forward]:
        """Remove the watch ``key``; its withdrawals."""
        watch = self._watches.pop(key)
        serving = self._serving.pop(key)
        if self._owners.get((watch.callback_service, watch.request_id)) == watch.caller:
            del self._owners[(watch.callback_service, watch.request_id)]
        return [Forward(WITHDRAWAL, name, watch) for name, due in sorted(serving.items()) if due is None]

    def _match(self, watch: Watch, serving: dict, now: float, renewal: bool) -> list[Forward]:
        """Bring ``serving`` up to the registry: forwards to who joins (and, on ``renewal``, to who
        stays), withdrawals from who leaves; one-shot vision systems join due at once."""
        wanted = set(self.registry.match(watch.region, watch.algorithm_name))
        forwards = []
        for name in sorted(serving.keys() - wanted):
            if serving.pop(name) is None:
                forwards.append(Forward(WITHDRAWAL, name, watch))
        left = watch.expires_at - now
        for name in sorted(wanted):
            if name in serving:
                if renewal and serving[name] is None:
                    forwards.append(Forward(RENEWAL, name, watch, left))
                continue
            entry = self.registry.get(name)
            if entry is None:  # removed since the match
                continue
            serving[name] = None if entry.watch_service else now
            if entry.watch_service:
                forwards.append(Forward(NEW, name, watch, left))
        return forwards

    @staticmethod
    def _one_shots(watch: Watch, serving: dict, now: float) -> list[Forward]:
        """The one-shots due by ``now``; each next one a period later (no burst to catch up)."""
        forwards = []
        for name, due in serving.items():
            if due is not None and due <= now:
                forwards.append(Forward(ONE_SHOT, name, watch))
                due += watch.period
                serving[name] = due if due > now else now + watch.period
        return forwards
