"""A bounded worker pool that sends items to many destinations, one at a time per destination.

The DRVS server forwards through it: items queue per destination, at most one in flight
each, ``max_pending`` in all; :meth:`Dispatcher.submit` refuses rather than queue without
bound, and an item that can start without blocking is sent by the thread at hand. Items
submitted for a caller are shared fairly: a caller holds at most its fair share of a
destination's places (:func:`fair_share`) and is refused ``RATE_LIMITED`` beyond it
(:class:`OverShare`), so one caller's flood leaves room for every other caller. No ROS here;
``send`` and ``begin`` are any callables. How and why: docs/design.md ("Forwarding").
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable, Hashable, Iterable

from drvs.common.status import BUSY, RATE_LIMITED, Refusal

logger = logging.getLogger('rosout.' + __name__)

__all__ = ['Dispatcher', 'Busy', 'OverShare', 'fair_share']

Begin = Callable[[Hashable, object, Callable[[], None]], bool]
"""``begin(destination, item, done) -> bool``: start sending without blocking; True if it
started (``done()`` will then be called once, from any thread, when it is over), False to
leave the item to a worker's ``send``."""


class Busy(Refusal):
    """The pool cannot take the items now; the message says why, ``retry_after`` when to try again."""

    def __init__(self, message: str, retry_after: float):
        super().__init__(BUSY, message, retry_after)


class OverShare(Refusal):
    """A caller holds its fair share of every destination it asked for: ``RATE_LIMITED``."""

    def __init__(self, message: str, retry_after: float):
        super().__init__(RATE_LIMITED, message, retry_after)


def fair_share(places: int, callers: int) -> int:
    """How many of a destination's ``places`` one of ``callers`` callers (those holding some, and
    the one asking) may hold: a fifth of the places (at least one) stays free for a caller yet to
    come, the rest is split evenly; at least one each.

    >>> fair_share(10, 1), fair_share(10, 2), fair_share(10, 3), fair_share(10, 20), fair_share(1, 1)
    (8, 4, 2, 1, 1)
    """
    spare = max(1, places // 5) if places > 1 else 0
    return max(1, (places - spare) // max(1, callers))


class Dispatcher:
    """Worker threads that call ``send(destination, item)``, and sends started without them.

    :param send: the call to make; runs on a worker thread.
    :param workers: number of worker threads.
    :param max_pending: items queued or in flight, in all.
    :param max_per_destination: items queued or in flight for one destination.
    :param retry_after: seconds a refused caller is told to wait (:class:`Busy`).
    :param begin: sends an item without blocking if it can (:data:`Begin`); tried first.
    """

    def __init__(
        self,
        send: Callable[[Hashable, object], None],
        workers: int = 8,
        max_pending: int = 1000,
        max_per_destination: int = 10,
        retry_after: float = 0.5,
        begin: Begin | None = None,
    ):
        if workers < 1 or max_pending < 1 or max_per_destination < 1:
            raise ValueError('workers, max_pending and max_per_destination must be at least 1')
        self.send = send
        self.begin = begin
        self.workers = workers
        self.max_pending = max_pending
        self.max_per_destination = max_per_destination
        self.retry_after = retry_after
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._queues: dict[Hashable, deque] = {}
        self._in_flight: dict[Hashable, Hashable | None] = {}  # destination -> its item's caller
        self._held: dict[tuple[Hashable, Hashable], int] = {}  # (destination, caller) -> queued + in flight
        self._holders: dict[Hashable, int] = {}  # destination -> callers holding some of its places
        self._ready: deque = deque()  # destinations with queued items and nothing in flight
        self._pending = 0
        self._threads: list[threading.Thread] = []
        self._stopping = False

    @property
    def pending(self) -> int:
        return self._pending

    def start(self) -> None:
        for number in range(self.workers):
            thread = threading.Thread(target=self._work, name=f'dispatch-{number}', daemon=True)
            thread.start()
            self._threads.append(thread)

    def stop(self, timeout: float = 5.0) -> None:
        """Drop what is queued and stop the workers (in-flight sends finish or time out on their own)."""
        with self._lock:
            self._stopping = True
            self._pending -= sum(len(queue) for queue in self._queues.values())
            for destination, queue in self._queues.items():
                for caller, _ in queue:
                    self._let_go(destination, caller)
            self._queues.clear()
            self._ready.clear()
            self._wake.notify_all()
        for thread in self._threads:
            thread.join(timeout)

    def submit(
        self,
        destinations: Iterable[Hashable],
        item: object,
        wake: bool = True,
        caller: Hashable | None = None,
    ) -> tuple[list, list]:
        """Queue ``item`` for each destination; return (accepted, skipped) destinations.

        A destination with ``max_per_destination`` items already is skipped, and so is one where
        ``caller`` (None: nobody's, no share) holds its :func:`fair_share` already. With
        ``wake`` false nothing is sent yet: call :meth:`release` with ``len(accepted)``
        soon, on this thread (a worker or a send that ends may take them first).

        :raises Busy: the pool has no room for all the accepted ones (nothing is queued then).
        :raises OverShare: nothing accepted, and ``caller`` holds its share of some destination.
        """
        destinations = list(destinations)
        with self._lock:
            if self._stopping:
                raise Busy('busy: the server is shutting down; try again later', self.retry_after)
            accepted: list[Hashable] = []
            skipped: list[Hashable] = []
            over: list[tuple[Hashable, int, int]] = []  # (destination, held, share) for the refusal
            for destination in destinations:
                load = len(self._queues.get(destination, ())) + (destination in self._in_flight)
                if caller is not None and (holding := self._over_share(destination, caller)):
                    skipped.append(destination)
                    over.append((destination, *holding))
                elif load >= self.max_per_destination:
                    skipped.append(destination)
                else:
                    accepted.append(destination)
            if over and not accepted:
                destination, held, _ = over[0]
                raise OverShare(
                    f'rate limited: {caller} holds {held} of the {self.max_per_destination} forward places '
                    f'of {destination}, its fair share while {self._callers(destination, caller) - 1} other '
                    f'caller(s) wait there; try again after {self.retry_after:g} s',
                    self.retry_after,
                )
            if self._pending + len(accepted) > self.max_pending:
                raise Busy(
                    f'busy: {self._pending} forwards pending, {len(accepted)} more would pass the limit of '
                    f'{self.max_pending}; try again later',
                    self.retry_after,
                )
            for destination in accepted:
                queue = self._queues.setdefault(destination, deque())
                queue.append((caller, item))
                if caller is not None:
                    held = self._held.get((destination, caller), 0)
                    if held == 0:
                        self._holders[destination] = self._holders.get(destination, 0) + 1
                    self._held[destination, caller] = held + 1
                if len(queue) == 1 and destination not in self._in_flight:
                    self._ready.append(destination)
            self._pending += len(accepted)
            if wake:
                self._wake.notify(len(accepted))
            return accepted, skipped

    def _callers(self, destination: Hashable, caller: Hashable) -> int:
        """The callers holding places of ``destination``, ``caller`` counted whether or not it holds one."""
        holders = self._holders.get(destination, 0)
        return holders if (destination, caller) in self._held else holders + 1

    def _over_share(self, destination: Hashable, caller: Hashable) -> tuple[int, int] | None:
        """(held, share) when ``caller`` holds its fair share of ``destination`` already, else None."""
        held = self._held.get((destination, caller), 0)
        share = fair_share(self.max_per_destination, self._callers(destination, caller))
        return (held, share) if held >= share else None

    def _let_go(self, destination: Hashable, caller: Hashable | None) -> None:
        """One of ``caller``'s items for ``destination`` is done with or dropped (lock held)."""
        if caller is None:
            return
        key = (destination, caller)
        left = self._held.get(key, 0) - 1
        if left > 0:
            self._held[key] = left
        elif self._held.pop(key, None) is not None:
            holders = self._holders[destination] - 1
            if holders:
                self._holders[destination] = holders
            else:
                del self._holders[destination]

    def holding(self, destination: Hashable, caller: Hashable) -> int:
        """How many of ``destination``'s places ``caller`` holds now (queued and in flight)."""
        with self._lock:
            return self._held.get((destination, caller), 0)

    def release(self, count: int) -> None:
        """Send up to ``count`` items that are ready (queued with ``submit(..., wake=False)``):
        each is started on this thread if ``begin`` can, else left to a worker."""
        if self.begin is None:
            with self._lock:
                self._wake.notify(count)
            return
        for _ in range(count):
            with self._lock:
                if not self._ready or self._stopping:
                    return
                destination = self._ready.popleft()
                caller, item = self._queues[destination].popleft()
                self._in_flight[destination] = caller
            self._begin_or_hand_over(destination, item)

    def drop(self, destination: Hashable) -> int:
        """Forget the queued items of ``destination`` (e.g. it was removed); return how many."""
        with self._lock:
            queue = self._queues.pop(destination, None)
            if not queue:
                return 0
            self._pending -= len(queue)
            for caller, _ in queue:
                self._let_go(destination, caller)
            try:
                self._ready.remove(destination)
            except ValueError:
                pass  # in flight: not in the ready list
            return len(queue)

    def _begin(self, destination: Hashable, item: object) -> bool:
        """Try ``begin``; True if the item is on its way or done with (an exception is logged)."""
        begin = self.begin
        if begin is None:  # nothing to try: the workers send it
            return False
        try:
            return begin(destination, item, lambda: self._finished(destination))
        except Exception:
            logger.exception('sending to %s failed unexpectedly', destination)
            self._finished(destination)
            return True

    def _begin_or_hand_over(self, destination: Hashable, item: object) -> None:
        """Start ``destination``'s in-flight ``item`` with ``begin``, or give it back to the workers."""
        if self._begin(destination, item):
            return
        with self._lock:
            caller = self._in_flight.pop(destination, None)
            queue = self._queues.get(destination)
            if queue is None or self._stopping:  # dropped meanwhile: so is the item
                self._pending -= 1
                self._let_go(destination, caller)
                return
            queue.appendleft((caller, item))
            self._ready.appendleft(destination)
            self._wake.notify()

    def _finished(self, destination: Hashable) -> None:
        """The item in flight to ``destination`` is done with: start its next one, if any."""
        with self._lock:
            self._let_go(destination, self._in_flight.pop(destination, None))
            self._pending -= 1
            queue = self._queues.get(destination)
            if not queue:
                if queue is not None:
                    del self._queues[destination]
                return
            if self.begin is None or self._stopping:
                self._ready.append(destination)
                self._wake.notify()
                return
            caller, item = queue.popleft()
            self._in_flight[destination] = caller
        self._begin_or_hand_over(destination, item)

    def _work(self) -> None:
        while True:
            with self._lock:
                while not self._ready and not self._stopping:
                    self._wake.wait()
                if self._stopping:
                    return
                destination = self._ready.popleft()
                queue = self._queues[destination]
                caller, item = queue.popleft()
                self._in_flight[destination] = caller
            if self.begin is not None and self._begin(destination, item):
                continue
            try:
                self.send(destination, item)
            except Exception:
                logger.exception('sending to %s failed unexpectedly', destination)
            self._finished(destination)
