"""Random request bodies for the gateway's hostile-input tests: often almost right, often wrong in
one field, sometimes cut short or not JSON at all (docs/gateway.md, "A client can't hurt it")."""

from __future__ import annotations

import copy
import json
import random

__all__ = ['random_body']

COLOUR = 'colour:0,0,150,80,80,255'
VALUES = [
    None,
    True,
    -1,
    0,
    1e308,
    2.5,
    'x',
    '',
    [],
    {},
    [1, 2],
    {'a': 1},
    COLOUR,
    'motion',
    '9:9',
    'a' * 300,
]


def random_body(rng: random.Random, path: str, region: dict | None = None) -> bytes:
    """A body for ``POST path`` (``/v1/detect`` or ``/v1/watches``) asking about ``region``."""
    if rng.random() < 0.15:
        return bytes(rng.randrange(256) for _ in range(rng.randrange(40)))
    region = dict(region or {'min_x': 0, 'min_y': 0, 'max_x': 4, 'max_y': 4})
    body: dict = {'algorithm': COLOUR, 'region': region, **({'wait': 0} if path == '/v1/detect' else {})}
    for _ in range(rng.randrange(4)):
        key = rng.choice(
            ['algorithm', 'region', 'wait', 'fused', 'period', 'zzz', 'region.min_x', 'region.max_y']
        )
        if key.startswith('region.') and isinstance(body.get('region'), dict):
            body['region'][key.split('.')[1]] = copy.deepcopy(rng.choice(VALUES))
        else:
            body[key] = copy.deepcopy(rng.choice(VALUES))  # a fresh {} or []: never filled in place
    text = json.dumps(body)
    if rng.random() < 0.1:
        text = text[: rng.randrange(len(text))]
    return text.encode()
