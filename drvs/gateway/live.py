"""The floor-plan page's live feed, without I/O: short-lived tickets for the browser's event stream,
and what changed since a listener last looked.

A browser's ``EventSource`` cannot send an ``Authorization`` header, and a token in its URL would
be logged; so the page trades its token for a ticket (``POST /v1/tickets``), good once and for
:data:`TICKET_LIFETIME` seconds, and opens ``GET /v1/live?ticket=...``. The stream sends the whole
state first, then each part again when it changes: ``registry``, ``objects``, and per robot
``robot`` (its status) and ``path``. A listener holds at most one pending copy of each part (the
newest is read when it is written), so a slow browser costs memory by the number of parts, never by
time. The page and the events: docs/gateway.md ("The floor-plan page").

>>> from drvs.testing.clock import ManualClock
>>> clock = ManualClock(0.0)
>>> tickets = Tickets(clock)
>>> ticket = tickets.issue('viewer')
>>> tickets.redeem(ticket), tickets.redeem(ticket)
('viewer', None)
"""

from __future__ import annotations

import secrets
from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping
from typing import Any

__all__ = ['MAX_PATH', 'MAX_ROBOTS', 'TICKET_LIFETIME', 'LiveFeed', 'LiveListener', 'Tickets', 'thin_path']

TICKET_LIFETIME = 30.0
"""Seconds a ticket stays good (it is good once)."""
MAX_TICKETS = 1024
"""Tickets outstanding at once; beyond, the oldest is forgotten."""
MAX_ROBOTS = 64
"""Robots the feed follows."""
MAX_PATH = 400
"""Points of a robot's path sent to the page (a longer one is thinned evenly, ends kept)."""

Key = tuple[str, str]
"""A part of the state: (``registry``, ''), (``objects``, ''), (``robot``, NAME), (``path``, NAME)."""


class Tickets:
    """One-use tickets, each standing for its owner (what the token that asked for it may do)."""

    def __init__(
        self, clock: Callable[[], float], lifetime: float = TICKET_LIFETIME, limit: int = MAX_TICKETS
    ):
        self.clock = clock
        self.lifetime = lifetime
        self.limit = limit
        self._tickets: OrderedDict[str, tuple[Any, float]] = OrderedDict()

    def issue(self, owner: Any) -> str:
        """A new ticket for ``owner``, good once within :attr:`lifetime` seconds."""
        self._expire()
        while len(self._tickets) >= self.limit:
            self._tickets.popitem(last=False)
        ticket = secrets.token_urlsafe(24)
        self._tickets[ticket] = (owner, self.clock() + self.lifetime)
        return ticket

    def redeem(self, ticket: str | None) -> Any:
        """The owner of ``ticket`` if it is good (then it is used up); None otherwise."""
        self._expire()
        if not ticket:
            return None
        entry = self._tickets.pop(ticket, None)
        return None if entry is None else entry[0]

    def _expire(self) -> None:
        now = self.clock()
        while self._tickets:
            ticket, (_, until) = next(iter(self._tickets.items()))
            if until > now:
                return
            del self._tickets[ticket]

    def __len__(self) -> int:
        return len(self._tickets)


def thin_path(points: list[list[float]], limit: int = MAX_PATH) -> list[list[float]]:
    """At most ``limit`` of ``points``, evenly spaced, the first and the last kept.

    >>> thin_path([[float(n), 0.0] for n in range(10)], 4)
    [[0.0, 0.0], [3.0, 0.0], [6.0, 0.0], [9.0, 0.0]]
    """
    if len(points) <= limit:
        return points
    step = (len(points) - 1) / (limit - 1)
    return [points[round(n * step)] for n in range(limit)]


class LiveListener:
    """One live stream: the parts changed since it last wrote them, in the order they changed."""

    def __init__(self) -> None:
        self._pending: OrderedDict[Key, None] = OrderedDict()
        self.wake: Callable[[], None] = lambda: None

    def mark(self, key: Key) -> None:
        self._pending[key] = None
        self._pending.move_to_end(key)
        self.wake()

    def take(self) -> list[Key]:
        keys = list(self._pending)
        self._pending.clear()
        return keys

    def __len__(self) -> int:
        return len(self._pending)


class LiveFeed:
    """The state the page shows, read from views that are replaced (never changed in place) when
    a message comes: :meth:`poll` finds the parts whose object changed and marks them on every
    listener.

    :param registry: the newest registry (a list) or None.
    :param objects: the newest fused tracks (a dict) or None.
    :param robots: robot name -> ``{"status": dict, "path": list}``, each value replaced on change.
    """

    def __init__(
        self,
        registry: Callable[[], Any],
        objects: Callable[[], Any],
        robots: Callable[[], Mapping[str, Mapping[str, Any]]],
    ):
        self._views: dict[str, Callable[[], Any]] = {'registry': registry, 'objects': objects}
        self._robots = robots
        self._seen: dict[Key, Any] = {}
        self.listeners: set[LiveListener] = set()

    def listen(self) -> LiveListener:
        """A new listener, with every part known now pending (the whole state first)."""
        listener = LiveListener()
        self.poll()
        for key in self._seen:
            listener.mark(key)
        self.listeners.add(listener)
        return listener

    def leave(self, listener: LiveListener) -> None:
        self.listeners.discard(listener)

    def _current(self) -> Iterator[tuple[Key, Any]]:
        for kind, view in self._views.items():
            value = view()
            if value is not None:
                yield (kind, ''), value
        robots = self._robots()
        for robot in sorted(robots)[:MAX_ROBOTS]:
            for kind in ('robot', 'path'):
                value = robots[robot].get('status' if kind == 'robot' else 'path')
                if value is not None:
                    yield (kind, robot), value

    def poll(self) -> list[Key]:
        """The parts that changed since the last poll, marked on every listener."""
        changed = []
        for key, value in self._current():
            if self._seen.get(key) is not value:
                self._seen[key] = value
                changed.append(key)
        for key in changed:
            for listener in self.listeners:
                listener.mark(key)
        return changed

    def event(self, key: Key) -> tuple[str, dict[str, Any]]:
        """The event that carries part ``key`` as it is now: (event name, JSON data)."""
        kind, robot = key
        value = self._seen[key]
        if kind == 'registry':
            return 'registry', {'vision_systems': value}
        if kind == 'objects':
            return 'objects', value
        if kind == 'robot':
            return 'robot', {'name': robot, **value}
        return 'path', {'name': robot, 'points': thin_path(value)}
