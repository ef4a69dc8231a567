"""Several DRVS servers in order (replicas on one registry database): which one to ask now.

A client asks the server in use; on ``UNAVAILABLE`` or no answer within its deadline it moves
to the next in the list (after the last, the first again); other refusals (``BUSY``,
``RATE_LIMITED``) are retried at the same server after their ``retry_after``. The first server is
the preferred one: ``return_after`` seconds after leaving it a client asks it again, and stays if it
answers; if it does not, the client goes back quietly and waits twice as long (up to
``RETURN_AFTER_MAX``) before the next try. The nodes' ``~servers`` names the servers by namespace
(:func:`namespaces`, :func:`service_names`). No ROS here.
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

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from drvs.common.settings import POSITIVE, ParamError, param
from drvs.common.status import UNAVAILABLE
from drvs.common.validation import ValidationError, global_ros_name

__all__ = [
    'RETURN_AFTER',
    'RETURN_AFTER_MAX',
    'Heard',
    'Move',
    'ServerList',
    'moves_on',
    'namespace_of',
    'namespaces',
    'server_return_param',
    'service_names',
]


RETURN_AFTER = 30.0
"""Seconds on another server before a client asks its first server again (``~server_return``)."""

RETURN_AFTER_MAX = 300.0
"""The longest wait between two tries of a first server that still does not answer."""


def server_return_param():
    """The ``~server_return`` parameter of the nodes that take ``~servers`` (a settings field)."""
    return param(
        RETURN_AFTER,
        'with several `~servers`: how long after leaving the first it asks the first again (it stays '
        'there if it answers; if not, it goes back and waits twice as long, up to 300 s)',
        unit='s',
        check=POSITIVE,
    )


def moves_on(status: int | None) -> bool:
    """Whether an answer with ``status`` (None: no answer) sends a client to the next server."""
    return status is None or status == UNAVAILABLE


def namespaces(text: str) -> list[str]:
    """The server namespaces of a ``~servers`` parameter: global ROS names separated by commas (a YAML
    list is given joined so), in order.

    >>> namespaces('/drvs, /drvs_b')
    ['/drvs', '/drvs_b']
    >>> namespaces('')
    Traceback (most recent call last):
    drvs.common.settings.ParamError: ~servers: empty; name at least one DRVS server namespace, e.g. [/drvs]

    :raises ParamError: naming ``~servers``: empty, a name that is not a global ROS name, or one twice.
    """
    names = [name.strip() for name in text.split(',')]
    if names == ['']:
        raise ParamError('servers', 'empty; name at least one DRVS server namespace, e.g. [/drvs]')
    for name in names:
        if not name:
            raise ParamError('servers', f'an empty name in {text!r}; expected namespaces such as /drvs')
        try:
            global_ros_name('servers', name)
        except ValidationError as error:
            problem = str(error).removeprefix('servers: ')
            raise ParamError('servers', f'{problem}; expected namespaces such as /drvs') from None
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise ParamError('servers', f'{", ".join(repeated)} named more than once')
    return names


def namespace_of(service: str) -> str:
    """The namespace of a server's service: where ``~servers`` defaults from.

    >>> namespace_of('/drvs/register_vision_service'), namespace_of('/register_vision_service')
    ('/drvs', '/')
    """
    return service.rsplit('/', 1)[0] or '/'


def service_names(servers: Sequence[str], service: str) -> list[str]:
    """The service of each server namespace: ``service``'s base name in it.

    >>> service_names(['/drvs', '/drvs_b', '/'], '/drvs/watch_object_boundary')
    ['/drvs/watch_object_boundary', '/drvs_b/watch_object_boundary', '/watch_object_boundary']
    """
    base = service.rsplit('/', 1)[-1]
    return [f'{namespace.rstrip("/")}/{base}' for namespace in servers]


@dataclass(frozen=True)
class Move:
    """A client moved to ``server`` (now in use); ``line``: what to log of it ('' for nothing)."""

    server: str
    line: str


@dataclass(frozen=True)
class Heard:
    """What a client makes of a call's end (:meth:`ServerList.heard`): a ``line`` to log ('' for
    nothing; at warning level when ``warning``), and whether it ``moved`` to another server."""

    line: str = ''
    warning: bool = False
    moved: bool = False


class ServerList:
    """The servers a client may ask, in order, and the one in use.

    Not thread-safe: one thread asks, or the caller holds a lock. The lines to log: each move
    once while some server answered since the last full round of failures; then one line
    when a whole round failed, and silence until a server answers again (one line then).

    :raises ValueError: an empty list, or a name twice.
    """

    def __init__(
        self,
        servers: Sequence[str],
        clock: Callable[[], float] = time.monotonic,
        return_after: float = RETURN_AFTER,
    ):
        names = list(servers)
        if not names:
            raise ValueError('servers: empty; name at least one DRVS server')
        repeated = sorted({name for name in names if names.count(name) > 1})
        if repeated:
            raise ValueError(f'servers: {", ".join(repeated)} named more than once')
        if not return_after > 0:
            raise ValueError(f'server_return: must be positive (seconds), got {return_after}')
        self.servers = names
        self._index = 0
        self.moves = 0  # times a failure moved to the next server
        self.returns = 0  # times the client went back to its first server and it answered
        self._failures = 0  # failures in a row since a server last answered
        self._clock = clock
        self.return_after = float(return_after)
        self._wait = self.return_after  # before the next try of the first server
        self._left_first: float | None = None  # when the client left the first server (None: on it)
        self._trying_first: int | None = None  # while trying the first again: the index it came from

    @property
    def current(self) -> str:
        """The server in use."""
        return self.servers[self._index]

    def to_ask(self) -> str:
        """The server to ask now: the one in use, or the first once it is time to try it again."""
        if (
            self._index != 0
            and self._left_first is not None
            and self._trying_first is None
            and self._clock() - self._left_first >= self._wait
        ):
            self._trying_first, self._index = self._index, 0
        return self.servers[self._index]

    def failed(self) -> str:
        """The server in use gave ``UNAVAILABLE`` or no answer: the next one (now in use), or, when it
        was the first tried again, the one the client came from (and a longer wait before the next try)."""
        self.moves += 1
        if self._trying_first is not None:
            back, self._trying_first = self._trying_first, None
            self._wait = min(2 * self._wait, max(RETURN_AFTER_MAX, self.return_after))
            self._move_to(back)
        else:
            self._move_to((self._index + 1) % len(self.servers))
            self._failures += 1
        return self.servers[self._index]

    def _move_to(self, index: int) -> None:
        if index == 0:
            self._left_first = None
        elif self._index == 0:
            self._left_first = self._clock()
        self._index = index

    def fail(self, server: str, why: str) -> Move | None:
        """``server`` gave ``UNAVAILABLE`` or no answer (``why`` says how): the move to the next
        one, or None when there is no other server or ``server`` is no longer the one in use
        (a call to it that was still out)."""
        if len(self.servers) == 1 or server != self.current:
            return None
        if self._trying_first is not None:  # the first still does not serve: back, quietly
            return Move(self.failed(), '')
        quiet = self._failures >= len(self.servers)
        new = self.failed()
        if quiet:
            return Move(new, '')
        if self._failures == len(self.servers):
            return Move(
                new,
                f'no DRVS server answers ({", ".join(self.servers)}; {server}: {why}); '
                f'still trying them in turn, now {new}',
            )
        return Move(new, f'DRVS server {server} did not serve ({why}); asking {new} from now on')

    def answered(self, server: str) -> str:
        """``server`` answered (anything but ``UNAVAILABLE``): what to log ('' unless it ends a
        whole round of failures)."""
        if server != self.current:
            return ''
        if self._trying_first is not None:
            self._trying_first, self._failures, self._wait = None, 0, self.return_after
            self._left_first = None
            self.returns += 1
            return f'DRVS server {server} answers again; asking it from now on'
        quiet, self._failures = self._failures >= len(self.servers), 0
        return f'DRVS server {server} answers again' if quiet and len(self.servers) > 1 else ''

    def heard(self, server: str, status: int | None, why: str) -> Heard:
        """A call to ``server`` ended: with no answer (``status`` None, ``why`` says how) or with an
        answer of ``status`` (``why``: its message). ``UNAVAILABLE`` or no answer moves on."""
        if moves_on(status):
            move = self.fail(server, why if status is None else f'UNAVAILABLE: {why}')
            return Heard() if move is None else Heard(move.line, warning=True, moved=True)
        return Heard(self.answered(server))
