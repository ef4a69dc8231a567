"""Read a node's private ``~parameters`` into its settings dataclass, one way for every node.

Every field of the dataclass is a parameter of the same name. A field without a
default is required. Values are checked against the type of the field's default
(an int is accepted where a float is expected; ``None`` defaults accept a number
or nothing), so a typo on the command line is refused with a message naming
the parameter instead of failing later.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping

_MISSING = object()
_TYPES = {'float': float, 'int': int, 'bool': bool, 'str': str}
_WHAT = {float: 'a number', int: 'an integer', bool: 'true or false', str: 'a string'}


def _expected(annotation) -> tuple[type, bool]:
    """(type, optional) of a field annotated float, int, bool, str, or one of them ``| None``."""
    if isinstance(annotation, str):  # postponed annotations
        return _TYPES[annotation.removesuffix(' | None')], annotation.endswith(' | None')
    args = getattr(annotation, '__args__', (annotation,))
    return next(a for a in args if a is not type(None)), type(None) in args


def _checked(name: str, value, annotation):
    """``value`` as the field's type, or ValueError naming the parameter."""
    expected, optional = _expected(annotation)
    if value is None and optional:
        return None
    if isinstance(value, bool) != (expected is bool):
        raise ValueError(f'~{name}: expected {_WHAT[expected]}, got {value!r}')
    if expected is float and isinstance(value, int | float):
        return float(value)
    if isinstance(value, expected):
        return value
    raise ValueError(f'~{name}: expected {_WHAT[expected]}, got {value!r}')


def read_params(cls, defaults: Mapping[str, object] | None = None, get: Callable | None = None):
    """Build ``cls`` from the private parameters; ``defaults`` replaces field defaults known only at run time.

    :raises ValueError: naming the parameter that is missing or of the wrong type; the
        dataclass's own ``__post_init__`` checks ranges.
    """
    if get is None:
        import rospy

        get = rospy.get_param
    values = {}
    for field in dataclasses.fields(cls):
        value = get('~' + field.name, _MISSING)
        if value is not _MISSING:
            values[field.name] = _checked(field.name, value, field.type)
            continue
        default = (defaults or {}).get(field.name, field.default)
        if default is dataclasses.MISSING:
            raise ValueError(f'~{field.name}: missing')
        values[field.name] = default
    return cls(**values)
