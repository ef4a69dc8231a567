"""Which floor the blind robot has asked its obstacle roles about, and since when their answers
are in: the box a plan must stay inside before the robot commits to it.

A call DRVS accepted for a region counts as answered once every vision system it reached called
back with frames taken since the call was sent, or ``settle`` seconds after it was accepted (a
``changes_only`` watch that finds nothing calls back nothing). Until then the robot knows the part
of the new region that its previous answered region covered. No ROS here; the rule:
docs/nodes/blind_robot.md ("Asking before committing to a plan").

>>> floor = AskedFloor(['obstacle', 'human'], settle=0.5)
>>> floor.accepted('obstacle', (0, 0, 4, 3), sent=0.9, now=1.0, vision_systems=2)
>>> floor.accepted('human', (0, 0, 5, 3), sent=0.9, now=1.0, vision_systems=2)
>>> floor.known(1.2) is NOTHING
True
>>> floor.known(1.5)  # both answered: the floor both roles were asked about
(0, 0, 4, 3)
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

__all__ = ['NOTHING', 'AskedFloor', 'Box', 'inside', 'intersection']

Box = tuple[float, float, float, float]
NOTHING: Box = (math.inf, math.inf, -math.inf, -math.inf)
"""The empty box: no floor known (it holds no box)."""


def intersection(a: Box, b: Box) -> Box:
    """The box both ``a`` and ``b`` cover (:data:`NOTHING` when they do not overlap)."""
    box = (max(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), min(a[3], b[3]))
    return box if box[0] <= box[2] and box[1] <= box[3] else NOTHING


def inside(inner: Box, outer: Box) -> bool:
    """Whether ``outer`` holds ``inner`` (an empty ``inner`` is held by anything).

    >>> inside((1, 1, 2, 2), (0, 0, 3, 3)), inside((1, 1, 4, 2), (0, 0, 3, 3))
    (True, False)
    """
    if inner[0] > inner[2] or inner[1] > inner[3]:
        return True
    return outer[0] <= inner[0] and outer[1] <= inner[1] and inner[2] <= outer[2] and inner[3] <= outer[3]


@dataclass
class _Asked:
    region: Box
    sent: float  # when the call was sent: frames taken since answer it
    since: float  # when DRVS accepted the call
    vision_systems: int  # how many it reached
    heard: set[str] = field(default_factory=set)  # those that called back since


class AskedFloor:
    """Per obstacle role, the region whose answers are in, and the calls still waiting for theirs;
    see the module docstring. Not thread-safe (the node holds its lock).

    :param roles: the obstacle roles; a plan must be known to all of them.
    :param settle: seconds after DRVS accepted a call when its answers count as in anyway.
    """

    def __init__(self, roles: Iterable[str], settle: float):
        if not settle >= 0:
            raise ValueError(f'settle: must be >= 0 seconds, got {settle}')
        self.settle = settle
        self._answered: dict[str, Box] = dict.fromkeys(roles, NOTHING)
        self._waiting: dict[str, list[_Asked]] = {role: [] for role in self._answered}

    def accepted(self, role: str, region: Box, sent: float, now: float, vision_systems: int) -> None:
        """DRVS accepted at ``now`` a call for ``role`` over ``region`` sent at ``sent``, forwarded to
        ``vision_systems`` (none: nothing there to hear, it is answered at once)."""
        if role not in self._answered:
            return
        asked = _Asked(tuple(region), sent, now, vision_systems)  # type: ignore[arg-type]
        if vision_systems <= 0:
            self._answer(role, asked)
        else:
            self._waiting[role].append(asked)

    def heard(self, role: str, vision_system: str, stamp: float) -> None:
        """``vision_system`` called back about ``role`` with frames taken at ``stamp``."""
        for asked in self._waiting.get(role, ()):
            if asked.sent <= stamp:
                asked.heard.add(vision_system)
        for asked in reversed(self._waiting.get(role, ())):
            if len(asked.heard) >= asked.vision_systems:
                self._answer(role, asked)
                return

    def region(self, role: str) -> Box | None:
        """The region ``role`` was last asked about (accepted), answered or not; None before."""
        waiting = self._waiting.get(role)
        if waiting:
            return waiting[-1].region
        answered = self._answered.get(role, NOTHING)
        return None if answered is NOTHING else answered

    def known(self, now: float) -> Box:
        """The floor every role's answers are in for at ``now`` (:data:`NOTHING`: none yet)."""
        known: Box | None = None
        for role, waiting in self._waiting.items():
            for asked in reversed(waiting):
                if now - asked.since >= self.settle:
                    self._answer(role, asked)
                    break
            box = self._answered[role]
            if waiting:  # a region still asked about: only what it keeps of the answered one
                box = intersection(box, waiting[-1].region)
            known = box if known is None else intersection(known, box)
        return NOTHING if known is None else known

    def _answer(self, role: str, asked: _Asked) -> None:
        """``asked`` is answered: it replaces the answered region; older calls are done with."""
        self._answered[role] = asked.region
        waiting = self._waiting[role]
        done = [i for i, other in enumerate(waiting) if other is asked]
        if done:
            del waiting[: done[0] + 1]
