"""The vision_system node's parameters (``~params``), read once into :class:`VisionSystemParams`.

Each field is declared with its default, meaning and range; docs/nodes/vision_system.md's table
is generated from them (:mod:`drvs.ros.param_docs`).
"""

from __future__ import annotations

from dataclasses import dataclass

from drvs.common.failover import namespace_of, namespaces, server_return_param, service_names
from drvs.common.settings import (
    NON_NEGATIVE,
    POSITIVE,
    REQUIRED,
    ParamError,
    Settings,
    at_least,
    one_of,
    param,
)

__all__ = ['SOURCES', 'VisionSystemParams']

SOURCES = ('render', 'topic')
"""Where frames come from: rendered from the world (the simulation), or a camera topic."""


@dataclass(frozen=True)
class VisionSystemParams(Settings):
    camera: str = param(
        REQUIRED,
        'which `vision_systems` entry of the world this node is (`render`)',
        default_text="the node's name",
    )
    world: str = param('', 'the world file (required with `~source` `render`)', default_text='none')
    source: str = param(
        '',
        'where frames come from: rendered from the world, or a camera topic',
        check=one_of(*SOURCES),
        default_text='`render` with `~world`, else `topic`',
    )
    compressed: bool = param(False, '`topic`: subscribe to `image/compressed` instead of `image`')
    depth: bool = param(
        False, '`topic`: lift outlines with the aligned depth image `depth`, and run `elevation` with it'
    )
    max_range: float = param(
        30.0,
        '`topic`: distance from the camera beyond which the floor is not part of the field of view',
        unit='m',
        check=POSITIVE,
    )
    frame_timeout: float = param(
        1.0,
        '`topic`: how long a request waits for a new frame when the newest is too old',
        unit='s',
        check=POSITIVE,
    )
    stale_after: float = param(
        3.0, '`topic`: time without frames after which the camera unregisters', unit='s', check=POSITIVE
    )
    tf_timeout: float = param(
        0.5,
        "`topic`: how long to wait for the camera's transform at an image's stamp",
        unit='s',
        check=POSITIVE,
    )
    map_frame: str = param('map', '`topic`: the frame outlines and fields of view are given in')
    reference: str = param(
        '',
        "an image file of the camera's empty floor, `foreground`'s reference (`drvs_calibrate --reference` "
        'writes one)',
        default_text='none: `render` renders the empty world; `topic` learns it from its first frames',
    )
    tag_height: float = param(
        0.0,
        'height above the floor of the plane AprilTags lie on, unless the request (`h=H`) or the world says',
        unit='m',
        check=NON_NEGATIVE,
    )
    motion_rate: float = param(
        5.0,
        'frames fed to algorithms with memory (`motion`) while they are in use',
        unit='Hz',
        check=POSITIVE,
    )
    motion_window: float = param(
        5.0,
        'time after the last `motion` request during which frames keep being fed',
        unit='s',
        check=POSITIVE,
    )
    min_area: float = param(20.0, 'smallest object', unit='px', check=NON_NEGATIVE)
    epsilon: float = param(
        1.0, 'outline simplification tolerance (Douglas-Peucker)', unit='px', check=NON_NEGATIVE
    )
    max_frame_age: float = param(
        0.1,
        'a request reuses the newest frame if it is at most this old',
        unit='s',
        check=NON_NEGATIVE,
    )
    callback_timeout: float = param(
        2.0,
        'limit on one callback to a robot; a failed or hung one is logged and dropped',
        unit='s',
        check=POSITIVE,
    )
    max_callback_clients: int = param(
        64,
        "connections to robots' callback services kept, the least recently used closed beyond it",
        check=at_least(1),
    )
    callback_idle: float = param(
        30.0, 'an unused connection to a callback service is closed after this', unit='s', check=POSITIVE
    )
    workers: int = param(2, 'threads processing requests', check=at_least(1))
    queue_size: int = param(
        32, 'requests waiting for a worker; beyond it requests are refused `BUSY`', check=at_least(1)
    )
    min_watch_period: float = param(
        0.1,
        'shortest period granted to a watch; a shorter one asked for is lengthened',
        unit='s',
        check=POSITIVE,
    )
    max_watch_duration: float = param(
        60.0, 'longest duration granted to a watch: it expires then unless renewed', unit='s', check=POSITIVE
    )
    max_watches: int = param(
        256, 'watches standing at once; beyond it new watches are refused `BUSY`', check=at_least(1)
    )
    change_tolerance: float = param(
        0.03,
        '`changes_only` watches: how far an outline moves before it is reported again',
        unit='m',
        check=NON_NEGATIVE,
    )
    register_service: str = param('/drvs/register_vision_service', "the DRVS server's RegisterVisionService")
    servers: str | None = param(
        None,
        'the DRVS servers (replicas on one registry database) by namespace, in order, e.g. '
        '`[/drvs, /drvs_b]`: it registers and renews through the first, and moves to the next on '
        '`UNAVAILABLE` or no answer within `~register_timeout` (each: `~register_service` in it)',
        default_text="`~register_service`'s namespace: `[/drvs]`",
        separator=',',
    )
    server_return: float = server_return_param()
    register_timeout: float = param(2.0, 'limit on one registration call', unit='s', check=POSITIVE)
    retry_period: float = param(
        1.0,
        "longest wait between registration attempts beyond the server's `retry_after`",
        unit='s',
        check=POSITIVE,
    )
    move_threshold: float = param(
        0.01,
        'how far a field-of-view vertex moves before the new field of view is registered',
        unit='m',
        check=NON_NEGATIVE,
    )
    poses_topic: str = param('/world_sim/poses', "world_sim's pose topic (`render`)")
    debug_rate: float = param(
        1.0,
        '`~debug_image` views per second while subscribed (0: only after requests)',
        unit='Hz',
        check=NON_NEGATIVE,
    )

    def __post_init__(self):
        if not self.source:  # frozen: the resolved default is set once, here
            object.__setattr__(self, 'source', 'render' if self.world else 'topic')
        super().__post_init__()
        if self.servers is not None:
            namespaces(self.servers)
        if self.source == 'render' and not self.world:
            raise ParamError(
                'world', 'required with ~source render (or use ~source topic and a camera topic)'
            )

    @property
    def register_services(self) -> list[str]:
        """The registration service of each server in ``~servers``, in order."""
        servers = [namespace_of(self.register_service)] if self.servers is None else namespaces(self.servers)
        return service_names(servers, self.register_service)
