"""The DRVS server's settings: every parameter with its default, meaning, unit and range.

Read from the node's private parameters (``~lease``, ...) by :func:`drvs.ros.params.read_params`;
docs/nodes/drvs_server.md's parameter table is generated from these declarations. No ROS here.
"""

from __future__ import annotations

from dataclasses import dataclass

from drvs.common.settings import NON_NEGATIVE, POSITIVE, ParamError, Range, Settings, at_least, param
from drvs.server.sites import MAX_SITE_LENGTH, SITE_PATTERN

__all__ = ['ServerSettings']


REGISTRY = Range(
    lambda value: value == 'memory' or value.startswith(('postgresql://', 'postgres://')),
    'must be memory or a postgresql:// DSN',
    '`memory` or a `postgresql://` DSN',
)

SITE = Range(
    lambda value: len(value) <= MAX_SITE_LENGTH and SITE_PATTERN.fullmatch(value) is not None,
    f'must be letters, digits, _ or -, at most {MAX_SITE_LENGTH} of them',
    f'letters, digits, `_`, `-` (at most {MAX_SITE_LENGTH})',
)


@dataclass(frozen=True)
class ServerSettings(Settings):
    registry: str = param(
        'memory',
        'where the registry lives: this process, or a PostgreSQL database shared by replicas '
        '(docs/registry.md)',
        check=REGISTRY,
    )
    site: str = param(
        '',
        'with a database: the site (ROS master) this server serves; entries of other sites are called at '
        'their rosrpc:// address (docs/registry.md, "Sites"); empty: the only site',
        check=SITE,
    )
    watch_takeover: float = param(
        5.0,
        'with a database: the watches of a replica not heard from this long are taken over',
        unit='s',
        check=POSITIVE,
    )
    lease: float = param(
        10.0, 'a registration expires unless renewed within this time', unit='s', check=POSITIVE
    )
    max_failures: int = param(
        3,
        'failed forwards in a row that remove (and eject) a vision system; renewals do not reset it',
        check=at_least(1),
    )
    ejection_time: float = param(
        10.0, 'an ejected vision system is refused this long × its ejections', unit='s', check=NON_NEGATIVE
    )
    max_ejection_time: float = param(
        300.0, 'the longest ejection; at least `~ejection_time`', unit='s', check=NON_NEGATIVE
    )
    forward_timeout: float = param(
        2.0, 'limit on one forward (connect, send, reply)', unit='s', check=POSITIVE
    )
    workers: int = param(8, 'forwarding threads (a hung vision system holds at most one)', check=at_least(1))
    max_pending: int = param(
        1000, 'forwards queued or running; beyond it requests are refused `BUSY`', check=at_least(1)
    )
    max_pending_per_vision_system: int = param(
        10,
        'a vision system this far behind is skipped by new requests; one caller holds at most its '
        'fair share of these places (a fifth kept free, the rest split among the callers: 8 alone, '
        '4 each of two), beyond it `RATE_LIMITED`',
        check=at_least(1),
    )
    busy_retry_after: float = param(0.5, '`retry_after` of a `BUSY` refusal', unit='s', check=POSITIVE)
    unavailable_retry_after: float = param(
        1.0, '`retry_after` when the master did not answer', unit='s', check=POSITIVE
    )
    max_requests_per_s: float = param(
        50.0, 'calls per second per caller id, on all three services', unit='/s', check=POSITIVE
    )
    burst: int = param(100, 'requests a caller may send at once before the rate applies', check=at_least(1))
    check_timeout: float = param(
        1.0, 'limit on each master lookup / probe during validation', unit='s', check=POSITIVE
    )
    callback_cache: float = param(
        5.0, 'how long a verified callback service is trusted', unit='s', check=NON_NEGATIVE
    )
    callback_memory: float = param(
        60.0,
        'a verified callback service the master stops listing is `UNAVAILABLE`, not `INVALID`, this long',
        unit='s',
        check=NON_NEGATIVE,
    )
    registry_period: float = param(
        0.2, 'minimum time between two `~registry` messages', unit='s', check=NON_NEGATIVE
    )
    min_watch_period: float = param(0.1, 'shortest period a watch is granted', unit='s', check=POSITIVE)
    max_watch_duration: float = param(
        60.0, 'longest duration a watch is granted (it expires unless renewed)', unit='s', check=POSITIVE
    )
    max_watches: int = param(
        1000, 'watches standing at once; beyond it new watches are refused `BUSY`', check=at_least(1)
    )
    fused_deadline: float = param(
        2.0,
        'a fused request is answered once every vision system asked has answered, or after this long',
        unit='s',
        check=POSITIVE,
    )
    max_fused_requests: int = param(
        1000, 'fused requests waiting for their vision systems; beyond it refused `BUSY`', check=at_least(1)
    )
    max_tracks: int = param(
        1000,
        'tracks per algorithm string; outlines beyond it are left untracked (counted in `~stats`)',
        check=at_least(1),
    )
    track_coast: float = param(
        2.0, 'a track no camera sees is predicted this long, then reported gone', unit='s', check=POSITIVE
    )
    objects_period: float = param(
        0.1, 'least time between two `~objects` messages (the fused tracks)', unit='s', check=POSITIVE
    )

    def __post_init__(self):
        super().__post_init__()
        if not self.max_ejection_time >= self.ejection_time:
            raise ParamError(
                'max_ejection_time',
                f'must be at least ~ejection_time ({self.ejection_time!r}), got {self.max_ejection_time!r}',
            )
