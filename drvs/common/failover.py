"""Several DRVS servers in order (replicas on one registry database): which one to ask now.

A client asks the server in use; on ``UNAVAILABLE`` or no answer within its deadline it moves
to the next in the list (after the last, the first again); other refusals (``BUSY``,
``RATE_LIMITED``) are retried at the same server after their ``retry_after``. No ROS here.
Replicas: docs/registry.md.

>>> servers = ServerList(['/drvs/detect_object_boundary', '/drvs_b/detect_object_boundary'])
>>> servers.current
'/drvs/detect_object_boundary'
>>> servers.failed()
'/drvs_b/detect_object_boundary'
>>> servers.failed(), servers.moves
('/drvs/detect_object_boundary', 2)
"""

from __future__ import annotations

from collections.abc import Sequence

from drvs.common.status import UNAVAILABLE

__all__ = ['ServerList', 'moves_on']


def moves_on(status: int | None) -> bool:
    """Whether an answer with ``status`` (None: no answer) sends a client to the next server."""
    return status is None or status == UNAVAILABLE


class ServerList:
    """The servers a client may ask, in order, and the one in use.

    :raises ValueError: an empty list, or a name twice.
    """

    def __init__(self, servers: Sequence[str]):
        names = list(servers)
        if not names:
            raise ValueError('servers: empty; name at least one DRVS server')
        repeated = sorted({name for name in names if names.count(name) > 1})
        if repeated:
            raise ValueError(f'servers: {", ".join(repeated)} named more than once')
        self.servers = names
        self._index = 0
        self.moves = 0  # times a failure moved to the next server

    @property
    def current(self) -> str:
        return self.servers[self._index]

    def failed(self) -> str:
        """The server in use gave ``UNAVAILABLE`` or no answer: the next one (now in use)."""
        self._index = (self._index + 1) % len(self.servers)
        self.moves += 1
        return self.current
