"""A track's constant-velocity filter, with late measurements put in their place."""

import random

import pytest

from drvs.server.track_motion import Motion, MotionNoise

NOISE = MotionNoise(acceleration=1.0, initial_speed=1.5)
R = 0.05**2


def measurements(count=20, seed=1, sigma=0.01):
    """(stamp, centroid) at 10 Hz of an object moving at (1, -0.5) m/s, ``sigma`` metres of noise."""
    noise = random.Random(seed)
    return [
        (0.1 * i, (0.1 * i + noise.gauss(0, sigma), -0.05 * i + noise.gauss(0, sigma))) for i in range(count)
    ]


def run(order, window=1.0):
    first_stamp, first_z = order[0]
    motion = Motion(NOISE, window, first_stamp, first_z, R)
    accepted = [motion.update(stamp, z, R) for stamp, z in order[1:]]
    return motion, accepted


def test_late_measurements_give_the_same_state_as_in_order():
    in_order, _ = run(measurements())
    shuffled = measurements()
    random.Random(3).shuffle(shuffled)
    late, accepted = run(shuffled, window=5.0)
    assert all(accepted)
    assert late.state == pytest.approx(in_order.state)
    assert late.first_stamp == 0.0


def test_the_velocity_follows_a_constant_velocity():
    motion, _ = run(measurements(count=11))
    assert (motion.state.vx, motion.state.vy) == pytest.approx((1.0, -0.5), abs=0.1)
    assert motion.position(2.0) == pytest.approx((2.0, -1.0), abs=0.1)
    assert motion.position(2.0, moving=False) == (motion.state.x, motion.state.y)


def test_a_measurement_older_than_the_window_kept_is_refused():
    motion, _ = run(measurements(count=30), window=1.0)
    before = motion.state
    assert not motion.update(0.5, (9.0, 9.0), R)
    assert motion.state == before
    assert motion.update(2.5, (2.5, -1.25), R)  # within the window: accepted


def test_average_speed_needs_a_track_as_old_as_the_span():
    motion, _ = run(measurements(count=5))
    assert motion.average_speed(1.0) is None
    motion, _ = run(measurements(count=25), window=1.5)
    assert motion.average_speed(1.0) == pytest.approx(1.118, abs=0.15)
