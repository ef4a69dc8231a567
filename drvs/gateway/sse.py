"""Server-Sent Events on the wire (the WHATWG HTML standard, "Server-sent events"): each event an
``id:``, an ``event:`` and one ``data:`` line of JSON, then a blank line; a comment line keeps an
idle stream open through proxies.

>>> from drvs.gateway.watches import Event
>>> encode(Event(3, 'callback', {'objects': []}))
b'id: 3\\nevent: callback\\ndata: {"objects": []}\\n\\n'
"""

from __future__ import annotations

import json

from drvs.gateway.watches import Event

__all__ = ['KEEP_ALIVE', 'RETRY', 'encode', 'last_event_id']

KEEP_ALIVE = b': keep-alive\n\n'
RETRY = b'retry: 1000\n\n'
"""Sent first: a browser's EventSource reconnects after 1 s (with Last-Event-ID)."""


def encode(event: Event) -> bytes:
    """One event as the stream carries it (JSON has no raw newlines, so one ``data:`` line)."""
    data = json.dumps(event.data, separators=(', ', ': '), allow_nan=False)
    return f'id: {event.id}\nevent: {event.kind}\ndata: {data}\n\n'.encode()


def last_event_id(header: str | None) -> int | None:
    """The ``Last-Event-ID`` header as an event id (None without one).

    :raises ValueError: not a whole number from 0.
    """
    if header is None or not header.strip():
        return None
    text = header.strip()
    if not text.isdigit() or len(text) > 18:
        raise ValueError(f'expected the id of an event (a whole number), got {header[:40]!r}')
    return int(text)
