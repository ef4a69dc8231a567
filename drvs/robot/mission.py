"""The blind robot's mission outside driving: how it asks, how it times answers, when it gives up
for want of a camera, and how it ends.

- which of the world's robots it is (:func:`fleet_robot`) and which schedule asks DRVS for it
  (:func:`schedule_for`: watches or the paper's polling), and what each round posts to it
  (:func:`post_round`);
- when a callback's frames were taken (:func:`callback_stamp`), and what a fused callback's
  status means (:func:`fused_outcome`);
- whether a vision system covers the robot, and when it fails for lack of one (:class:`Coverage`);
- the node's exit code (:func:`mission_end`).

No ROS here: every time is passed in (ROS seconds). docs/nodes/blind_robot.md describes the node.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass

from drvs.common.status import ACCEPTED, INVALID, UNSUPPORTED
from drvs.robot.controller import ARRIVED, ARRIVING, FAILED, FINAL_STATES
from drvs.robot.params import WATCH, RobotParams
from drvs.robot.perception import LOCALISATION_ROLES, STATIC_ROLES, Fix, Region
from drvs.robot.poll_schedule import RequestSchedule
from drvs.robot.watch_schedule import WatchSchedule
from drvs.sim.world import FleetRobot, World

__all__ = [
    'FAIL',
    'MAX_STAMP_AGE',
    'SKIP',
    'USE',
    'STAMP_SKEW',
    'Coverage',
    'MissionEnd',
    'callback_stamp',
    'fused_outcome',
    'fleet_robot',
    'fused_role',
    'PER_CAMERA_ROLES',
    'mission_end',
    'obstacle_memory_ttl',
    'post_round',
    'request_schedule',
    'schedule_for',
    'watch_schedule',
]

MAX_STAMP_AGE = 2.0
"""Seconds; a callback stamped older than this (or in the future) is timed by its arrival instead."""
STAMP_SKEW = 0.05
"""Seconds a stamp may lie in the future (two hosts' clocks) and still be believed."""

Schedule = RequestSchedule | WatchSchedule


def fleet_robot(world: World, name: str | None, node_name: str) -> FleetRobot:
    """The world's robot named ``name``; by default the one named as the node (its base name),
    else the world's only robot.

    :raises drvs.sim.world.WorldError: no robot of that name (the message lists the known ones).
    """
    if name is not None:
        return world.fleet_robot(name)
    if len(world.robots) == 1:
        return world.robots[0]
    return world.fleet_robot(node_name.rsplit('/', 1)[-1])


# -- asking ----------------------------------------------------------------------------------------
def request_schedule(params: RobotParams, **kwargs) -> RequestSchedule:
    """The robot's request schedule for ``params``; ``kwargs`` (clock, rng) are for tests."""
    return RequestSchedule(
        periods={'station': params.station_period},
        max_rate=params.max_request_rate,
        cap=params.retry_cap,
        **kwargs,
    )


def watch_schedule(params: RobotParams, roles: Collection[str], **kwargs) -> WatchSchedule:
    """The robot's watch schedule for ``params`` and ``roles``; ``kwargs`` (clock, rng) are for tests.

    The robot itself and moving obstacles are evaluated every control period (fused ones every
    ``~fused_period``: the fusion stage predicts its tracks between, and a fused watch costs the
    server a callback from each of its vision systems every period), static obstacles every
    ``~obstacle_period``, the station every ``~station_period``; every watch stands
    ``~watch_duration``. The robot's own watch is renewed as well when it heard nothing of itself
    for a quarter of ``~fix_timeout``: with ``changes_only`` a robot standing still gets no
    callback, and a renewal makes the vision systems report in full, so its fix stays younger
    than half ``~fix_timeout`` (beyond which it would look for itself over the whole floor).
    The robot-station box of the obstacle roles shrinks a little at a time as the robot drives:
    its watches move only once it fell under a quarter of their area.
    """
    periods = {role: params.fused_period if fused_role(params, role) else 1.0 / params.rate for role in roles}
    periods.update(dict.fromkeys(set(STATIC_ROLES) & set(roles), params.obstacle_period))
    periods['station'] = params.station_period
    return WatchSchedule(
        periods,
        params.watch_duration,
        keep_alive={'self': params.fix_timeout / 4},
        shrink={role: 0.25 for role in roles if role not in LOCALISATION_ROLES},
        max_rate=params.max_request_rate,
        cap=params.retry_cap,
        **kwargs,
    )


PER_CAMERA_ROLES = ('self', *STATIC_ROLES)
"""The roles asked per camera even with ``~fused`` (:func:`fused_role`)."""


def fused_role(params: RobotParams, role: str) -> bool:
    """Whether ``role`` is asked for fused answers: with ``~fused``, the station, people and the
    other robots (:data:`PER_CAMERA_ROLES` are not).

    - The robot itself: each camera's outline is measured at its frame's stamp, and the robot
      knows its own motion since; a fused track is a model's prediction, which stands still
      for a second after the robot starts again (a stationary track). Asked fused (with the
      fusion stage giving its newest camera's outline), the robot lost itself at the edge of
      the cameras' view in the tags world and ran into the walker in the crossing, runs that
      pass asked per camera; in the warehouse its fix was 9-17 cm off (p90) where per camera
      it was 2-5 cm.
    - Static obstacles: they never move, so a per-camera watch calls back next to nothing, and
      each camera's outline of a shelf stands until it changes, where the fusion stage's
      outline of a shelf wider than one camera's view comes in parts.

    >>> params = RobotParams(world='w.yaml')
    >>> [fused_role(params, role) for role in ('self', 'station', 'obstacle', 'human', 'robot')]
    [False, True, False, True, True]
    """
    return params.fused and role not in PER_CAMERA_ROLES


def obstacle_memory_ttl(params: RobotParams) -> float:
    """Seconds a source's obstacle outlines stand without a new report
    (:class:`~drvs.robot.occupancy.ObstacleMemory`): polling, ``~obstacle_ttl``; with per-camera
    watches, ``~watch_duration`` (each renewal makes the vision systems report in full, so a dead
    one's outlines expire); fused, until replaced (the fusion stage reports what changed and
    what is gone, and a static obstacle never changes).
    """
    if params.requests != WATCH:
        return params.obstacle_ttl
    return math.inf if params.fused else params.watch_duration


def schedule_for(params: RobotParams, roles: Collection[str], clock: Callable[[], float]) -> Schedule:
    """The schedule ``~requests`` asks for: watches timed by ``clock`` (ROS time), or polling,
    timed by its own monotonic clock."""
    if params.requests == WATCH:
        return watch_schedule(params, roles, clock=clock)
    return request_schedule(params)


def post_round(
    schedule: Schedule, regions: Mapping[str, Region], fix: Fix | None, station: Fix | None, state: str
) -> None:
    """Tell ``schedule`` which region each role needs now, or, once the mission is over, to stop
    asking (its watches are then cancelled).

    A watch is renewed when the robot heard nothing of itself for a while (``fix``'s stamp), and
    stopped at the station (``ARRIVING``) the robot asks for a full report, which confirms the
    arrival sooner than a keep-alive. Polling asks for the station less often once found.
    """
    if state in FINAL_STATES:
        schedule.stop()
    elif isinstance(schedule, WatchSchedule):
        heard = {'self': fix.stamp} if fix is not None else None
        schedule.post(regions, heard, ('self',) if state == ARRIVING else ())
    else:
        found = [role for role, f in zip(LOCALISATION_ROLES, (fix, station), strict=True) if f]
        schedule.post({role: region.box for role, region in regions.items()}, found)


# -- callbacks -------------------------------------------------------------------------------------
def callback_stamp(stamp: float, received: float) -> float:
    """When a callback's frames were taken: its ``stamp``, unless that is in the future (by more
    than :data:`STAMP_SKEW`) or older than :data:`MAX_STAMP_AGE` — a vision system whose clock
    is off, or no stamp — then its arrival, ``received``.

    >>> callback_stamp(9.5, 10.0), callback_stamp(10.02, 10.0), callback_stamp(11.0, 10.0)
    (9.5, 10.02, 10.0)
    >>> callback_stamp(7.0, 10.0), callback_stamp(0.0, 10.0)
    (10.0, 10.0)
    """
    if 0 < received - stamp < MAX_STAMP_AGE or abs(received - stamp) < STAMP_SKEW:
        return stamp
    return received


USE, SKIP, FAIL = 'use', 'skip', 'fail'
"""What :func:`fused_outcome` says to do with a fused callback."""


def fused_outcome(status: int) -> str:
    """What to do with a fused callback of ``status`` (CallbackCoordinates' constants):

    - ``OK``: :data:`USE` its objects — what the vision systems that answered found, maybe nothing;
    - ``INVALID``, ``UNSUPPORTED``: :data:`FAIL` — every vision system asked refused the request
      (the callback's message says why), asking again cannot help;
    - ``UNAVAILABLE`` (no vision system answered in time) or a status the robot does not know:
      :data:`SKIP` — it says nothing about the floor; what the robot knew stands.

    >>> fused_outcome(0), fused_outcome(1), fused_outcome(4)
    ('use', 'fail', 'skip')
    """
    if status == ACCEPTED:
        return USE
    if status in (INVALID, UNSUPPORTED):
        return FAIL
    return SKIP


# -- coverage --------------------------------------------------------------------------------------
class Coverage:
    """How many vision systems DRVS reached with each role's last accepted call, and whether one
    covers the robot itself: none for ``timeout`` seconds fails the mission.

    Not thread-safe: the node holds its lock around every call.

    :param timeout: seconds without a vision system for the ``self`` role (``~fix_timeout``).
    :param started_at: when the mission started; never covered since, it counts from then.
    """

    def __init__(self, timeout: float, started_at: float):
        self.timeout = timeout
        self.started_at = started_at
        self.vision_systems: dict[str, int] = {}  # role -> vision systems its last accepted call reached
        self._ever = False  # whether a self call ever reached a vision system
        self._none_since: float | None = None  # since when the self calls reach none

    def accepted(self, role: str, vision_systems: int, now: float) -> None:
        """DRVS accepted a call for ``role`` and forwarded it to ``vision_systems``."""
        self.vision_systems[role] = vision_systems
        if role != 'self':
            return
        if vision_systems > 0:
            self._ever, self._none_since = True, None
        elif self._none_since is None:
            # Never covered since start: count from the start, as the fix timeout does.
            self._none_since = now if self._ever else self.started_at

    @property
    def covered(self) -> bool:
        """Whether the robot's last accepted ``self`` call reached a vision system."""
        return self.vision_systems.get('self', 0) > 0

    def failure(self, now: float) -> str | None:
        """Why the mission fails now for want of a vision system; None while it need not."""
        if self._none_since is None or now - self._none_since <= self.timeout:
            return None
        return (
            f'no vision system covers the robot: DRVS forwarded its self request to none '
            f'for {self.timeout:.1f} s'
        )


# -- the end ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MissionEnd:
    """How the node ends: its exit code, and what it logs."""

    code: int
    failure: str = ''  # why it failed, logged as an error ("blind robot failed: ...")
    early: bool = False  # stopped before it reached the station (logged as a warning)


def mission_end(once: bool, crash: str | None, state: str | None, reason: str = '') -> MissionEnd:
    """The exit code once the node stops: 0 at the station; 1 when a background loop crashed
    (``crash``), with or without ``~once``; with ``~once`` also 1 when the mission failed or the
    node was shut down (Ctrl-C) before the robot reached its station.

    :param state: the controller's state (None: it never started); ``reason``: why it failed.

    >>> mission_end(True, None, ARRIVED), mission_end(False, None, FAILED, 'lost')
    (MissionEnd(code=0, failure='', early=False), MissionEnd(code=0, failure='lost', early=False))
    """
    if crash is not None:
        return MissionEnd(1, crash)
    if state == FAILED:
        return MissionEnd(1 if once else 0, reason)
    if once and state != ARRIVED:
        return MissionEnd(1, early=True)
    return MissionEnd(0)
