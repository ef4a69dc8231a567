"""The fusion tracker's rate: frames a second for 20 people walking, 4 cameras at 10 Hz seeing all.

Standalone (not a section of ``bench.run``): ``python -m bench.tracker_rate``. Prints the
frames fused a second (each frame: 20 outlines of one camera), and the cost of ``tracks()``
right after a round of 4 frames. docs/fusion-tracking.md ("Cost") quotes it.
"""

from __future__ import annotations

import math
import random
import time

from drvs.server.tracker import Observation, Tracker

PEOPLE = 20
CAMERAS = 4
SECONDS = 30


def square(x: float, y: float, size: float = 0.5) -> tuple[tuple[float, float], ...]:
    h = size / 2
    return ((x - h, y - h), (x + h, y - h), (x + h, y + h), (x - h, y + h))


def main() -> None:
    rng = random.Random(1)
    people = [(rng.uniform(0, 20), rng.uniform(0, 20), rng.uniform(0, 2 * math.pi)) for _ in range(PEOPLE)]
    offsets = [(rng.gauss(0, 0.03), rng.gauss(0, 0.03)) for _ in range(CAMERAS)]  # pose errors
    rounds = []
    for k in range(SECONDS * 10):
        frames = []
        for i, (ox, oy) in enumerate(offsets):
            t = k / 10 + i * 0.025
            outlines = [
                Observation(square(x + math.cos(a) * t + ox + rng.gauss(0, 0.02), y + math.sin(a) * t + oy))
                for x, y, a in people
            ]
            frames.append((f'cam{i}', t, outlines))
        rounds.append(frames)
    tracker = Tracker()
    fusing = querying = 0.0
    for frames in rounds:
        start = time.perf_counter()
        for camera, stamp, outlines in frames:
            tracker.frame(camera, stamp, outlines)
        middle = time.perf_counter()
        tracker.tracks(frames[-1][1])
        fusing += middle - start
        querying += time.perf_counter() - middle
    count = len(rounds) * CAMERAS
    print(
        f'{count / fusing:.0f} frames/s ({1e3 * fusing / count:.2f} ms a frame of {PEOPLE} outlines, '
        f'{CAMERAS} cameras); tracks() after each round: {1e3 * querying / len(rounds):.2f} ms; '
        f'{len(tracker)} tracks, ids issued: {max(v.track_id for v in tracker.tracks(SECONDS))}'
    )


if __name__ == '__main__':
    main()
