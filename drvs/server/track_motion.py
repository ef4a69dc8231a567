"""A track's motion: a constant-velocity Kalman filter on its centroid that accepts late measurements.

Cameras capture at different times and their frames arrive out of stamp order. :class:`Motion`
keeps the measurements of the last ``window`` seconds with the filter's state after each; a late
measurement is put in its place and the filter re-run from there, so the state does not depend on
the order of arrival. The two axes share one covariance (isotropic noise), so the filter is a few
float operations. The method and its constants: docs/fusion-tracking.md.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

__all__ = ['Motion', 'MotionNoise', 'State']

MAX_KEPT = 256
"""Measurements kept per track at most, whatever the window (40 a second from 4 cameras at 10 Hz)."""

Point = tuple[float, float]


@dataclass(frozen=True)
class MotionNoise:
    """The filter's noise: ``acceleration`` (m/s², the white-noise acceleration's standard
    deviation), ``initial_speed`` (m/s, the velocity prior's standard deviation)."""

    acceleration: float
    initial_speed: float


@dataclass(frozen=True)
class State:
    """The filter's state at ``stamp``: position, velocity and the covariance shared by both axes
    (``p_pp`` position variance, ``p_pv`` covariance, ``p_vv`` velocity variance)."""

    stamp: float
    x: float
    y: float
    vx: float
    vy: float
    p_pp: float
    p_pv: float
    p_vv: float

    def predicted(self, stamp: float, q: float) -> State:
        """The state predicted to ``stamp`` (not earlier than this state's)."""
        dt = stamp - self.stamp
        if dt <= 0:
            return self
        return State(
            stamp,
            self.x + dt * self.vx,
            self.y + dt * self.vy,
            self.vx,
            self.vy,
            self.p_pp + 2 * dt * self.p_pv + dt * dt * self.p_vv + q * dt**3 / 3,
            self.p_pv + dt * self.p_vv + q * dt * dt / 2,
            self.p_vv + q * dt,
        )

    def updated(self, z: Point, r: float) -> State:
        """The state corrected by a position measurement ``z`` of variance ``r`` (each axis)."""
        s = self.p_pp + r
        k_p, k_v = self.p_pp / s, self.p_pv / s
        ex, ey = z[0] - self.x, z[1] - self.y
        return State(
            self.stamp,
            self.x + k_p * ex,
            self.y + k_p * ey,
            self.vx + k_v * ex,
            self.vy + k_v * ey,
            (1 - k_p) * self.p_pp,
            (1 - k_p) * self.p_pv,
            self.p_vv - k_v * self.p_pv,
        )


class Motion:
    """One track's filter with the measurements of the last ``window`` seconds (see the module
    docstring). Not thread-safe: the tracker owns it."""

    def __init__(self, noise: MotionNoise, window: float, stamp: float, z: Point, r: float):
        self.noise = noise
        self.window = window
        self._q = noise.acceleration**2
        self._stamps: list[float] = []
        self._measurements: list[tuple[Point, float]] = []
        self._states: list[State] = []  # after each measurement
        self._base: State | None = None  # after the measurements dropped from the window
        self.first_stamp = stamp
        self.update(stamp, z, r)

    @property
    def state(self) -> State:
        """The newest state (after the newest measurement)."""
        return self._states[-1]

    def update(self, stamp: float, z: Point, r: float) -> bool:
        """Add a measurement taken at ``stamp``; False (and nothing changes) when it is older than
        the window kept."""
        if self._base is not None and stamp < self._base.stamp:
            return False
        k = bisect.bisect_right(self._stamps, stamp)
        self._stamps.insert(k, stamp)
        self._measurements.insert(k, (z, r))
        del self._states[k:]
        state = self._states[k - 1] if k else self._base
        for stamp_i, (z_i, r_i) in zip(self._stamps[k:], self._measurements[k:], strict=True):
            if state is None:
                speed = self.noise.initial_speed**2
                state = State(stamp_i, z_i[0], z_i[1], 0.0, 0.0, r_i, 0.0, speed)
            else:
                state = state.predicted(stamp_i, self._q).updated(z_i, r_i)
            self._states.append(state)
        self.first_stamp = min(self.first_stamp, stamp)
        self._trim()
        return True

    def _trim(self) -> None:
        newest = self._stamps[-1]
        drop = bisect.bisect_left(self._stamps, newest - self.window)
        drop = min(max(drop, len(self._stamps) - MAX_KEPT), len(self._stamps) - 1)
        if drop > 0:
            self._base = self._states[drop - 1]
            del self._stamps[:drop], self._measurements[:drop], self._states[:drop]

    def position(self, stamp: float, moving: bool = True) -> Point:
        """The centroid predicted to ``stamp`` (before the newest state too: then moved back along
        the velocity); ``moving`` False keeps it where it is."""
        state = self._states[-1]
        if not moving:
            return (state.x, state.y)
        dt = stamp - state.stamp
        return (state.x + dt * state.vx, state.y + dt * state.vy)

    def average_speed(self, span: float) -> float | None:
        """The filtered centroid's average speed over the last ``span`` seconds, or None when the
        track is younger than that."""
        newest = self._states[-1]
        if newest.stamp - self.first_stamp < span:
            return None
        k = bisect.bisect_left(self._stamps, newest.stamp - span)
        start = self._states[k - 1] if k else self._base or self._states[0]  # at or before the span's start
        elapsed = newest.stamp - start.stamp
        if elapsed <= 0:
            return None
        return math.hypot(newest.x - start.x, newest.y - start.y) / elapsed
