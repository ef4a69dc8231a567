"""Why a DRVS call was or was not accepted: the status codes of every DRVS service response.

The constants of the ``.srv`` files, repeated for code that imports no ROS (a test checks
that both agree), with :class:`Refusal` and :func:`is_temporary`. What each code means and
what a client does: docs/interface.md ("Status codes").

>>> is_temporary(BUSY), is_temporary(INVALID)
(True, False)
>>> str(Refusal(RATE_LIMITED, 'rate limited: too many requests', 0.02))
'rate limited: too many requests'
"""

from __future__ import annotations

ACCEPTED, INVALID, BUSY, RATE_LIMITED, UNAVAILABLE, UNSUPPORTED = 0, 1, 2, 3, 4, 5

NAMES = {
    ACCEPTED: 'ACCEPTED',
    INVALID: 'INVALID',
    BUSY: 'BUSY',
    RATE_LIMITED: 'RATE_LIMITED',
    UNAVAILABLE: 'UNAVAILABLE',
    UNSUPPORTED: 'UNSUPPORTED',
}
TEMPORARY = frozenset({BUSY, RATE_LIMITED, UNAVAILABLE})


def is_temporary(status: int) -> bool:
    """Whether a refusal with ``status`` should be retried later."""
    return status in TEMPORARY


def name(status: int) -> str:
    """``'BUSY'`` for 2; unknown codes as ``'status 9'``."""
    return NAMES.get(status, f'status {status}')


class Refusal(Exception):
    """A call DRVS does not accept: a status code, a message for humans, and when to retry.

    :param status: one of the codes above except ``ACCEPTED``.
    :param message: what is wrong, naming the field or the condition.
    :param retry_after: seconds, for the temporary codes; 0 otherwise.
    """

    def __init__(self, status: int, message: str, retry_after: float = 0.0):
        super().__init__(message)
        self.status = status
        self.message = message
        self.retry_after = float(retry_after)
