"""A bounded worker pool that sends items to many destinations, one at a time per destination.

The DRVS server forwards each robot request to several vision systems. Each
vision system has one persistent connection that carries one call at a time,
so items queue per destination (FIFO) and at most one is in flight per
destination: a hung destination holds one worker, never more, and the others
keep flowing. Bounds: ``max_pending`` items in all (queued + in flight) and
``max_per_destination`` per destination; :meth:`Dispatcher.submit` refuses
instead of queueing without bound.

No ROS here; ``send`` is any callable. It should handle its own errors; an
exception that escapes it is logged with its traceback and the worker goes on.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable, Hashable, Iterable

from drvs.status import BUSY, Refusal

logger = logging.getLogger('rosout.' + __name__)

__all__ = ['Dispatcher', 'Busy']


class Busy(Refusal):
    """The pool cannot take the items now; the message says why, ``retry_after`` when to try again."""

    def __init__(self, message: str, retry_after: float):
        super().__init__(BUSY, message, retry_after)


class Dispatcher:
    """Worker threads that call ``send(destination, item)``.

    :param send: the call to make; runs on a worker thread.
    :param workers: number of worker threads.
    :param max_pending: items queued or in flight, in all.
    :param max_per_destination: items queued or in flight for one destination.
    :param retry_after: seconds a refused caller is told to wait (:class:`Busy`).
    """

    def __init__(
        self,
        send: Callable[[Hashable, object], None],
        workers: int = 8,
        max_pending: int = 1000,
        max_per_destination: int = 10,
        retry_after: float = 0.5,
    ):
        if workers < 1 or max_pending < 1 or max_per_destination < 1:
            raise ValueError('workers, max_pending and max_per_destination must be at least 1')
        self.send = send
        self.workers = workers
        self.max_pending = max_pending
        self.max_per_destination = max_per_destination
        self.retry_after = retry_after
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._queues: dict[Hashable, deque] = {}
        self._in_flight: set[Hashable] = set()
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
            self._queues.clear()
            self._ready.clear()
            self._wake.notify_all()
        for thread in self._threads:
            thread.join(timeout)

    def submit(self, destinations: Iterable[Hashable], item: object) -> tuple[list, list]:
        """Queue ``item`` for each destination; return (accepted, skipped) destinations.

        A destination with ``max_per_destination`` items already is skipped.

        :raises Busy: the pool has no room for all the accepted ones (nothing is queued then).
        """
        destinations = list(destinations)
        with self._lock:
            if self._stopping:
                raise Busy('busy: the server is shutting down; try again later', self.retry_after)
            accepted, skipped = [], []
            for destination in destinations:
                load = len(self._queues.get(destination, ())) + (destination in self._in_flight)
                (skipped if load >= self.max_per_destination else accepted).append(destination)
            if self._pending + len(accepted) > self.max_pending:
                raise Busy(
                    f'busy: {self._pending} forwards pending, {len(accepted)} more would pass the limit of '
                    f'{self.max_pending}; try again later',
                    self.retry_after,
                )
            for destination in accepted:
                queue = self._queues.setdefault(destination, deque())
                queue.append(item)
                if len(queue) == 1 and destination not in self._in_flight:
                    self._ready.append(destination)
            self._pending += len(accepted)
            self._wake.notify(len(accepted))
            return accepted, skipped

    def drop(self, destination: Hashable) -> int:
        """Forget the queued items of ``destination`` (e.g. it was removed); return how many."""
        with self._lock:
            queue = self._queues.pop(destination, None)
            if not queue:
                return 0
            self._pending -= len(queue)
            try:
                self._ready.remove(destination)
            except ValueError:
                pass  # in flight: not in the ready list
            return len(queue)

    def _work(self) -> None:
        while True:
            with self._lock:
                while not self._ready and not self._stopping:
                    self._wake.wait()
                if self._stopping:
                    return
                destination = self._ready.popleft()
                queue = self._queues[destination]
                item = queue.popleft()
                self._in_flight.add(destination)
            try:
                self.send(destination, item)
            except Exception:
                logger.exception('sending to %s failed unexpectedly', destination)
            with self._lock:
                self._in_flight.discard(destination)
                self._pending -= 1
                queue = self._queues.get(destination)
                if queue:
                    self._ready.append(destination)
                    self._wake.notify()
                elif queue is not None:
                    del self._queues[destination]
