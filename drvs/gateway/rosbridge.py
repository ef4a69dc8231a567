"""The rosbridge v2 protocol as DRVS speaks it, without ROS or sockets: parsing and checking a
client's frames, the ``status`` messages, the token rights of each operation, the table of
DRVS's calls to client-hosted services awaiting their ``service_response`` (each with a
deadline), a client's bounded send queue and a subscription's throttle. The endpoint that uses
them: :mod:`drvs.gateway.bridge`; the contract: docs/gateway.md ("rosbridge endpoint").

>>> parse('{"op": "call_service", "service": "/drvs/detect_object_boundary", "id": "c1"}').service
'/drvs/detect_object_boundary'
>>> try:
...     parse('{"op": "publish", "topic": "/x"}')
... except ProtocolError as error:
...     print(error.field)
op
"""

from __future__ import annotations

import itertools
import json
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

__all__ = [
    'LEVELS',
    'OPS',
    'Op',
    'PendingCall',
    'PendingCalls',
    'ProtocolError',
    'SendQueue',
    'Throttle',
    'bearer_from_protocols',
    'parse',
    'required_right',
    'status',
]

LEVELS = ('info', 'warning', 'error', 'none')
"""``status`` levels, least severe first; ``set_level`` X: only statuses at X or above are sent."""
DEFAULT_LEVEL = 'warning'
"""The status level of a new connection (rosbridge's is ``error``; DRVS also sends the warning that a
slow client lost messages)."""
BEARER = 'bearer.'
"""A WebSocket subprotocol offered as ``bearer.TOKEN`` carries the connection's token."""
SUBPROTOCOL = 'drvs'
"""The subprotocol the endpoint selects when a client offers it (browsers offer it beside the token)."""

_ID = (str, int)
_NUMBER = (int, float)
# op -> {field: (types, required)}; fields not named here are ignored, as rosbridge does.
_FIELDS: dict[str, dict[str, tuple[tuple[type, ...], bool]]] = {
    'auth': {'mac': ((str,), True)},
    'call_service': {
        'service': ((str,), True),
        'args': ((dict, list), False),
        'timeout': (_NUMBER, False),
        'compression': ((str,), False),
    },
    'service_response': {
        'service': ((str,), True),
        'id': (_ID, True),
        'result': ((bool,), False),
        'values': ((dict, str, type(None)), False),
    },
    'advertise_service': {'service': ((str,), True), 'type': ((str,), True)},
    'unadvertise_service': {'service': ((str,), True)},
    'subscribe': {
        'topic': ((str,), True),
        'type': ((str,), False),
        'throttle_rate': (_NUMBER, False),
        'queue_length': (_NUMBER, False),
        'compression': ((str,), False),
    },
    'unsubscribe': {'topic': ((str,), True)},
    'set_level': {'level': ((str,), True)},
}
OPS = tuple(_FIELDS)
"""The operations the endpoint serves; any other (``publish``, ``advertise``, actions, fragments) is
answered with an error ``status``."""
_TYPE_NAMES = {str: 'a string', int: 'an integer', float: 'a number', dict: 'an object', list: 'an array'}
_TYPE_NAMES.update({bool: 'true or false', type(None): 'null'})


class ProtocolError(ValueError):
    """A frame the endpoint cannot serve: ``field`` names what is wrong (``frame``, ``op``,
    ``service``, ...); ``id`` is the frame's ``id`` when it had one, for the ``status`` answer."""

    def __init__(self, field: str, message: str, id: str | int | None = None):
        super().__init__(f'{field}: {message}')
        self.field = field
        self.id = id


@dataclass(frozen=True)
class Op:
    """One checked frame: its ``op``, ``id`` (None when absent) and every field it carried."""

    op: str
    id: str | int | None
    fields: dict[str, Any]

    def __getattr__(self, name: str) -> Any:
        try:
            return self.fields[name]
        except KeyError:
            raise AttributeError(name) from None


def _kind(types: tuple[type, ...]) -> str:
    return ' or '.join(_TYPE_NAMES.get(kind, kind.__name__) for kind in types)


def _has_type(value: Any, types: tuple[type, ...]) -> bool:
    if isinstance(value, bool):
        return bool in types  # JSON true is no number
    if isinstance(value, float) and not math.isfinite(value):
        return False
    return isinstance(value, types)


def parse(text: str | bytes) -> Op:
    """A text frame -> its :class:`Op`.

    :raises ProtocolError: not JSON, not an object, no ``op``, an op not served here, a field
        missing or of the wrong type (named in the error).
    """
    try:
        message = json.loads(text, parse_constant=_no_constant)
    except (ValueError, RecursionError) as error:
        raise ProtocolError('frame', f'not JSON: {error}') from None
    if not isinstance(message, dict):
        raise ProtocolError('frame', f'expected a JSON object, got {type(message).__name__}')
    frame_id = message.get('id')
    if frame_id is not None and not _has_type(frame_id, _ID):
        raise ProtocolError('id', f'expected a string or an integer, got {json.dumps(frame_id)[:40]}')
    op = message.get('op')
    if not isinstance(op, str):
        raise ProtocolError('op', 'missing or not a string', frame_id)
    fields = _FIELDS.get(op)
    if fields is None:
        raise ProtocolError(
            'op', f'{op[:40]!r} is not supported here (supported: {", ".join(OPS)})', frame_id
        )
    for name, (types, required) in fields.items():
        if name not in message or (message[name] is None and type(None) not in types):
            if required:
                raise ProtocolError(name, f'missing (op {op} needs it)', frame_id)
            continue
        if not _has_type(message[name], types):
            raise ProtocolError(name, f'expected {_kind(types)}', frame_id)
    if op == 'set_level' and message['level'] not in LEVELS:
        raise ProtocolError('level', f'expected one of {", ".join(LEVELS)}', frame_id)
    if 'timeout' in message and op == 'call_service' and not message['timeout'] > 0:
        raise ProtocolError('timeout', 'must be positive seconds', frame_id)
    return Op(op, frame_id, message)


def _no_constant(name: str) -> Any:
    raise ValueError(f'{name} is not JSON')


def status(level: str, message: str, id: str | int | None = None) -> dict[str, Any]:
    """A ``status`` message (``id`` when it answers a frame that had one)."""
    answer: dict[str, Any] = {'op': 'status', 'level': level, 'msg': message}
    if id is not None:
        answer['id'] = id
    return answer


def shown(level: str, threshold: str) -> bool:
    """Whether a status of ``level`` is sent to a connection at ``threshold`` (``set_level``)."""
    return threshold != 'none' and LEVELS.index(level) >= LEVELS.index(threshold)


def required_right(op: Op, services: dict[str, str]) -> tuple[tuple[str, ...], str | None]:
    """The token operations that allow ``op`` (any one of them; () = none needed) and the algorithm
    to check them with.

    :param services: DRVS's services the endpoint serves -> the token operation each needs.
    """
    if op.op == 'call_service':
        args = op.fields.get('args')
        algorithm = args.get('algorithm') if isinstance(args, dict) else None
        return (services.get(op.service, 'detect'),), algorithm if isinstance(algorithm, str) else None
    if op.op == 'advertise_service':  # a callback service serves a request or a watch
        return ('detect', 'watch'), None
    if op.op == 'subscribe':
        return ('read',), None
    return (), None


def bearer_from_protocols(header: str | None) -> str | None:
    """The token of a ``Sec-WebSocket-Protocol`` header offering ``bearer.TOKEN``; None without one."""
    for offered in (header or '').split(','):
        offered = offered.strip()
        if offered.startswith(BEARER) and len(offered) > len(BEARER):
            return offered[len(BEARER) :]
    return None


T = TypeVar('T')


@dataclass
class PendingCall(Generic[T]):
    """A call DRVS made to a client-hosted service, awaiting the client's ``service_response``."""

    id: str
    service: str
    deadline: float
    waiter: T


class PendingCalls(Generic[T]):
    """The calls a connection's hosted services are serving, each with its deadline.

    :param clock: monotonic seconds.
    :param limit: calls waiting at once; one more is refused (:meth:`add` returns None).
    """

    def __init__(self, clock: Callable[[], float], limit: int):
        self.clock = clock
        self.limit = limit
        self._calls: dict[str, PendingCall[T]] = {}
        self._ids = itertools.count(1)

    def __len__(self) -> int:
        return len(self._calls)

    def add(self, service: str, timeout: float, waiter: T) -> PendingCall[T] | None:
        """A new call to ``service`` due within ``timeout`` seconds; None when :attr:`limit` wait already."""
        self.expire()
        if len(self._calls) >= self.limit:
            return None
        call = PendingCall(f'drvs:{service}:{next(self._ids)}', service, self.clock() + timeout, waiter)
        self._calls[call.id] = call
        return call

    def answer(self, call_id: str | int, service: str) -> PendingCall[T]:
        """The call a ``service_response`` answers, removed from the table.

        :raises ProtocolError: no such call waiting (never made, answered, or past its deadline),
            or a response naming another service.
        """
        call = self._calls.get(str(call_id))
        if call is None or call.deadline < self.clock():
            self._calls.pop(str(call_id), None)
            raise ProtocolError(
                'id', f'no call {str(call_id)[:80]!r} is waiting (answered or too late)', call_id
            )
        if call.service != service:
            raise ProtocolError('service', f'call {call.id!r} was made to {call.service!r}', call_id)
        return self._calls.pop(call.id)

    def drop(self, call_id: str) -> PendingCall[T] | None:
        """Forget a call (its caller stopped waiting)."""
        return self._calls.pop(call_id, None)

    def expire(self) -> list[PendingCall[T]]:
        """Remove and return the calls past their deadline."""
        now = self.clock()
        late = [call for call in self._calls.values() if call.deadline < now]
        for call in late:
            del self._calls[call.id]
        return late

    def clear(self) -> list[PendingCall[T]]:
        """Remove and return every call (the connection closed)."""
        calls = list(self._calls.values())
        self._calls.clear()
        return calls


class SendQueue:
    """A connection's outgoing frames: at most ``capacity``; when full the oldest is dropped, and
    the next :meth:`take` starts with a warning ``status`` saying how many were lost."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self._queue: deque[str] = deque()
        self.dropped = 0  # since the last take
        self.dropped_total = 0

    def __len__(self) -> int:
        return len(self._queue)

    def put(self, frame: str) -> None:
        if len(self._queue) >= self.capacity:
            self._queue.popleft()
            self.dropped += 1
            self.dropped_total += 1
        self._queue.append(frame)

    def take(self, level: str = DEFAULT_LEVEL) -> list[str]:
        """Every frame waiting, oldest first, after the warning if some were dropped (and ``level``
        lets warnings through)."""
        frames = []
        if self.dropped and shown('warning', level):
            note = f'{self.dropped} message(s) dropped: this client read too slowly'
            frames.append(json.dumps(status('warning', note)))
        self.dropped = 0
        frames.extend(self._queue)
        self._queue.clear()
        return frames


@dataclass
class Throttle:
    """A subscription's ``throttle_rate`` (ms between two messages; 0: every message)."""

    milliseconds: float = 0.0
    last: float = field(default=-math.inf)

    def due(self, now: float) -> bool:
        """Whether a message at ``now`` (seconds) goes out; it counts as sent if so."""
        if now - self.last < self.milliseconds / 1000.0:
            return False
        self.last = now
        return True
