#!/usr/bin/env python3
"""Matching time against the number of registered cameras (the registry's spatial index).

For each size N: register N cameras one by one (validation + insertion, as a
bulk load without intermediate rebuilds; random 2 x 1.5 m quadrilaterals,
rotated, on a square floor that grows with N so the density stays about 0.5
cameras per square metre), build the index, then time queries of 3 x 3 m
regions of interest, and the same queries by brute force (every polygon
tested) for the smaller sizes.
Also times moves: re-registering 1 % of the cameras, then querying while the
index rebuilds in the background.

Run: ``.venv/bin/python bench/bench_matching.py [N ...]`` (default 1000 10000
100000 1000000; the last needs about 2 GB of memory and a few minutes).
"""

import math
import random
import sys
import time

from drvs.registry import Registry
from drvs.spatial_index import FieldOfViewIndex, interiors_intersect
from drvs.validation import region_geometry


def camera(rng, side):
    cx, cy, a = rng.uniform(0, side), rng.uniform(0, side), rng.uniform(0, math.pi)
    c, s = math.cos(a), math.sin(a)
    return [
        (cx + x * c - y * s, cy + x * s + y * c)
        for x, y in ((-1, -0.75), (1, -0.75), (1.2, 0.75), (-1, 0.75))
    ]


def run(n, queries=2000, seed=1):
    rng = random.Random(seed)
    side = math.sqrt(n / 0.5)
    index = FieldOfViewIndex(background=True, min_rebuild=n + 1)  # bulk load: no rebuilds until the end
    registry = Registry(lease=1e9, index=index)
    started = time.perf_counter()
    for i in range(n):
        registry.register(f'/vs{i}/detect_object_boundary', camera(rng, side))
    register_s = time.perf_counter() - started
    started = time.perf_counter()
    index.rebuild_now()
    build_s = time.perf_counter() - started
    index.min_rebuild = 256
    boxes = []
    for _ in range(queries):
        x, y = rng.uniform(0, side), rng.uniform(0, side)
        boxes.append((x, y, x + 3, y + 3))
    started = time.perf_counter()
    matched = sum(len(registry.match(box)) for box in boxes)
    query_us = (time.perf_counter() - started) / queries * 1e6
    brute_us = None
    if n <= 10000:
        polygons = [(e.service_name, e.polygon) for e in registry.entries()]
        started = time.perf_counter()
        for box in boxes[:200]:
            region = region_geometry(box)
            [name for name, polygon in polygons if interiors_intersect(polygon, region)]
        brute_us = (time.perf_counter() - started) / 200 * 1e6
    # Moves: 1 % of the cameras re-register elsewhere; queries continue during background rebuilds.
    moves = max(1, n // 100)
    started = time.perf_counter()
    for i in rng.sample(range(n), moves):
        registry.register(f'/vs{i}/detect_object_boundary', camera(rng, side))
    move_us = (time.perf_counter() - started) / moves * 1e6
    started = time.perf_counter()
    for box in boxes[:500]:
        registry.match(box)
    query_moving_us = (time.perf_counter() - started) / 500 * 1e6
    index.wait_for_rebuild()
    return {
        'n': n,
        'register_us_each': register_s / n * 1e6,
        'tree_build_s': build_s,
        'query_us': query_us,
        'matches_per_query': matched / queries,
        'brute_force_us': brute_us,
        'move_us_each': move_us,
        'query_during_moves_us': query_moving_us,
        'rebuilds': index.rebuilds,
    }


def main(argv):
    sizes = [int(a) for a in argv] or [1000, 10000, 100000, 1000000]
    print(
        '| N | register (µs each) | tree build (s) | query (µs) | matches/query | brute force (µs) '
        '| move (µs each) | query during moves (µs) |'
    )
    print('|---|---|---|---|---|---|---|---|')
    for n in sizes:
        r = run(n)
        brute = f'{r["brute_force_us"]:.0f}' if r['brute_force_us'] else '-'
        print(
            f'| {n} | {r["register_us_each"]:.1f} | {r["tree_build_s"]:.2f} | {r["query_us"]:.1f} | '
            f'{r["matches_per_query"]:.1f} | {brute} | {r["move_us_each"]:.1f} | '
            f'{r["query_during_moves_us"]:.1f} |',
            flush=True,
        )


if __name__ == '__main__':
    main(sys.argv[1:])
