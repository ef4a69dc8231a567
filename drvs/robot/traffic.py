"""Keeping clear of the other robots: their velocities, the floor they will sweep, and who yields.

:class:`MoverTracker` gives each other robot a velocity — from its successive outlines
(nearest-neighbour association), or as DRVS's fused tracks give it. :func:`swept` is the floor
a robot covers over a short horizon, which the map holds as an obstacle; :class:`Yielding`
stops this robot while a predicted closest approach is under a safety distance and the rule
says it is the one to give way. No ROS; every time is passed in. The rules:
docs/nodes/blind_robot.md ("Other robots").
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from shapely.affinity import translate
from shapely.geometry import Polygon

__all__ = [
    'PERSON_MARGIN',
    'STILL',
    'YIELD_MARGIN',
    'Mover',
    'MoverTracker',
    'Yielding',
    'clear_of_people',
    'closest_approach',
    'swept',
]

Point = tuple[float, float]
STILL = 0.15
"""m/s: a robot slower than this stands still (the map holds it; nobody starts giving way to it)."""
YIELD_MARGIN = 0.2
"""Metres beyond the sum of two robots' radii under which their predicted closest approach is too close."""
PERSON_MARGIN = 0.25
"""Metres beyond the robot's radius and a person's under which the robot comes too close to them."""
SETTLE = 0.5
"""Seconds: with no velocity clear of people, the one whose closest approach from then on is the
largest is taken (:func:`clear_of_people`)."""


@dataclass(frozen=True)
class Mover:
    """Another robot: its outline and its velocity (m/s in ``map``), seen at ``seen`` (None: now)."""

    outline: Polygon
    velocity: Point = (0.0, 0.0)
    seen: float | None = None

    def at(self, now: float) -> Mover:
        """This mover predicted to ``now`` (moved along its velocity since it was seen)."""
        if self.seen is None or now <= self.seen:
            return self
        age = now - self.seen
        return Mover(
            translate(self.outline, self.velocity[0] * age, self.velocity[1] * age), self.velocity, now
        )

    @property
    def position(self) -> Point:
        centre = self.outline.centroid
        return (centre.x, centre.y)

    @property
    def speed(self) -> float:
        return math.hypot(*self.velocity)

    @property
    def radius(self) -> float:
        """Metres from its centroid to its farthest corner."""
        centre = self.outline.centroid
        return max(math.dist((centre.x, centre.y), corner) for corner in self.outline.exterior.coords)


class MoverTracker:
    """Velocities of the other robots from their outlines at successive times.

    Each outline is matched to the nearest outline of the previous update within ``gate``
    metres (plus ``max_speed`` times the time between them); its velocity is the centroid's
    displacement over that time, smoothed (``smoothing`` of the new estimate, the rest of the
    old), capped at ``max_speed``. An outline without a match stands still until the next update.
    """

    def __init__(self, gate: float = 0.3, smoothing: float = 0.5, max_speed: float = 2.0):
        self.gate, self.smoothing, self.max_speed = gate, smoothing, max_speed
        self.movers: list[Mover] = []
        self._stamp: float | None = None

    def update(
        self, stamp: float, outlines: Sequence[Polygon], velocities: Sequence[Point | None] | None = None
    ) -> list[Mover]:
        """The movers at ``stamp`` (when the outlines were seen): ``velocities`` where given (a
        fused track's), estimated for the others. Nothing seen since the last update (the same
        ``stamp``, maybe fewer outlines): the velocities of the last one carry on."""
        given = list(velocities) if velocities is not None else [None] * len(outlines)
        if self._stamp is not None and stamp <= self._stamp:
            return [
                Mover(outline, velocity if velocity is not None else self._carried(outline), self._stamp)
                for outline, velocity in zip(outlines, given, strict=True)
            ]
        dt = stamp - self._stamp if self._stamp is not None else 0.0
        previous, movers = list(self.movers), []
        for outline, velocity in zip(outlines, given, strict=True):
            if velocity is None:
                velocity = self._estimate(outline, previous, dt)
            movers.append(Mover(outline, velocity, stamp))
        self.movers, self._stamp = movers, stamp
        return movers

    def _carried(self, outline: Polygon) -> Point:
        """The velocity of the last update's mover nearest ``outline``, within ``gate``; else standing."""
        centre = outline.centroid
        near = [(centre.distance(m.outline.centroid), i) for i, m in enumerate(self.movers)]
        near = [(d, i) for d, i in near if d <= self.gate]
        return self.movers[min(near)[1]].velocity if near else (0.0, 0.0)

    def _estimate(self, outline: Polygon, previous: list[Mover], dt: float) -> Point:
        if not previous or dt <= 0:
            return (0.0, 0.0)
        centre = outline.centroid
        match = min(previous, key=lambda m: centre.distance(m.outline.centroid))
        moved = centre.distance(match.outline.centroid)
        if moved > self.gate + self.max_speed * dt:
            return (0.0, 0.0)
        previous.remove(match)
        old = match.outline.centroid
        measured = ((centre.x - old.x) / dt, (centre.y - old.y) / dt)
        a = self.smoothing
        vx, vy = (a * m + (1 - a) * v for m, v in zip(measured, match.velocity, strict=True))
        speed = math.hypot(vx, vy)
        if speed > self.max_speed:
            vx, vy = vx * self.max_speed / speed, vy * self.max_speed / speed
        return (vx, vy)


def swept(outline: Polygon, velocity: Point, horizon: float) -> Polygon:
    """The floor ``outline`` covers moving at ``velocity`` for ``horizon`` seconds.

    >>> from shapely.geometry import box
    >>> swept(box(0, 0, 1, 1), (0.5, 0.0), 2.0).bounds
    (0.0, 0.0, 2.0, 1.0)
    """
    dx, dy = velocity[0] * horizon, velocity[1] * horizon
    if math.hypot(dx, dy) < 1e-6:
        return outline
    return outline.union(translate(outline, dx, dy)).convex_hull


def closest_approach(offset: Point, relative: Point, horizon: float) -> tuple[float, float]:
    """(when, how close) two robots come within ``horizon`` seconds, from the other's ``offset``
    and ``relative`` velocity (both the other's minus this robot's).

    >>> closest_approach((2.0, 0.5), (-1.0, 0.0), 5.0)
    (2.0, 0.5)
    """
    speed2 = relative[0] ** 2 + relative[1] ** 2
    t = 0.0 if speed2 == 0 else -(offset[0] * relative[0] + offset[1] * relative[1]) / speed2
    t = min(max(t, 0.0), horizon)
    return t, math.hypot(offset[0] + relative[0] * t, offset[1] + relative[1] * t)


class Yielding:
    """Whether this robot gives way now (see the module docstring).

    A conflict is another robot whose closest approach to this one (at the velocity it means to
    drive) within ``horizon`` seconds is under ``distance``. It starts giving way to a moving
    robot when it closes the gap at least as fast as the other (the one running into the other
    gives way; near a tie, both do). It goes on while the conflict lasts, judged with the other's
    velocity when it started while the other stands (the other may be giving way too, and will
    go on as before); but once the other stood ``patience`` seconds meanwhile it drives on
    (round it: the map holds it) until that conflict is over. ``patience`` differs between the
    robots of a fleet, so two robots giving way to each other do not wait for ever.

    :param horizon: seconds ahead the robots' motions are predicted.
    :param distance: metres between two robots' centres under which they come too close.
    :param patience: seconds it waits for a robot that stands still as well.
    :param tie: m/s by which the other may close the gap faster and this robot still gives way.
    :param gate: metres the robot it gives way to may move between two steps and still be the same.
    :param release: metres beyond ``distance`` the predicted closest approach must reach before it
        stops giving way.
    """

    def __init__(
        self,
        horizon: float,
        distance: float,
        patience: float,
        tie: float = 0.05,
        gate: float = 0.5,
        release: float = 0.1,
    ):
        self.horizon, self.distance, self.patience = horizon, distance, patience
        self.tie, self.gate, self.release = tie, gate, release
        self.yields = 0  # conflicts it gave way in
        self._other: Mover | None = None  # the robot it gives way to, as it was when it started
        self._at: Point = (0.0, 0.0)  # where that robot was at the last step
        self._waited = 0.0  # seconds that robot stood still since
        self._last: float | None = None  # the time of the last step
        self._over: Point | None = None  # gave up waiting for a robot, last seen here: drives on

    def conflict(self, position: Point, velocity: Point, movers: Sequence[Mover]) -> Mover | None:
        """The robot of ``movers`` this one would come too close to soonest, or None."""
        found = []
        for i, mover in enumerate(movers):
            t = self._too_close(position, velocity, mover.position, mover.velocity)
            if t is not None:
                found.append((t, i))
        return movers[min(found)[1]] if found else None

    def _too_close(
        self, position: Point, velocity: Point, other: Point, its: Point, margin: float = 0.0
    ) -> float | None:
        """When (s from now) a robot at ``other`` moving at ``its`` comes closer than ``distance``
        (plus ``margin``); None: it does not."""
        offset = (other[0] - position[0], other[1] - position[1])
        t, d = closest_approach(offset, (its[0] - velocity[0], its[1] - velocity[1]), self.horizon)
        limit = self.distance + margin
        if d < limit and (t > 0 or math.hypot(*offset) < limit):
            return t
        return None

    def gives_way(self, position: Point, velocity: Point, mover: Mover) -> bool:
        """Whether this robot, at ``position`` meaning to drive at ``velocity``, gives way to ``mover``."""
        if mover.speed < STILL:
            return False
        p, v = mover.position, mover.velocity
        gap = math.hypot(p[0] - position[0], p[1] - position[1])
        if gap < 1e-9:
            return True
        ux, uy = (p[0] - position[0]) / gap, (p[1] - position[1]) / gap
        mine = velocity[0] * ux + velocity[1] * uy
        theirs = -(v[0] * ux + v[1] * uy)
        return mine >= theirs - self.tie

    def step(self, now: float, position: Point, velocity: Point, movers: Sequence[Mover]) -> Mover | None:
        """The robot this one gives way to now (it then stands still), or None (it drives on).
        ``movers`` are predicted to ``now`` first."""
        movers = [mover.at(now) for mover in movers]
        dt = 0.0 if self._last is None else max(now - self._last, 0.0)
        self._last = now
        if math.hypot(*velocity) < 1e-9:
            return None
        if self._other is not None:
            held = self._holding(dt, position, velocity, movers)
            if held is not None:
                return held
        if self._over is not None:
            passing = self._same(self._over, movers)
            if passing is not None and self._too_close(
                position, velocity, passing.position, passing.velocity
            ):
                self._over = passing.position
                return None
            self._over = None
        mover = self.conflict(position, velocity, movers)
        if mover is None or not self.gives_way(position, velocity, mover):
            return None
        self._other, self._at, self._waited = mover, mover.position, 0.0
        self.yields += 1
        return mover

    def _holding(self, dt: float, position: Point, velocity: Point, movers: Sequence[Mover]) -> Mover | None:
        """Still giving way to the robot it gave way to: that robot now, or None (no longer)."""
        assert self._other is not None  # by step
        now_seen = self._same(self._at, movers)
        if now_seen is None:  # out of sight: no longer in the way
            self._other = None
            return None
        self._at = now_seen.position
        its = now_seen.velocity
        if now_seen.speed < STILL:
            self._waited += dt
            its = self._other.velocity  # it may go on as before at any moment
            if self._waited > self.patience:
                self._other, self._over = None, now_seen.position
                return None
        if self._too_close(position, velocity, now_seen.position, its, self.release) is None:
            self._other = None
            return None
        return now_seen

    def _same(self, at: Point, movers: Sequence[Mover]) -> Mover | None:
        """The mover nearest ``at``, within ``gate``; None without one."""
        near = [(math.dist(at, m.position), i) for i, m in enumerate(movers)]
        near = [(d, i) for d, i in near if d <= self.gate]
        return movers[min(near)[1]] if near else None


def _out_of_the_way(position: Point, people: Sequence[Mover], speed: float) -> Point | None:
    """A velocity of ``speed`` square to the way the nearest of ``people`` walks, away from the line it
    walks along (left of it when the robot stands on that line); None without a speed."""
    if speed <= 0:
        return None
    person = min(people, key=lambda p: math.dist(p.position, position))
    vx, vy = person.velocity
    norm = math.hypot(vx, vy)
    nx, ny = -vy / norm, vx / norm  # left of its way
    if nx * (position[0] - person.position[0]) + ny * (position[1] - person.position[1]) < 0:
        nx, ny = -nx, -ny
    return (nx * speed + 0.0, ny * speed + 0.0)  # (+ 0.0: no -0.0)


def clear_of_people(
    position: Point,
    planned: Point,
    people: Sequence[Mover],
    radius: float,
    horizon: float,
    back: Point = (0.0, 0.0),
    free: Callable[[Point], bool] = lambda point: True,
) -> tuple[Point, Mover | None]:
    """The velocity that keeps a robot of ``radius`` at ``position`` clear of moving ``people``
    (who give way to nobody), and the person it changed the plan for (None: ``planned`` is clear).

    A velocity is clear when, kept for ``horizon`` seconds, the predicted closest approach to each
    person moving at their velocity stays over the robot's radius, the person's and
    :data:`PERSON_MARGIN`. The first clear one of: ``planned``, half of it, standing still,
    stepping aside (square to the nearest person's way, away from the line they walk along) and
    ``back`` (the way the robot came, reversed: floor it has just been on), the last two where
    ``free`` holds the point they reach in one second or two; with none clear, the one that comes
    least close from :data:`SETTLE` seconds on (when it is already too close, the way out). So the
    robot waits before a person's way, and steps out of it rather than wait in it. (Backing alone was not
    enough: a robot that came from where the person was coming from stood in their way, backing
    towards them being worse, until it was walked into.)

    >>> from shapely.geometry import box
    >>> person = Mover(box(1.8, -0.2, 2.2, 0.2), (-0.5, 0.0))
    >>> clear_of_people((0.0, 0.0), (0.5, 0.0), [person], 0.2, 2.0)[0]  # head on: stand
    (0.0, 0.0)
    >>> clear_of_people((0.0, 0.0), (0.0, 0.5), [person], 0.2, 2.0)[0]  # moving out of the way
    (0.0, 0.5)
    >>> clear_of_people((1.0, 0.0), (0.0, 0.0), [person], 0.2, 2.0, back=(0.5, 0.0))[0]  # in its way
    (0.0, -0.5)
    >>> coming_down = Mover(box(-0.2, 0.8, 0.2, 1.2), (0.0, -0.3))  # where the robot came from
    >>> clear_of_people((0.0, 0.0), (0.0, 0.0), [coming_down], 0.2, 2.0, back=(0.0, 0.5))[0]
    (0.5, 0.0)
    >>> walking_at_it = Mover(box(1.2, 0.1, 1.6, 0.5), (0.0, -0.3))  # already close, coming nearer
    >>> clear_of_people((1.0, 0.0), (0.5, 0.0), [walking_at_it], 0.2, 2.0, back=(-0.5, 0.0))[0]
    (-0.5, 0.0)
    """
    moving = [p for p in people if p.speed >= STILL]
    if not moving:
        return planned, None
    candidates = [planned, (planned[0] / 2, planned[1] / 2), (0.0, 0.0)]
    step = math.hypot(*back) or math.hypot(*planned)
    aside = _out_of_the_way(position, moving, step)
    for way in (aside, back):
        # Where it gets to in one second or two: out of a person's way can take more than one (the
        # floor the person sweeps, and the margin round it, are not free in the map either).
        if (
            way is not None
            and math.hypot(*way) > 0
            and any(free((position[0] + way[0] * t, position[1] + way[1] * t)) for t in (1.0, 2.0))
        ):
            candidates.append(way)
    best: tuple[float, Point, Mover | None] | None = None
    for velocity in candidates:
        closest, later, nearest = math.inf, math.inf, None
        for person in moving:
            offset = (person.position[0] - position[0], person.position[1] - position[1])
            relative = (person.velocity[0] - velocity[0], person.velocity[1] - velocity[1])
            limit = radius + person.radius + PERSON_MARGIN
            slack = closest_approach(offset, relative, horizon)[1] - limit
            # Already too close, every velocity's closest approach is now: rank them by the one
            # from half a second on (the way out, not further in).
            ahead = (offset[0] + relative[0] * SETTLE, offset[1] + relative[1] * SETTLE)
            later = min(later, closest_approach(ahead, relative, max(horizon - SETTLE, 0.0))[1] - limit)
            if slack < closest:
                closest, nearest = slack, person
        if closest >= 0:
            return velocity, (None if velocity == planned else nearest)
        if best is None or later > best[0]:
            best = (later, velocity, nearest)
    assert best is not None  # planned is always a candidate
    return best[1], best[2]
