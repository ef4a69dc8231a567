"""What an HTTP client sends, checked: JSON bodies and query strings, each problem a
:class:`BadRequest` naming the field (``region.min_x: expected a number, got "a"``).

The checks of DRVS itself (the region, the algorithm string) are the server's own
(:mod:`drvs.common.validation`, :mod:`drvs.algorithms`), so most requests DRVS would refuse
are refused here without a call. The fields: docs/gateway.md.

>>> detect_body(json_body(
...     b'{"algorithm": "motion", "region": {"min_x": 0, "min_y": 0, "max_x": 2, "max_y": 1}}'
... ))
DetectBody(algorithm='motion', region=(0.0, 0.0, 2.0, 1.0), wait=2.0, fused=False)
>>> detect_body({'algorithm': 'motion', 'region': [0, 0, 1, 1]})
Traceback (most recent call last):
drvs.gateway.body.BadRequest: region: expected an object {"min_x", "min_y", "max_x", "max_y"}, got an array
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from drvs.algorithms import AlgorithmError, default_algorithms, parse_algorithm, split_algorithm
from drvs.common.validation import ValidationError, region_of_interest

__all__ = [
    'BadRequest',
    'DetectBody',
    'WatchBody',
    'detect_body',
    'json_body',
    'region_query',
    'watch_body',
]

REGION_FIELDS = ('min_x', 'min_y', 'max_x', 'max_y')
DEFAULT_WAIT = 2.0
"""Seconds ``POST /v1/detect`` collects callbacks when the body gives no ``wait``."""
DEFAULT_PERIOD = 1.0
"""Seconds between a watch's evaluations when the body gives no ``period``."""
MAX_PERIOD = 3600.0


class BadRequest(ValueError):
    """A request the gateway answers ``400``: ``field`` (dotted, ``region.min_x``; ``body`` for the
    whole body) and what is wrong with it."""

    def __init__(self, field: str, problem: str):
        super().__init__(f'{field}: {problem}')
        self.field = field
        self.problem = problem


@dataclass(frozen=True)
class DetectBody:
    """``POST /v1/detect``: one question, the callbacks collected for ``wait`` seconds."""

    algorithm: str
    region: tuple[float, float, float, float]
    wait: float = DEFAULT_WAIT
    fused: bool = False


@dataclass(frozen=True)
class WatchBody:
    """``POST /v1/watches``: a standing question, every ``period`` seconds."""

    algorithm: str
    region: tuple[float, float, float, float]
    period: float = DEFAULT_PERIOD
    changes_only: bool = False
    fused: bool = False


def _kind(value: Any) -> str:
    if value is None:
        return 'null'
    if isinstance(value, bool):
        return 'a boolean'
    if isinstance(value, int | float):
        return 'a number'
    if isinstance(value, str):
        return 'a string'
    if isinstance(value, list):
        return 'an array'
    return 'an object'


def _refuse_constant(name: str) -> float:
    raise ValueError(f'{name} is not JSON')


def json_body(raw: bytes) -> dict:
    """The JSON object of a request body.

    :raises BadRequest: ``body``: empty, not UTF-8, not JSON (with where), NaN or Infinity,
        nested too deeply, or not an object.
    """
    if not raw.strip():
        raise BadRequest('body', 'empty; expected a JSON object')
    try:
        value = json.loads(raw.decode('utf-8'), parse_constant=_refuse_constant)
    except UnicodeDecodeError as error:
        raise BadRequest('body', f'not UTF-8 (byte {error.start})') from None
    except json.JSONDecodeError as error:
        raise BadRequest(
            'body', f'not JSON: {error.msg} at line {error.lineno} column {error.colno}'
        ) from None
    except ValueError as error:  # NaN, Infinity
        raise BadRequest('body', str(error)) from None
    except RecursionError:
        raise BadRequest('body', 'nested too deeply') from None
    if not isinstance(value, dict):
        raise BadRequest('body', f'expected a JSON object, got {_kind(value)}')
    return value


def _number(field: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise BadRequest(field, f'expected a number, got {_kind(value)}')
    number = float(value)
    if not math.isfinite(number):
        raise BadRequest(field, f'expected a finite number, got {value}')
    return number


def _boolean(field: str, value: Any) -> bool:
    if not isinstance(value, bool):
        raise BadRequest(field, f'expected true or false, got {_kind(value)}')
    return value


def _unknown(body: Mapping[str, Any], known: tuple[str, ...], where: str = '') -> None:
    for field in body:
        if field not in known:
            raise BadRequest(f'{where}{field}', f'unknown field; expected {", ".join(known)}')


def region(value: Any, field: str = 'region') -> tuple[float, float, float, float]:
    """A region object ``{"min_x", "min_y", "max_x", "max_y"}`` in metres in ``map``, checked as the
    server checks a region of interest."""
    if not isinstance(value, dict):
        raise BadRequest(
            field, f'expected an object {{"min_x", "min_y", "max_x", "max_y"}}, got {_kind(value)}'
        )
    _unknown(value, REGION_FIELDS, f'{field}.')
    for name in REGION_FIELDS:
        if name not in value:
            raise BadRequest(f'{field}.{name}', 'missing')
    numbers = [_number(f'{field}.{name}', value[name]) for name in REGION_FIELDS]
    try:
        return region_of_interest(numbers)
    except ValidationError as error:
        raise BadRequest(field, str(error).removeprefix('region_of_interest: ')) from None


def algorithm(value: Any) -> str:
    """An algorithm string ``NAME[:PARAMS]``: parsed in full when NAME is one this installation has
    (as the server does), its syntax only otherwise (a plugin of the vision systems)."""
    if not isinstance(value, str):
        raise BadRequest('algorithm', f'expected a string NAME:PARAMS, got {_kind(value)}')
    try:
        name, _ = split_algorithm(value)
        if name in default_algorithms():
            parse_algorithm(value)
    except AlgorithmError as error:
        raise BadRequest('algorithm', str(error).removeprefix('algorithm: ')) from None
    return value


def _common(body: Mapping[str, Any], known: tuple[str, ...]) -> dict[str, Any]:
    _unknown(body, known)
    for name in ('algorithm', 'region'):
        if name not in body:
            raise BadRequest(name, 'missing')
    fields: dict[str, Any] = {'algorithm': algorithm(body['algorithm']), 'region': region(body['region'])}
    if 'fused' in body:
        fields['fused'] = _boolean('fused', body['fused'])
    return fields


def detect_body(body: Mapping[str, Any], max_wait: float = 30.0) -> DetectBody:
    """``POST /v1/detect``'s body: ``algorithm``, ``region``, optional ``wait`` (0 to ``max_wait``
    seconds) and ``fused``."""
    fields = _common(body, ('algorithm', 'region', 'wait', 'fused'))
    if 'wait' in body:
        wait = _number('wait', body['wait'])
        if not 0 <= wait <= max_wait:
            raise BadRequest('wait', f'{wait:g} s; expected 0 to {max_wait:g} s')
        fields['wait'] = wait
    return DetectBody(**fields)


def watch_body(body: Mapping[str, Any]) -> WatchBody:
    """``POST /v1/watches``'s body: ``algorithm``, ``region``, optional ``period`` (seconds, more than
    0), ``changes_only`` and ``fused``."""
    fields = _common(body, ('algorithm', 'region', 'period', 'changes_only', 'fused'))
    if 'period' in body:
        period = _number('period', body['period'])
        if not 0 < period <= MAX_PERIOD:
            raise BadRequest('period', f'{period:g} s; expected more than 0, at most {MAX_PERIOD:g} s')
        fields['period'] = period
    if 'changes_only' in body:
        fields['changes_only'] = _boolean('changes_only', body['changes_only'])
    return WatchBody(**fields)


def region_query(query: Mapping[str, str]) -> tuple[float, float, float, float]:
    """``?min_x=..&min_y=..&max_x=..&max_y=..`` as a checked region."""
    values: dict[str, Any] = {}
    for name, text in query.items():
        if name in REGION_FIELDS:
            try:
                values[name] = float(text)
            except ValueError:
                raise BadRequest(name, f'expected a number, got {text!r}') from None
        else:
            values[name] = text
    try:
        return region(values, 'query')
    except BadRequest as error:
        raise BadRequest(error.field.removeprefix('query.'), error.problem) from None
