"""ROS messages <-> JSON the way rosbridge converts them, without importing ROS: a message is any
object with ``__slots__`` and ``_slot_types`` (what genpy generates), its fields become JSON
members of the same names, ``time`` and ``duration`` become ``{"secs", "nsecs"}``, ``uint8[]`` and
``char[]`` a base64 string, numbers JSON cannot carry (NaN, infinity) ``null``. From JSON, a missing
field keeps its default, and an unknown field or a value of the wrong type or out of range is
refused naming its path (``objects[2].boundary.points[0].x``). The contract: docs/gateway.md
("rosbridge endpoint").
"""

from __future__ import annotations

import base64
import binascii
import math
from collections.abc import Callable
from typing import Any

__all__ = ['FieldError', 'from_json', 'to_json']

_INTS = {
    'int8': (-(2**7), 2**7 - 1),
    'uint8': (0, 2**8 - 1),
    'byte': (-(2**7), 2**7 - 1),
    'char': (0, 2**8 - 1),
    'int16': (-(2**15), 2**15 - 1),
    'uint16': (0, 2**16 - 1),
    'int32': (-(2**31), 2**31 - 1),
    'uint32': (0, 2**32 - 1),
    'int64': (-(2**63), 2**63 - 1),
    'uint64': (0, 2**64 - 1),
}
_FLOATS = ('float32', 'float64')
_TIMES = ('time', 'duration')
_BYTES = ('uint8', 'char')
MAX_ITEMS = 100_000
"""The longest array accepted from JSON."""

Resolve = Callable[[str], Any]
"""A message type name (``geometry_msgs/Point``) -> its class."""


class FieldError(ValueError):
    """A JSON value that does not fit the message: ``field`` is its path, the message says why."""

    def __init__(self, field: str, message: str):
        super().__init__(f'{field}: {message}')
        self.field = field


def _split(slot_type: str) -> tuple[str, int | None, bool]:
    """``float64[3]`` -> (``float64``, 3, True); ``string[]`` -> (``string``, None, True)."""
    base, bracket, rest = slot_type.partition('[')
    if not bracket:
        return slot_type, None, False
    size = rest.rstrip(']')
    return base, int(size) if size else None, True


def _number(value: float) -> float | None:
    return value if math.isfinite(value) else None


def to_json(message: Any) -> dict[str, Any]:
    """A message -> a JSON-ready dict (rosbridge's field names and rules)."""
    return {
        slot: _value_to_json(getattr(message, slot), slot_type)
        for slot, slot_type in zip(message.__slots__, message._slot_types, strict=True)
    }


def _value_to_json(value: Any, slot_type: str) -> Any:
    base, _, is_array = _split(slot_type)
    if is_array:
        if base in _BYTES and isinstance(value, bytes | bytearray):
            return base64.b64encode(bytes(value)).decode('ascii')
        return [_value_to_json(item, base) for item in value]
    if base in _TIMES:
        return {'secs': value.secs, 'nsecs': value.nsecs}
    if base in _FLOATS:
        return _number(float(value))
    if base in _INTS or base in ('bool', 'string'):
        return value
    return to_json(value)


def from_json(data: Any, message_class: Any, resolve: Resolve, field: str = '') -> Any:
    """A JSON object -> a new ``message_class`` with those fields (missing ones at their defaults).

    :param resolve: the class of a nested message type, for arrays of messages.
    :raises FieldError: an unknown field, or a value of the wrong type or out of range.
    """
    message = message_class()
    _fill(message, data, resolve, field)
    return message


def _fill(message: Any, data: Any, resolve: Resolve, field: str) -> None:
    if not isinstance(data, dict):
        raise FieldError(field or 'args', f'expected an object with the fields of {message._type}')
    slots = dict(zip(message.__slots__, message._slot_types, strict=True))
    for name, value in data.items():
        path = f'{field}.{name}' if field else str(name)
        if name not in slots:
            raise FieldError(path, f'{message._type} has no such field (it has {", ".join(slots) or "none"})')
        current = getattr(message, name)
        setattr(message, name, _value(value, slots[name], current, resolve, path))


def _value(value: Any, slot_type: str, current: Any, resolve: Resolve, path: str) -> Any:
    base, size, is_array = _split(slot_type)
    if is_array:
        if base in _BYTES and isinstance(value, str):
            try:
                return base64.b64decode(value, validate=True)
            except (binascii.Error, ValueError):
                raise FieldError(path, 'expected base64 text or an array of integers') from None
        if not isinstance(value, list):
            raise FieldError(path, f'expected an array of {base}')
        if len(value) > MAX_ITEMS or (size is not None and len(value) != size):
            raise FieldError(path, f'expected {size if size is not None else f"at most {MAX_ITEMS}"} items')
        items = [
            _value(item, base, _default_item(base, resolve), resolve, f'{path}[{i}]')
            for i, item in enumerate(value)
        ]
        return bytes(items) if base in _BYTES else items
    if base in _TIMES:
        if not isinstance(value, dict) or set(value) - {'secs', 'nsecs'}:
            raise FieldError(path, 'expected {"secs": integer, "nsecs": integer}')
        for part in ('secs', 'nsecs'):
            setattr(current, part, _value(value.get(part, 0), 'int32', None, resolve, f'{path}.{part}'))
        return current
    if base in _INTS:
        low, high = _INTS[base]
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            raise FieldError(path, f'expected an integer {low} to {high} ({base})')
        return value
    if base in _FLOATS:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise FieldError(path, f'expected a number ({base})')
        return float(value)
    if base == 'bool':
        if not isinstance(value, bool):
            raise FieldError(path, 'expected true or false')
        return value
    if base == 'string':
        if not isinstance(value, str):
            raise FieldError(path, 'expected a string')
        return value
    _fill(current, value, resolve, path)
    return current


def _default_item(base: str, resolve: Resolve) -> Any:
    """A fresh value for one item of an array of ``base`` (a message or a time; None otherwise)."""
    if base in _TIMES:
        return resolve(base)()
    if base in _INTS or base in _FLOATS or base in ('bool', 'string'):
        return None
    return resolve(base)()
