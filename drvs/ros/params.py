"""Read a node's private ``~parameters`` into its settings dataclass, one way for every node.

Every field of the dataclass is a parameter of the same name, declared with
:func:`drvs.settings.param`. A field without a default is required. Values are
checked against the field's type (an int is accepted where a float is expected;
``None`` defaults accept a number or nothing), so a typo on the command line is
refused with a message naming the parameter instead of failing later; building
the dataclass then checks the declared ranges (:func:`drvs.settings.check`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping

from drvs.settings import typed

_MISSING = object()


def _joined(field: dataclasses.Field, value):
    """A list given for a ``str`` field declared with a separator, joined; anything else unchanged."""
    separator = field.metadata.get('separator')
    if not separator or not isinstance(value, list):
        return value
    if not all(isinstance(item, str) for item in value):
        raise ValueError(f'~{field.name}: expected a string or a list of strings, got {value!r}')
    return separator.join(value)


def read_params(cls, defaults: Mapping[str, object] | None = None, get: Callable | None = None):
    """Build ``cls`` from the private parameters; ``defaults`` replaces field defaults known only at run time.

    :param get: ``get(name, default)``, :func:`rospy.get_param` unless given (tests pass a dict's).
    :raises ValueError: naming the parameter that is missing, of the wrong type or out of its range.
    """
    if get is None:
        import rospy

        get = rospy.get_param
    values = {}
    for field in dataclasses.fields(cls):
        value = get('~' + field.name, _MISSING)
        if value is not _MISSING:
            values[field.name] = typed(field.name, _joined(field, value), field.type)
            continue
        default = (defaults or {}).get(field.name, field.default)
        if default is dataclasses.MISSING:
            raise ValueError(f'~{field.name}: missing')
        values[field.name] = default
    return cls(**values)
