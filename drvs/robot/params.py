"""The blind robot's parameters: one field per private ``~parameter``, each declared with its
default, meaning and range; the node's parameter table (docs/nodes/blind_robot.md) is generated
from them (:mod:`drvs.ros.param_docs`).

No ROS here: :mod:`drvs.ros.params` reads them, :mod:`drvs.robot.mission` builds the robot's
schedule from them.
"""

from __future__ import annotations

from dataclasses import dataclass

from drvs.common.failover import namespace_of, namespaces, server_return_param, service_names
from drvs.common.settings import NON_NEGATIVE, POSITIVE, REQUIRED, Settings, one_of, param
from drvs.robot.mapping import MAX_CELLS

__all__ = ['POLL', 'WATCH', 'RobotParams']

WATCH, POLL = 'watch', 'poll'
"""The values of ``~requests``: standing requests, or the paper's one-shot requests every tick."""


@dataclass(frozen=True)
class RobotParams(Settings):
    """The blind robot's ``~parameters`` (read once at start)."""

    world: str = param(REQUIRED, 'the world file: colour models, floor size, robot size and speed')
    robot: str | None = param(
        None,
        "the world's robot this node drives (its body, station and colour models)",
        default_text="the node's name if the world has a robot of that name, else the world's only robot",
    )
    requests: str = param(
        WATCH,
        'how it asks DRVS: `watch` (standing requests, renewed) or `poll` (the paper: '
        'one-shot requests every control tick)',
        check=one_of(WATCH, POLL),
    )
    fused: bool = param(
        True,
        'ask DRVS for fused answers about the station, people and other robots: one callback per '
        'request or watch period from the fusion stage, every object once, tracked, with its velocity '
        '(itself and static obstacles: per camera); false: one callback per vision system (the paper)',
    )
    fused_period: float = param(
        0.5,
        'with `~fused`, the evaluation period asked for moving obstacles (people, other robots; '
        'per camera: the control period)',
        unit='s',
        check=POSITIVE,
    )
    rate: float = param(
        5.0, 'control ticks (and, polling, rounds of DRVS requests) per second', unit='Hz', check=POSITIVE
    )
    resolution: float | None = param(
        None,
        'occupancy grid cell size',
        unit='m',
        check=POSITIVE,
        default_text=f'0.05 m, coarser on a floor that would need more than {MAX_CELLS:,} cells',
    )
    robot_radius: float | None = param(
        None,
        'inflation of obstacles (the default contains the body whatever its heading)',
        unit='m',
        check=NON_NEGATIVE,
        default_text="half the diagonal of the robot's footprint",
    )
    robot_height: float | None = param(
        None,
        'an obstacle counts unless the room under it (`DetectedObject.clearance`, measured by '
        '`elevation`) is at least this plus 5 cm: the robot drives under a shelf that high',
        unit='m',
        check=POSITIVE,
        default_text="the robot's height in the world file",
    )
    obstacle_clearance: float = param(
        0.1,
        'cells this much beyond `~robot_radius` from an obstacle cost a quarter more: a plan '
        'keeps off obstacles where there is room (a fix or an outline a few centimetres off does '
        'not graze them)',
        unit='m',
        check=NON_NEGATIVE,
    )
    roi_margin: float = param(
        0.75, 'added around the robot-station box for obstacle requests', unit='m', check=NON_NEGATIVE
    )
    obstacle_ttl: float = param(
        1.5,
        "polling, a vision system's obstacle outlines are forgotten this long after it last reported "
        'them; with watches, this long after it reported them gone (and after `~watch_duration` at most)',
        unit='s',
        check=POSITIVE,
    )
    goal_tolerance: float = param(
        0.1, "distance from the station's centre at which the robot stops", unit='m', check=POSITIVE
    )
    fix_timeout: float = param(
        5.0,
        'no new fix of the robot (at start, of the station) or no camera covering it for this long: '
        'the robot stops and fails',
        unit='s',
        check=POSITIVE,
    )
    unreachable_timeout: float = param(
        5.0, 'the station may stay unreachable this long before the robot fails', unit='s', check=POSITIVE
    )
    speed: float | None = param(
        None, 'top speed', unit='m/s', check=POSITIVE, default_text="the world's robot speed"
    )
    lookahead: float = param(
        0.2, 'distance along the plan to the point the robot steers to', unit='m', check=POSITIVE
    )
    replan_distance: float = param(
        0.3, 'map changes this close to the remaining plan trigger a repair', unit='m', check=NON_NEGATIVE
    )
    route_tolerance: float = param(
        0.15,
        'a repaired plan straying further from the old route counts as a re-plan',
        unit='m',
        check=POSITIVE,
    )
    answer_wait: float = param(
        0.5,
        'a new plan is followed once the obstacles of its corridor were asked about and answered: '
        'by every vision system asked, or this long after DRVS accepted the call',
        unit='s',
        check=NON_NEGATIVE,
    )
    robot_clearance: float = param(
        0.15,
        'other robots (the `robot` role) are kept clear by this much more than `~robot_radius`, '
        'over the floor they sweep in `~traffic_horizon`',
        unit='m',
        check=NON_NEGATIVE,
    )
    traffic_horizon: float = param(
        1.0,
        "how far ahead the other robots' motion is predicted: the floor they sweep meanwhile is an "
        'obstacle, and a closest approach within it under twice `~robot_radius` (plus 5 cm) makes '
        'the robot give way',
        unit='s',
        check=NON_NEGATIVE,
    )
    people_horizon: float = param(
        2.0,
        "how far ahead people's motion is predicted: a velocity that would bring the robot closer to "
        'someone moving than `~robot_radius`, their half size and 25 cm within it is not taken (the '
        'robot slows, stops or backs along the way it came instead)',
        unit='s',
        check=POSITIVE,
    )
    yield_patience: float = param(
        1.0,
        'the longest the robot gives way to one robot, plus half as much again for each robot of '
        'the world whose name sorts before its own (two robots giving way to each other do not wait '
        'for ever); then it drives on, round the other',
        unit='s',
        check=NON_NEGATIVE,
    )
    map_period: float = param(
        1.0,
        'at most one `~map` per period while the map changes (it is the whole grid, a byte a cell); '
        '0: one per change. Unchanged, it is published every 5 s',
        unit='s',
        check=NON_NEGATIVE,
    )
    station_period: float = param(
        2.0,
        'time between station requests once the station was found; with watches, its evaluation period',
        unit='s',
        check=POSITIVE,
    )
    obstacle_period: float = param(
        0.5,
        'with watches, the evaluation period asked for static obstacles (the robot itself and moving '
        'obstacles: the control period)',
        unit='s',
        check=POSITIVE,
    )
    watch_duration: float = param(
        20.0,
        "a watch stands this long unless renewed (at half the granted time; the robot's own also "
        'when it heard nothing of itself for a quarter of `~fix_timeout`)',
        unit='s',
        check=POSITIVE,
    )
    self_margin: float = param(
        1.0,
        'once found, the robot is asked for around its predicted position, its radius plus this; '
        'its station in its box plus this',
        unit='m',
        check=POSITIVE,
    )
    request_timeout: float = param(
        1.0, 'limit on one DRVS call; a call that takes longer counts as failed', unit='s', check=POSITIVE
    )
    max_request_rate: float = param(
        40.0, 'DRVS calls per second, retries included', unit='/s', check=POSITIVE
    )
    retry_cap: float = param(
        1.0,
        'longest wait (before jitter) between retries of a role; keep it well below `~fix_timeout`',
        unit='s',
        check=POSITIVE,
    )
    drvs_service: str = param(
        '/drvs/detect_object_boundary', "the DRVS server's DetectObjectBoundary (with `poll`)"
    )
    watch_service: str = param(
        '/drvs/watch_object_boundary', "the DRVS server's WatchObjectBoundary (with `watch`)"
    )
    servers: str | None = param(
        None,
        'the DRVS servers (replicas on one registry database) by namespace, in order, e.g. '
        '`[/drvs, /drvs_b]`: it asks the first, and moves to the next on `UNAVAILABLE` or no answer '
        'within `~request_timeout`, its watches renewed there at once (each: the service in use in it)',
        default_text='the namespace of `~watch_service` (`watch`) or `~drvs_service` (`poll`): `[/drvs]`',
        separator=',',
    )
    server_return: float = server_return_param()
    once: bool = param(False, 'exit when done: 0 at the station, 1 otherwise')

    def __post_init__(self):
        super().__post_init__()
        if self.servers is not None:
            namespaces(self.servers)

    @property
    def services(self) -> list[str]:
        """The service it asks (``~watch_service`` or ``~drvs_service``) on each server of ``~servers``."""
        service = self.watch_service if self.requests == WATCH else self.drvs_service
        servers = [namespace_of(service)] if self.servers is None else namespaces(self.servers)
        return service_names(servers, service)
