"""The gateway's watches: numbered events, a bounded buffer to resume from, a bounded queue per
listener, and when to renew or withdraw the DRVS watch behind each. No I/O, an injected clock;
called from one thread (the gateway's event loop). The rules: docs/gateway.md ("Watches").

An HTTP watch stands on a DRVS watch the gateway asked for ``duration`` seconds and renews at half
of it while the HTTP watch stands. Nobody listening for ``linger`` seconds (counted from its
creation too) withdraws it, as does ``DELETE``.

>>> from drvs.testing.clock import ManualClock
>>> clock = ManualClock(0.0)
>>> hub = WatchHub(clock, duration=10, linger=30, buffer=4, queue=2)
>>> watch = hub.open('w1', 'gw-1', owner='robot', body=None)
>>> listener = hub.listen('w1')
>>> for n in range(3):
...     _ = hub.deliver('gw-1', {'n': n})
>>> [(event.id, event.kind, event.data.get('n')) for event in listener.take()]
[(1, 'status', None), (2, 'callback', 1), (3, 'callback', 2)]
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

__all__ = ['Event', 'GatewayWatch', 'Listener', 'WatchHub']

CALLBACK, STATUS, END = 'callback', 'status', 'end'


@dataclass(frozen=True)
class Event:
    """One Server-Sent Event: ``id`` (per watch, from 1, increasing), ``kind`` (``callback``,
    ``status`` or ``end``) and its JSON ``data``."""

    id: int
    kind: str
    data: dict[str, Any]


class Listener:
    """One event stream's queue: at most ``capacity`` events; when full, the oldest is dropped and
    the next :meth:`take` starts with a ``status`` event saying how many."""

    def __init__(self, watch: GatewayWatch, capacity: int):
        self.watch = watch
        self.capacity = capacity
        self._queue: deque[Event] = deque()
        self.dropped = 0
        self._last_dropped = 0
        self.wake: Callable[[], None] = lambda: None

    def put(self, event: Event) -> None:
        if len(self._queue) >= self.capacity:
            self._last_dropped = self._queue.popleft().id
            self.dropped += 1
        self._queue.append(event)
        self.wake()

    def replay(self, events: list[Event]) -> None:
        """Queue ``events`` (a resume from the watch's bounded buffer) whatever the capacity."""
        self._queue.extend(events)

    def take(self) -> list[Event]:
        """Every event waiting, oldest first, after a ``status`` event if some were dropped."""
        events = []
        if self.dropped:
            events.append(
                Event(
                    self._last_dropped,
                    STATUS,
                    {
                        'status': 'DROPPED',
                        'dropped': self.dropped,
                        'message': f'{self.dropped} event(s) dropped: this client read too slowly',
                    },
                )
            )
            self.dropped = 0
        events.extend(self._queue)
        self._queue.clear()
        return events

    def __len__(self) -> int:
        return len(self._queue)


@dataclass
class GatewayWatch:
    """One HTTP watch: its public ``id``, the DRVS watch's ``request_id``, its ``owner`` (a token's
    name) and ``body``; its events and listeners."""

    id: str
    request_id: str
    owner: str
    body: Any
    created: float
    buffer: deque[Event]
    listeners: list[Listener] = field(default_factory=list)
    next_id: int = 1
    renew_at: float = 0.0
    quiet_since: float | None = None  # when the last listener left (or the watch was made)
    ended: bool = False
    granted: dict[str, Any] = field(default_factory=dict)  # the DRVS answer: period, duration, vision_systems

    def publish(self, kind: str, data: dict[str, Any]) -> Event:
        event = Event(self.next_id, kind, data)
        self.next_id += 1
        self.buffer.append(event)
        for listener in self.listeners:
            listener.put(event)
        return event


class WatchHub:
    """Every open watch, by its id and by its DRVS request id.

    :param clock: monotonic seconds.
    :param duration: seconds asked of each DRVS watch; renewed at half.
    :param linger: seconds a watch stands with nobody listening.
    :param buffer: events kept per watch for ``Last-Event-ID``.
    :param queue: events waiting per listener.
    """

    def __init__(self, clock: Callable[[], float], duration: float, linger: float, buffer: int, queue: int):
        self.clock = clock
        self.duration = duration
        self.linger = linger
        self.buffer = buffer
        self.queue = queue
        self._watches: dict[str, GatewayWatch] = {}
        self._by_request: dict[str, GatewayWatch] = {}
        self.withdrawn = 0  # watches ended for want of listeners

    def __len__(self) -> int:
        return len(self._watches)

    def __iter__(self) -> Iterator[GatewayWatch]:
        return iter(list(self._watches.values()))

    def get(self, watch_id: str) -> GatewayWatch | None:
        return self._watches.get(watch_id)

    def owned_by(self, owner: str) -> int:
        """How many watches ``owner`` holds open."""
        return sum(1 for watch in self._watches.values() if watch.owner == owner)

    def open(
        self, watch_id: str, request_id: str, owner: str, body: Any, granted: dict | None = None
    ) -> GatewayWatch:
        """A new watch whose DRVS watch was granted now (``granted['duration']`` seconds, else
        ``duration``): renewed at half of that."""
        now = self.clock()
        watch = GatewayWatch(
            watch_id, request_id, owner, body, now, deque(maxlen=self.buffer), quiet_since=now
        )
        self.renewed(watch, granted or {})
        self._watches[watch_id] = watch
        self._by_request[request_id] = watch
        return watch

    def renewed(self, watch: GatewayWatch, granted: dict[str, Any]) -> None:
        """The DRVS watch was granted again (``granted`` as DRVS answered): next renewal at half."""
        watch.granted = dict(granted)
        duration = float(granted.get('duration') or self.duration)
        watch.renew_at = self.clock() + duration / 2

    def retry_renewal(self, watch: GatewayWatch, after: float, data: dict[str, Any]) -> None:
        """A renewal failed: tell the listeners (a ``status`` event) and try again ``after`` seconds on."""
        watch.renew_at = self.clock() + max(after, 0.1)
        watch.publish(STATUS, data)

    def deliver(self, request_id: str, data: dict[str, Any]) -> bool:
        """A callback of the DRVS watch ``request_id``: a ``callback`` event; False if no watch has it."""
        watch = self._by_request.get(request_id)
        if watch is None or watch.ended:
            return False
        watch.publish(CALLBACK, data)
        return True

    def listen(self, watch_id: str, last_event_id: int | None = None) -> Listener:
        """A new listener of the watch ``watch_id``, given every buffered event after
        ``last_event_id`` (with a ``status`` event first when some are no longer buffered); without
        one, every buffered event (those of a watch nobody listened to yet).

        :raises KeyError: no such watch.
        """
        watch = self._watches[watch_id]
        listener = Listener(watch, self.queue)
        replay: list[Event] = []  # kept whole, however long: the buffer bounds it
        if last_event_id is not None:
            oldest = watch.buffer[0].id if watch.buffer else watch.next_id
            if last_event_id + 1 < oldest:
                lost = oldest - last_event_id - 1
                replay.append(
                    Event(
                        oldest - 1,
                        STATUS,
                        {
                            'status': 'GAP',
                            'dropped': lost,
                            'message': f'{lost} event(s) after {last_event_id} are no longer kept; '
                            f'resuming from {oldest}',
                        },
                    )
                )
            replay.extend(event for event in watch.buffer if event.id > last_event_id)
        else:
            replay.extend(watch.buffer)
        listener.replay(replay)
        watch.listeners.append(listener)
        watch.quiet_since = None
        return listener

    def leave(self, listener: Listener) -> None:
        """``listener``'s stream closed; the linger starts when it was the last."""
        watch = listener.watch
        if listener in watch.listeners:
            watch.listeners.remove(listener)
        if not watch.listeners:
            watch.quiet_since = self.clock()

    def end(self, watch_id: str, reason: str) -> GatewayWatch | None:
        """End the watch ``watch_id`` (DELETE, or withdrawn): an ``end`` event, then forgotten. The
        caller withdraws the DRVS watch. None if there was none."""
        watch = self._watches.pop(watch_id, None)
        if watch is None:
            return None
        self._by_request.pop(watch.request_id, None)
        watch.publish(END, {'reason': reason})
        watch.ended = True
        return watch

    def due(self) -> tuple[list[GatewayWatch], list[GatewayWatch]]:
        """(watches to renew now, watches ended now for want of listeners — withdraw them)."""
        now = self.clock()
        ended = [
            watch
            for watch in self._watches.values()
            if watch.quiet_since is not None and now - watch.quiet_since >= self.linger
        ]
        for watch in ended:
            self.end(watch.id, f'nobody listened for {self.linger:g} s')
        self.withdrawn += len(ended)
        renew = [watch for watch in self._watches.values() if now >= watch.renew_at]
        return renew, ended
