"""DRVS's answers as HTTP answers: every refusal a status code, a JSON body naming the problem,
and ``Retry-After`` where waiting helps. The table: docs/gateway.md ("Errors").

>>> answer = refusal(RATE_LIMITED, 'rate limited: too many requests', 0.2)
>>> answer.status, answer.headers['Retry-After'], answer.body['error']
(429, '1', 'RATE_LIMITED')
>>> refusal(INVALID, 'region_of_interest: min_x 2 is greater than max_x 1', 0).body['field']
'region'
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from drvs.common.status import BUSY, INVALID, RATE_LIMITED, UNAVAILABLE, UNSUPPORTED, name

__all__ = [
    'HttpAnswer',
    'bad_request',
    'error',
    'forbidden',
    'no_server',
    'refusal',
    'retry_after_header',
    'unauthorized',
]

DRVS_FIELDS = {'region_of_interest': 'region', 'algorithm': 'algorithm', 'period': 'period'}
"""A field DRVS names in an ``INVALID`` message -> the field of the gateway's body."""
_FIELD = re.compile(r'^([a-z_]+):')


@dataclass(frozen=True)
class HttpAnswer:
    """An HTTP status, a JSON body and extra headers."""

    status: int
    body: dict[str, Any]
    headers: Mapping[str, str] = field(default_factory=dict)


def retry_after_header(seconds: float) -> str:
    """``Retry-After`` in whole seconds (HTTP has no fractions), at least 1."""
    return str(max(1, math.ceil(seconds)))


def error(status: int, code: str, message: str, retry_after: float | None = None, **extra: Any) -> HttpAnswer:
    """``{"error": code, "message": message, ...extra}`` with ``status``; with ``retry_after``
    also ``"retry_after"`` (seconds) and the ``Retry-After`` header."""
    body: dict[str, Any] = {'error': code, 'message': message, **extra}
    headers = {}
    if retry_after is not None:
        body['retry_after'] = round(retry_after, 3)
        headers['Retry-After'] = retry_after_header(retry_after)
    return HttpAnswer(status, body, headers)


def bad_request(field_name: str, message: str) -> HttpAnswer:
    """``400``: the request's ``field_name`` is wrong (``message`` says how)."""
    return error(400, 'INVALID', message, field=field_name)


def refusal(
    status: int, message: str, retry_after: float, available_algorithms: Iterable[str] = ()
) -> HttpAnswer:
    """A DRVS refusal: ``INVALID`` 400 with the field, ``UNSUPPORTED`` 422 with the algorithms the
    registered vision systems run, ``RATE_LIMITED`` 429, ``BUSY`` and ``UNAVAILABLE`` 503 (with
    ``Retry-After``); a code the gateway does not know 502."""
    if status == INVALID:
        match = _FIELD.match(message)
        drvs_field = match.group(1) if match else ''
        return bad_request(DRVS_FIELDS.get(drvs_field, drvs_field or 'body'), message)
    if status == UNSUPPORTED:
        return error(422, 'UNSUPPORTED', message, available_algorithms=sorted(set(available_algorithms)))
    if status == RATE_LIMITED:
        return error(429, 'RATE_LIMITED', message, retry_after)
    if status in (BUSY, UNAVAILABLE):
        return error(503, name(status), message, retry_after)
    return error(502, name(status), f'DRVS answered a status the gateway does not know: {message}')


def no_server(message: str, retry_after: float) -> HttpAnswer:
    """``503``: no DRVS server answered within the gateway's ``~server_timeout``."""
    return error(503, 'NO_SERVER', message, retry_after)


def unauthorized(message: str) -> HttpAnswer:
    """``401``: no token, or one the gateway does not know."""
    answer = error(401, 'UNAUTHORIZED', message)
    return HttpAnswer(answer.status, answer.body, {'WWW-Authenticate': 'Bearer realm="drvs"'})


def forbidden(message: str) -> HttpAnswer:
    """``403``: a token used outside its rights."""
    return error(403, 'FORBIDDEN', message)
