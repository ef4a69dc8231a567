"""Random rosbridge frames for the rosbridge endpoint's hostile-input tests: valid operations with
fields dropped, retyped or out of range, frames cut short, and plain garbage (docs/gateway.md,
"rosbridge endpoint")."""

from __future__ import annotations

import json
import random

__all__ = ['random_frame']

COLOUR = 'colour:0,0,150,80,80,255'
CALLBACK = '/robot/callback'
STRANGE = [None, True, -1, 2**70, 1e308, '', 'x' * 300, [], {}, [[[]]], {'a': {'b': {}}}, '\u0000', '/drvs']


def _valid(server: str) -> list[dict]:
    return [
        {'op': 'advertise_service', 'type': 'drvs/CallbackCoordinates', 'service': CALLBACK},
        {
            'op': 'call_service',
            'id': 'c1',
            'service': f'{server}/detect_object_boundary',
            'args': {'algorithm': COLOUR, 'callback_service': CALLBACK, 'request_id': 'random'},
        },
        {'op': 'subscribe', 'topic': f'{server}/registry'},
        {'op': 'unsubscribe', 'topic': f'{server}/registry'},
        {'op': 'set_level', 'level': 'info'},
        {'op': 'service_response', 'id': f'drvs:{CALLBACK}:1', 'service': CALLBACK, 'values': {}},
        {'op': 'unadvertise_service', 'service': CALLBACK},
        {'op': 'auth', 'mac': 'x'},
    ]


def random_frame(rng: random.Random, server: str = '/drvs') -> str:
    """A hostile text frame for an endpoint in front of the DRVS server ``server``."""
    choice = rng.random()
    if choice < 0.15:
        return bytes(rng.randrange(256) for _ in range(rng.randrange(1, 64))).decode('latin-1')
    frame = rng.choice(_valid(server))
    for _ in range(rng.randrange(1, 4)):
        target = frame['args'] if isinstance(frame.get('args'), dict) and rng.random() < 0.5 else frame
        key = rng.choice([*target, 'op', 'id', 'zzz'])
        if rng.random() < 0.2:
            target.pop(key, None)
        else:
            target[key] = json.loads(json.dumps(rng.choice(STRANGE)))
    text = json.dumps(frame)
    if choice > 0.9:
        text = text[: rng.randrange(len(text))]
    return text
