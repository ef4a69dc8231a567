"""What the server's acknowledgements say, and the ones it makes once and shares.

The texts are part of the interface (docs/nodes/drvs_server.md); tests assert them word for
word. No ROS here: the glue puts them into the service responses.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

from drvs.server.dispatch import Busy
from drvs.server.watch_table import CANCELLED, NOT_STANDING

__all__ = [
    'MAX_REPLIES_KEPT',
    'SharedReplies',
    'busy_everywhere',
    'forwarded',
    'sent_to_none',
    'watch_answer',
]

MAX_REPLIES_KEPT = 4096
"""Acknowledgements kept for reuse, one per (vision systems forwarded to, skipped)."""

K = TypeVar('K', bound=Hashable)
V = TypeVar('V')


def forwarded(count: int, skipped: int) -> str:
    """The acknowledgement of a request sent to ``count`` vision systems, ``skipped`` busy ones not.

    >>> forwarded(1, 0), forwarded(2, 1)
    ('forwarded to 1 vision system', 'forwarded to 2 vision systems; 1 busy vision system(s) skipped')
    """
    message = f'forwarded to {count} vision system{"s" if count != 1 else ""}'
    if skipped:
        message += f'; {skipped} busy vision system(s) skipped'
    return message


def sent_to_none(covered_by_others: bool, algorithm: str) -> str:
    """The acknowledgement of a valid request no vision system gets: ``covered_by_others`` when
    vision systems that run other algorithms cover its region.

    >>> sent_to_none(True, 'sift')
    "no vision system that runs 'sift' covers the region of interest"
    """
    if covered_by_others:
        return f'no vision system that runs {algorithm!r} covers the region of interest'
    return 'no vision system covers the region of interest'


def busy_everywhere(count: int, algorithm: str, max_pending: int, retry_after: float) -> Busy:
    """The refusal of a request whose ``count`` vision systems all have ``max_pending`` forwards
    pending."""
    return Busy(
        f'busy: all {count} vision systems that cover the region and run {algorithm!r} have '
        f'{max_pending} forwards pending; try again later',
        retry_after,
    )


def watch_answer(change: str, request_id: str, serving: int) -> str:
    """The answer to a watch call: what ``change`` the call made, how many vision systems serve it.

    >>> watch_answer('started', 'crate', 1)
    "watch 'crate' started; 1 vision system serves it"
    >>> watch_answer(NOT_STANDING, 'crate', 0)
    "no watch 'crate' stands: nothing to cancel"
    """
    if change == CANCELLED:
        return f'watch {request_id!r} cancelled'
    if change == NOT_STANDING:
        return f'no watch {request_id!r} stands: nothing to cancel'
    served = '1 vision system serves' if serving == 1 else f'{serving} vision systems serve'
    return f'watch {request_id!r} {change}; {served} it'


class SharedReplies(Generic[K, V]):
    """Replies made once per key and shared, at most ``max_kept`` (beyond them: made each time).

    A reply is only ever serialised, and a new one costs more than the check that chose it.

    >>> replies = SharedReplies(max_kept=1)
    >>> replies.get((1, 0), list) is replies.get((1, 0), list)
    True
    >>> replies.get((2, 0), list) is replies.get((2, 0), list)  # no room: made each time
    False
    """

    def __init__(self, max_kept: int = MAX_REPLIES_KEPT):
        self.max_kept = int(max_kept)
        self._lock = threading.Lock()  # guards _kept's growth (reads need no lock)
        self._kept: dict[K, V] = {}

    def __len__(self) -> int:
        return len(self._kept)

    def get(self, key: K, make: Callable[[], V]) -> V:
        """The reply kept for ``key``, else ``make()`` (kept while there is room)."""
        reply = self._kept.get(key)
        if reply is None:
            reply = make()
            with self._lock:
                if len(self._kept) < self.max_kept:
                    reply = self._kept.setdefault(key, reply)
        return reply
