"""How long a client waits before retrying: the server's hint, backoff and jitter.

A DRVS server refuses temporarily (BUSY, RATE_LIMITED, UNAVAILABLE) with a
``retry_after`` hint in seconds; a call may also just fail. A client retries
no earlier than the hint, backs off exponentially (``base * 2**attempt``,
capped at ``cap``) when it keeps failing, and multiplies by a random factor
in ``[1, 1 + jitter]`` so that clients refused together do not come back
together. Jitter only ever lengthens the wait, so the hint is always honoured.

No ROS here; the random source is injectable so tests are deterministic.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable

__all__ = ['retry_delay']

_MAX_EXPONENT = 1000  # 2.0 ** 1000 is still a finite float; beyond it ** raises OverflowError


def retry_delay(
    retry_after: float,
    attempt: int,
    *,
    base: float = 0.1,
    cap: float = 5.0,
    jitter: float = 0.5,
    rng: Callable[[], float] = random.random,
) -> float:
    """Seconds to wait before retry number ``attempt`` (0 for the first retry).

    ``max(retry_after, min(cap, base * 2**attempt)) * (1 + jitter * rng())``:
    never earlier than ``retry_after`` (a negative or non-finite hint counts
    as 0) and, for ``rng`` in [0, 1], at most ``max(retry_after, cap) * (1 + jitter)``.

    >>> retry_delay(0.0, 0, rng=lambda: 0.0)
    0.1
    >>> retry_delay(0.0, 3, rng=lambda: 0.0)
    0.8
    >>> retry_delay(2.0, 0, rng=lambda: 1.0)  # the server's hint, plus at most 50 %
    3.0
    >>> retry_delay(0.0, 10**9, rng=lambda: 1.0)  # capped, however many attempts
    7.5

    :raises ValueError: ``attempt``, ``base``, ``cap`` or ``jitter`` is negative.
    """
    if attempt < 0:
        raise ValueError(f'attempt: must not be negative, got {attempt}')
    if not base >= 0:
        raise ValueError(f'base: must not be negative, got {base}')
    if not cap >= 0:
        raise ValueError(f'cap: must not be negative, got {cap}')
    if not jitter >= 0:
        raise ValueError(f'jitter: must not be negative, got {jitter}')
    if not (math.isfinite(retry_after) and retry_after > 0):
        retry_after = 0.0
    backoff = min(cap, base * 2.0 ** min(attempt, _MAX_EXPONENT))  # base * 2**1000 may be inf: fine
    return max(retry_after, backoff) * (1 + jitter * rng())
