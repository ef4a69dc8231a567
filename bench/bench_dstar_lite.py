#!/usr/bin/env python3
"""D* Lite: incremental repair vs planning from scratch, on the robot's own grid.

The scenario is the paper's obstacles floor (7 x 5.5 m at 0.05 m: 140 x 110
cells) with random static boxes inflated like the robot's map. A robot walks
its plan; every few cells a 0.3 m "human" moves onto the path a short way
ahead (cells change near the robot, as when DRVS reports a walker). Each time,
the same change is planned two ways:

- repair: ``update_cells`` + ``compute_shortest_path`` on the running planner;
- scratch: a new planner on the changed grid (its search only; building the
  neighbour table is timed apart).

Both must give the same path cost. Reported: vertex expansions and seconds,
and their ratios scratch / repair (how many times cheaper the repair is).

    .venv/bin/python bench/bench_dstar_lite.py [--seeds 5] [--events 20]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from shapely.geometry import box

from drvs.dstar_lite import INF, DStarLite
from drvs.occupancy import CostGrid, GridSpec

SPEC = GridSpec((7.0, 5.5), 0.05)
RADIUS = 0.15 * 2**0.5


def scenario(seed: int):
    rng = np.random.default_rng(seed)
    statics = []
    while len(statics) < 12:
        x, y = rng.uniform(1.2, 5.5), rng.uniform(0.3, 5.2)
        w, h = rng.uniform(0.2, 0.6), rng.uniform(0.2, 1.2)
        statics.append(box(x - w / 2, y - h / 2, x + w / 2, y + h / 2))
    return statics


def run(seed: int, events: int) -> list[dict]:
    statics = scenario(seed)
    grid = CostGrid(SPEC, RADIUS)
    grid.apply(statics)
    start, goal = SPEC.cell_of((0.4, 2.65)), SPEC.cell_of((6.6, 2.65))
    planner = DStarLite(grid.costs, start, goal)
    planner.compute_shortest_path()
    results = []
    for _ in range(events):
        path = planner.path()
        if len(path) < 20:
            break
        start = path[6]
        planner.set_start(start)
        ahead = SPEC.centre_of(path[16])
        human = box(ahead[0] - 0.15, ahead[1] - 0.15, ahead[0] + 0.15, ahead[1] + 0.15)
        changes = grid.apply([*statics, human])

        before = planner.expansions
        t0 = time.perf_counter()
        planner.update_cells(changes)
        planner.compute_shortest_path()
        repair_s = time.perf_counter() - t0
        repair_n = planner.expansions - before

        t0 = time.perf_counter()
        fresh = DStarLite(grid.costs, start, goal)
        build_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        fresh.compute_shortest_path()
        scratch_s = time.perf_counter() - t0

        if abs(fresh.path_cost() - planner.path_cost()) > 1e-6 * max(1.0, fresh.path_cost()):
            raise SystemExit(f'seed {seed}: repair cost {planner.path_cost()} != fresh {fresh.path_cost()}')
        if planner.path_cost() == INF:
            break
        results.append(
            {
                'repair_n': repair_n,
                'scratch_n': fresh.expansions,
                'repair_s': repair_s,
                'scratch_s': scratch_s,
                'build_s': build_s,
                'changed': len(changes),
            }
        )
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--seeds', type=int, default=5)
    parser.add_argument('--events', type=int, default=20)
    args = parser.parse_args()
    rows = [row for seed in range(args.seeds) for row in run(seed, args.events)]
    if not rows:
        raise SystemExit('no events ran')

    def total(key):
        return sum(row[key] for row in rows)

    print(f'{len(rows)} change events on a {SPEC.cols}x{SPEC.rows} grid, {args.seeds} seeds')
    print(f'cells changed per event (median): {statistics.median(r["changed"] for r in rows)}')
    print(
        f'expansions per event (mean): repair {total("repair_n") / len(rows):.0f}, '
        f'scratch {total("scratch_n") / len(rows):.0f}, ratio {total("scratch_n") / total("repair_n"):.1f}x'
    )
    print(
        f'search time per event (mean): repair {1e3 * total("repair_s") / len(rows):.1f} ms, '
        f'scratch {1e3 * total("scratch_s") / len(rows):.1f} ms, '
        f'ratio {total("scratch_s") / total("repair_s"):.1f}x'
    )
    print(f'building a new planner (neighbour table, mean): {1e3 * total("build_s") / len(rows):.1f} ms')


if __name__ == '__main__':
    main()
