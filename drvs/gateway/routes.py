"""The gateway's routes, in one table, and the OpenAPI 3 document built from it.

The application registers exactly these routes (:mod:`drvs.gateway.app`) and ``GET
/v1/openapi.json`` serves :func:`openapi` of the same table, so the document cannot miss a route
or name one that is not served (a test checks both). The prose: docs/gateway.md.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

__all__ = ['ROUTES', 'Route', 'openapi']

VERSION = '1.0.0'


@dataclass(frozen=True)
class Route:
    """One route: ``method`` and ``path`` (aiohttp's ``{name}`` placeholders, as OpenAPI's), the
    handler's ``name`` (the OpenAPI operationId), the token operation it needs (None: public), a
    summary, its JSON request schema (a name in :data:`SCHEMAS`), query parameters, and its answers
    (status -> description, schema name or None). A ``ticket`` route takes its rights from a
    ``?ticket=`` of ``POST /v1/tickets`` instead of a header (a browser's EventSource sends none)."""

    method: str
    path: str
    name: str
    op: str | None
    summary: str
    request: str | None = None
    query: tuple[str, ...] = ()
    answers: dict[int, tuple[str, str | None]] = field(default_factory=dict)
    content_type: str = 'application/json'
    ticket: bool = False


_ERRORS: dict[int, tuple[str, str | None]] = {
    400: ('a field is wrong: `field` names it', 'Error'),
    401: ('no token, or an unknown one', 'Error'),
    403: ('the token may not do this', 'Error'),
    429: ('too many requests or watches for this token (`Retry-After`)', 'Error'),
    503: ('DRVS is busy, unavailable or not answering (`Retry-After`)', 'Error'),
}


def _answers(ok: int, what: str, schema: str | None, *errors: int) -> dict[int, tuple[str, str | None]]:
    return {ok: (what, schema), **{code: _ERRORS[code] for code in errors}}


ROUTES: tuple[Route, ...] = (
    Route(
        'POST',
        '/v1/detect',
        'detect',
        'detect',
        'Ask once; the answer holds every callback received within `wait` seconds',
        request='DetectRequest',
        answers={
            **_answers(200, 'accepted: the callbacks received', 'DetectAnswer', 400, 401, 403, 429, 503),
            413: ('the body is larger than `~max_body`', 'Error'),
            422: ('no vision system runs the algorithm: `available_algorithms`', 'Error'),
        },
    ),
    Route(
        'POST',
        '/v1/watches',
        'open_watch',
        'watch',
        'Open a watch: its callbacks every period, as Server-Sent Events at `events`',
        request='WatchRequest',
        answers={
            **_answers(201, 'the watch is open', 'Watch', 400, 401, 403, 429, 503),
            413: ('the body is larger than `~max_body`', 'Error'),
            422: ('no vision system runs the algorithm: `available_algorithms`', 'Error'),
        },
    ),
    Route(
        'GET',
        '/v1/watches/{id}/events',
        'watch_events',
        'watch',
        "The watch's events (`callback`, `status`, `end`), each with an `id:`; resume with `Last-Event-ID`",
        answers={
            **_answers(200, 'a text/event-stream', None, 400, 401, 403, 429),
            404: ('no such watch (or it ended)', 'Error'),
        },
        content_type='text/event-stream',
    ),
    Route(
        'DELETE',
        '/v1/watches/{id}',
        'close_watch',
        'watch',
        'End a watch: its listeners get `end`, the DRVS watch is withdrawn',
        answers={
            **_answers(204, 'ended', None, 401, 403),
            404: ('no such watch (or it ended)', 'Error'),
        },
    ),
    Route(
        'GET',
        '/v1/vision_systems',
        'vision_systems',
        'read',
        'The registry: every vision system, its field of view and algorithms',
        answers=_answers(200, 'the registry', 'VisionSystems', 401, 403, 503),
    ),
    Route(
        'GET',
        '/v1/coverage',
        'coverage',
        'read',
        'Which vision systems cover a region, and which algorithms there',
        query=('min_x', 'min_y', 'max_x', 'max_y'),
        answers=_answers(
            200, 'the vision systems that see part of the region', 'Coverage', 400, 401, 403, 503
        ),
    ),
    Route(
        'GET',
        '/v1/objects',
        'objects',
        'read',
        'The fused tracks (`/drvs/objects`): every object once, with ids and velocities',
        answers=_answers(200, 'the tracks', 'Objects', 401, 403),
    ),
    Route(
        'GET',
        '/v1/health',
        'health',
        'read',
        'The gateway, the DRVS server and the vision systems, from `/diagnostics`',
        answers=_answers(200, 'health', 'Health', 401, 403),
    ),
    Route(
        'GET',
        '/v1/openapi.json',
        'openapi',
        None,
        'This document',
        answers={200: ('the OpenAPI 3 document', None)},
    ),
    Route(
        'GET',
        '/',
        'page',
        None,
        'The live floor-plan page (it asks for a token)',
        answers={200: ('an HTML page', None)},
        content_type='text/html',
    ),
    Route(
        'GET',
        '/static/{name}',
        'static',
        None,
        "The page's scripts and styles",
        answers={200: ('a file', None), 404: ('no such file', 'Error')},
        content_type='text/javascript',
    ),
    Route(
        'POST',
        '/v1/tickets',
        'ticket',
        'read',
        'A ticket for `GET /v1/live`: good once, for 30 s (a browser cannot send a header there)',
        answers=_answers(201, 'the ticket', 'Ticket', 401, 403, 429),
    ),
    Route(
        'GET',
        '/v1/live',
        'live',
        'read',
        'The floor plan live: events `registry`, `objects`, `robot`, `path` (the whole state first)',
        answers={
            **_answers(200, 'a text/event-stream', None, 429),
            401: ('no ticket, or one used or expired', 'Error'),
        },
        content_type='text/event-stream',
        ticket=True,
    ),
)

_NUMBER = {'type': 'number'}
_POINTS = {'type': 'array', 'items': {'type': 'array', 'items': _NUMBER, 'minItems': 2, 'maxItems': 2}}
_REGION = {
    'type': 'object',
    'description': 'a rectangle on the floor, metres in `map`',
    'required': ['min_x', 'min_y', 'max_x', 'max_y'],
    'additionalProperties': False,
    'properties': {name: _NUMBER for name in ('min_x', 'min_y', 'max_x', 'max_y')},
}
_STRINGS = {'type': 'array', 'items': {'type': 'string'}}
_ALGORITHM = {'type': 'string', 'description': 'NAME:PARAMS, e.g. colour:0,0,150,80,80,255', 'maxLength': 256}
SCHEMAS: dict[str, dict[str, Any]] = {
    'Region': _REGION,
    'DetectRequest': {
        'type': 'object',
        'required': ['algorithm', 'region'],
        'additionalProperties': False,
        'properties': {
            'algorithm': _ALGORITHM,
            'region': {'$ref': '#/components/schemas/Region'},
            'wait': {
                'type': 'number',
                'minimum': 0,
                'default': 2,
                'description': 'seconds to collect callbacks',
            },
            'fused': {'type': 'boolean', 'default': False},
        },
    },
    'WatchRequest': {
        'type': 'object',
        'required': ['algorithm', 'region'],
        'additionalProperties': False,
        'properties': {
            'algorithm': _ALGORITHM,
            'region': {'$ref': '#/components/schemas/Region'},
            'period': {
                'type': 'number',
                'minimum': 0,
                'exclusiveMinimum': True,
                'default': 1,
                'description': 'seconds',
            },
            'changes_only': {'type': 'boolean', 'default': False},
            'fused': {'type': 'boolean', 'default': False},
        },
    },
    'Object': {
        'type': 'object',
        'properties': {
            'boundary': {**_POINTS, 'description': 'the outline in `map`, counter-clockwise seen from above'},
            'bounding_box': {'$ref': '#/components/schemas/Region'},
            'label': {'type': 'string'},
            'height': {**_NUMBER, 'description': "metres above the floor of the object's top; 0: unknown"},
            'clearance': {
                **_NUMBER,
                'description': "metres above the floor of the object's underside; 0: on the floor or unknown",
            },
            'track_id': {'type': 'integer', 'description': '0: not tracked'},
            'confidence': _NUMBER,
            'velocity': {'type': 'array', 'items': _NUMBER, 'description': '[x, y, z] m/s in `map`'},
            'stationary': {'type': 'boolean'},
            'seen_by': _STRINGS,
        },
    },
    'Callback': {
        'type': 'object',
        'properties': {
            'vision_system': {'type': 'string'},
            'stamp': {'type': 'number', 'description': 'capture time of the frame, seconds'},
            'algorithm': {'type': 'string'},
            'objects': {'type': 'array', 'items': {'$ref': '#/components/schemas/Object'}},
            'fused': {'type': 'boolean'},
            'status': {'type': 'string', 'description': 'fused only: OK, INVALID, UNAVAILABLE, UNSUPPORTED'},
            'message': {'type': 'string'},
            'answered': _STRINGS,
            'refused': _STRINGS,
            'missing': _STRINGS,
            'gone': {'type': 'array', 'items': {'type': 'integer'}},
        },
    },
    'DetectAnswer': {
        'type': 'object',
        'properties': {
            'status': {'type': 'string', 'enum': ['ACCEPTED']},
            'message': {'type': 'string'},
            'vision_systems': {'type': 'integer', 'description': 'how many were asked'},
            'callbacks': {'type': 'array', 'items': {'$ref': '#/components/schemas/Callback'}},
        },
    },
    'Watch': {
        'type': 'object',
        'properties': {
            'id': {'type': 'string'},
            'events': {'type': 'string', 'description': 'the URL of its event stream'},
            'vision_systems': {'type': 'integer'},
            'period': {'type': 'number', 'description': 'seconds, granted'},
        },
    },
    'VisionSystem': {
        'type': 'object',
        'properties': {
            'name': {'type': 'string'},
            'field_of_view': _POINTS,
            'algorithms': _STRINGS,
        },
    },
    'VisionSystems': {
        'type': 'object',
        'properties': {
            'vision_systems': {'type': 'array', 'items': {'$ref': '#/components/schemas/VisionSystem'}}
        },
    },
    'Coverage': {
        'type': 'object',
        'properties': {
            'region': {'$ref': '#/components/schemas/Region'},
            'vision_systems': {'type': 'array', 'items': {'$ref': '#/components/schemas/VisionSystem'}},
            'algorithms': _STRINGS,
        },
    },
    'Objects': {
        'type': 'object',
        'properties': {
            'stamp': {'type': 'number', 'nullable': True},
            'algorithms': _STRINGS,
            'objects': {'type': 'array', 'items': {'$ref': '#/components/schemas/Object'}},
        },
    },
    'Health': {
        'type': 'object',
        'properties': {
            'gateway': {'type': 'object'},
            'server': {'type': 'object', 'nullable': True},
            'nodes': {'type': 'array', 'items': {'type': 'object'}},
        },
    },
    'Ticket': {
        'type': 'object',
        'properties': {
            'ticket': {'type': 'string'},
            'expires_in': {'type': 'number', 'description': 'seconds'},
            'live': {'type': 'string', 'description': 'the path of the live stream with the ticket'},
        },
    },
    'Error': {
        'type': 'object',
        'required': ['error', 'message'],
        'properties': {
            'error': {'type': 'string', 'description': 'INVALID, UNSUPPORTED, RATE_LIMITED, BUSY, ...'},
            'message': {'type': 'string'},
            'field': {'type': 'string', 'description': '400: the field that is wrong'},
            'available_algorithms': _STRINGS,
            'retry_after': {'type': 'number', 'description': 'seconds, as Retry-After'},
        },
    },
}


def _operation(route: Route) -> dict[str, Any]:
    operation: dict[str, Any] = {'operationId': route.name, 'summary': route.summary, 'responses': {}}
    if route.ticket:
        operation['description'] = 'Needs a `ticket` from `POST /v1/tickets`.'
    elif route.op is not None:
        operation['security'] = [{'bearer': []}]
        operation['description'] = f'Needs a token with the operation `{route.op}`.'
    parameters = [{'name': name, 'in': 'query', 'required': True, 'schema': _NUMBER} for name in route.query]
    if route.ticket:
        parameters.append({'name': 'ticket', 'in': 'query', 'required': True, 'schema': {'type': 'string'}})
    for name in re.findall(r'{(\w+)}', route.path):
        parameters.append({'name': name, 'in': 'path', 'required': True, 'schema': {'type': 'string'}})
    if route.content_type == 'text/event-stream' and not route.ticket:
        parameters.append(
            {'name': 'Last-Event-ID', 'in': 'header', 'required': False, 'schema': {'type': 'string'}}
        )
    if parameters:
        operation['parameters'] = parameters
    if route.request is not None:
        operation['requestBody'] = {
            'required': True,
            'content': {'application/json': {'schema': {'$ref': f'#/components/schemas/{route.request}'}}},
        }
    for code, (description, schema) in route.answers.items():
        answer: dict[str, Any] = {'description': description}
        if schema is not None:
            answer['content'] = {'application/json': {'schema': {'$ref': f'#/components/schemas/{schema}'}}}
        elif code == 200:
            answer['content'] = {route.content_type: {}}
        operation['responses'][str(code)] = answer
    return operation


def openapi(routes: tuple[Route, ...] = ROUTES) -> dict[str, Any]:
    """The OpenAPI 3.0 document of ``routes``."""
    paths: dict[str, dict[str, Any]] = {}
    for route in routes:
        paths.setdefault(route.path, {})[route.method.lower()] = _operation(route)
    return {
        'openapi': '3.0.3',
        'info': {
            'title': 'DRVS gateway',
            'version': VERSION,
            'description': 'DRVS over HTTP and Server-Sent Events: docs/gateway.md',
        },
        'paths': paths,
        'components': {
            'schemas': SCHEMAS,
            'securitySchemes': {'bearer': {'type': 'http', 'scheme': 'bearer'}},
        },
    }
