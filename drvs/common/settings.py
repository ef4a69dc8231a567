"""Node settings declared next to their fields, and checked in one place.

A node's settings are a frozen dataclass, one field per private ``~parameter``, each
declared with :func:`param` (default, meaning, unit, range); :func:`check` enforces the
ranges, every problem at once. The node pages' parameter tables are generated from these
declarations (:mod:`drvs.ros.param_docs`); the rules: docs/design.md ("Parameters").

>>> from dataclasses import dataclass
>>> @dataclass(frozen=True)
... class Example(Settings):
...     lease: float = param(10.0, 'a registration expires unless renewed within this time', unit='s',
...                          check=POSITIVE)
...     workers: int = param(8, 'forwarding threads', check=at_least(1))
>>> Example(workers=2)
Example(lease=10.0, workers=2)
>>> Example(lease=-1)
Traceback (most recent call last):
drvs.common.settings.ParamError: ~lease: must be positive, got -1.0
>>> Example(lease=0, workers=0)
Traceback (most recent call last):
drvs.common.settings.ParamError: ~lease: must be positive, got 0.0
~workers: must be at least 1, got 0
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable
from typing import Any

__all__ = [
    'NON_NEGATIVE',
    'POSITIVE',
    'ParamError',
    'REQUIRED',
    'Range',
    'Settings',
    'at_least',
    'between',
    'check',
    'checked',
    'one_of',
    'param',
    'typed',
]

REQUIRED = dataclasses.MISSING
"""The default of a parameter that has none: it must be given."""


class ParamError(ValueError):
    """Parameters that cannot be used: one ``~name: problem`` line per parameter.

    :param name: the parameter, without ``~``.
    :param problem: what is wrong with it, e.g. ``must be positive, got -1.0``.
    """

    def __init__(self, name: str, problem: str):
        self.problems: tuple[tuple[str, str], ...] = ((name, problem),)
        super().__init__(f'~{name}: {problem}')

    @classmethod
    def of(cls, problems: Iterable[tuple[str, str]]) -> ParamError:
        """One error listing every ``(name, problem)``, in order."""
        problems = tuple(problems)
        error = cls(*problems[0])
        error.problems = problems
        error.args = ('\n'.join(f'~{name}: {problem}' for name, problem in problems),)
        return error

    @classmethod
    def combined(cls, errors: Iterable[ParamError]) -> ParamError:
        """One error listing the problems of every error in ``errors``."""
        return cls.of(problem for error in errors for problem in error.problems)

    @property
    def names(self) -> tuple[str, ...]:
        """The parameters named, in order."""
        return tuple(name for name, _ in self.problems)

    def annotated(self, note: Callable[[str], str]) -> ParamError:
        """The same error with ``note(name)`` appended to each problem (nothing for an empty note)."""
        return ParamError.of((name, problem + note(name)) for name, problem in self.problems)


@dataclasses.dataclass(frozen=True)
class Range:
    """One kind of range: whether a value is in it, its rule as an error says it, and as a table shows it."""

    holds: Callable[[Any], bool]
    rule: str
    short: str


POSITIVE = Range(lambda value: value > 0, 'must be positive', '> 0')
NON_NEGATIVE = Range(lambda value: value >= 0, 'must not be negative', '≥ 0')


def at_least(minimum: int) -> Range:
    """A count of at least ``minimum``."""
    return Range(lambda value: value >= minimum, f'must be at least {minimum}', f'≥ {minimum}')


def between(low: int, high: int) -> Range:
    """From ``low`` to ``high``, both included."""
    return Range(lambda value: low <= value <= high, f'must be {low} to {high}', f'{low} to {high}')


def one_of(*choices: str) -> Range:
    """One of the strings ``choices``."""
    return Range(
        lambda value: value in choices,
        f'must be one of {", ".join(choices)}',
        ' or '.join(f'`{choice}`' for choice in choices),
    )


def param(
    default: Any,
    meaning: str,
    *,
    unit: str = '',
    check: Range | None = None,
    default_text: str = '',
    separator: str = '',
) -> Any:
    """A settings field: ``default`` (or :data:`REQUIRED`) and what its node's docs page says of it.

    :param meaning: one line, what the parameter does.
    :param unit: of the value, e.g. ``s``, ``m``, ``px``.
    :param check: the range a value must be in (:func:`check` enforces it).
    :param default_text: the default as the table says it when it is resolved at run time
        (the dataclass default then stands for "not given").
    :param separator: a ``str`` parameter that may also be given as a list of strings,
        joined with this.
    """
    metadata = {
        'meaning': meaning,
        'unit': unit,
        'range': check,
        'default_text': default_text,
        'separator': separator,
    }
    return dataclasses.field(default=default, metadata=metadata)


_TYPES = {'float': float, 'int': int, 'bool': bool, 'str': str}
_WHAT = {float: 'a number', int: 'an integer', bool: 'true or false', str: 'a string'}


def annotation_type(annotation: Any) -> tuple[type, bool]:
    """(type, optional) of a field annotated float, int, bool, str, or one of them ``| None``."""
    if isinstance(annotation, str):  # postponed annotations
        return _TYPES[annotation.removesuffix(' | None')], annotation.endswith(' | None')
    args = getattr(annotation, '__args__', (annotation,))
    return next(a for a in args if a is not type(None)), type(None) in args


def typed(name: str, value: Any, annotation: Any) -> Any:
    """``value`` as the field's type (an int where a float is expected becomes one).

    :raises ParamError: ``~name: expected a number, got 'fast'``; a number must be finite.
    """
    expected, optional = annotation_type(annotation)
    if value is None and optional:
        return None
    if isinstance(value, bool) != (expected is bool):
        raise ParamError(name, f'expected {_WHAT[expected]}, got {value!r}')
    if expected is float and isinstance(value, int | float) and math.isfinite(value):
        return float(value)
    if expected is not float and isinstance(value, expected):
        return value
    raise ParamError(name, f'expected {_WHAT[expected]}, got {value!r}')


def checked(field: dataclasses.Field, value: Any) -> Any:
    """``value`` of the settings field ``field`` as its type (:func:`typed`), checked against its range.

    :raises ParamError: ``~name: <rule>, got <value>``, or as :func:`typed`.
    """
    value = typed(field.name, value, field.type)
    declared = field.metadata.get('range')
    if declared is not None and value is not None and not declared.holds(value):
        raise ParamError(field.name, f'{declared.rule}, got {value!r}')
    return value


def check(settings: Any) -> None:
    """Check every field of the dataclass instance ``settings``: its type, then its declared range.

    Numbers given as ints where floats are declared are stored as floats.

    :raises ParamError: ``~name: <rule>, got <value>``, one line for each field of the wrong
        type or out of its range.
    """
    errors = []
    for field in dataclasses.fields(settings):
        try:
            value = checked(field, getattr(settings, field.name))
        except ParamError as error:
            errors.append(error)
            continue
        object.__setattr__(settings, field.name, value)  # frozen: only an int made a float
    if errors:
        raise ParamError.combined(errors)


class Settings:
    """Base of a settings dataclass: building one checks it (:func:`check`).

    A subclass with rules across fields extends ``__post_init__``: ``super().__post_init__()``
    first, then its own checks, raising ``ParamError(name, 'must ..., got ...')``.
    """

    def __post_init__(self) -> None:
        check(self)
