"""Registry: match, registration and move time from 10 to 1,000,000 registered fields of view.

What is measured, for each size N, through the server's own path
(:meth:`drvs.server.registry.Registry.register` with its validation, and
:meth:`~drvs.server.registry.Registry.match` with the region's) on a registry built as
the server builds it (its default index):

- **registration**: N cameras registered one by one, each call timed. The
  cameras are random 2 x 1.5 m quadrilaterals, rotated, on a square floor that
  grows with N so that the density stays 0.5 cameras per square metre (a
  ceiling of overhead cameras); their polygons are made before the clock runs;
- **static match**: 3 x 3 m regions of interest at random places, each call
  timed, in two windows (before and after the moving ones, pooled, so that a
  drift of the shared machine's speed weighs on both sides of the ratio);
- **move**: re-registration of a camera with a new polygon somewhere else;
- **match while 1 % of the cameras move per second**: moves are interleaved
  with the matches on the wall clock (before each match, every move due by now
  at N/100 per second is made; only the match is timed), so a match pays for
  what the moves did to the index and for nothing else. The same with a thread
  making the moves is reported beside it: there a match also waits whenever
  the mover holds CPython's GIL, a cost of the interpreter, not of the index
  (and the mover, sharing the GIL with a loop that never waits, makes fewer
  moves than due at 1M: the report says how many);
- **the paper's linear scan** (Algorithm 1: every registered polygon tested
  with shapely, by the same rule, :func:`drvs.server.spatial_index.interiors_intersect`)
  at each size until one match takes over 1 s; larger sizes are not scanned
  (nothing is extrapolated). Its answers are checked against the index's.

After the registrations a full garbage collection is made (and timed) so that
none falls into a timed window: at 1M one takes seconds. The collector's time
during the registrations is measured too: the mean includes it, the p50 not.

The anchor of the match figures is the linear scan of the same run, and the
static match is the anchor of the moving one. At the largest size the match and
the registration are broken down (region check / index / the registry's own
filter; validation / the rest), and profiled with cProfile if over their target.

Run alone: ``.venv/bin/python -m bench.run --only registry`` (``--size quick``).
"""

from __future__ import annotations

import cProfile
import gc
import io
import math
import pstats
import random
import threading
import time

from bench.common import Context, Section, figure, save, spread, table, target
from drvs.common.validation import field_of_view_polygon, region_geometry, region_of_interest
from drvs.server.registry import Registry
from drvs.server.spatial_index import interiors_intersect

NAME = 'registry'
TITLE = 'Registry: match, registration and moves, 10 to 1M fields of view'

DENSITY = 0.5  # cameras per square metre
REGION = 3.0  # side of a region of interest, metres
MOVING_SHARE = 0.01  # of the cameras move every second
LINEAR_LIMIT_S = 1.0  # the linear scan is measured up to the first size where a match takes longer
TARGET_US = 50.0


def camera(rng: random.Random, side: float) -> list[tuple[float, float]]:
    """A 2 x 1.5 m field of view (slightly trapezoidal), rotated, somewhere on a side x side floor."""
    cx, cy, a = rng.uniform(0, side), rng.uniform(0, side), rng.uniform(0, math.pi)
    c, s = math.cos(a), math.sin(a)
    corners = ((-1, -0.75), (1, -0.75), (1.2, 0.75), (-1, 0.75))
    return [(cx + x * c - y * s, cy + x * s + y * c) for x, y in corners]


def regions(rng: random.Random, side: float, count: int) -> list[tuple[float, float, float, float]]:
    """``count`` regions of interest, REGION metres square, anywhere on the floor."""
    boxes = []
    for _ in range(count):
        x, y = rng.uniform(0, side), rng.uniform(0, side)
        boxes.append((x, y, x + REGION, y + REGION))
    return boxes


def timed(function, arguments) -> list[float]:
    """µs per call of ``function(argument)``, for each argument."""
    clock, times = time.perf_counter_ns, []
    for argument in arguments:
        started = clock()
        function(argument)
        times.append((clock() - started) / 1e3)
    return times


class Mover:
    """Moves random cameras of ``registry`` at ``rate`` per second of wall clock; times each move."""

    def __init__(self, registry: Registry, names: list[str], rate: float, rng: random.Random, side: float):
        self.registry, self.names, self.rate, self.rng, self.side = registry, names, rate, rng, side
        self.times: list[float] = []  # µs per move
        self.started = time.perf_counter()

    def catch_up(self) -> None:
        """Make every move due by now."""
        due = int((time.perf_counter() - self.started) * self.rate)
        clock, rng = time.perf_counter_ns, self.rng
        while len(self.times) < due:
            name, polygon = rng.choice(self.names), camera(rng, self.side)
            started = clock()
            self.registry.register(name, polygon)
            self.times.append((clock() - started) / 1e3)


def matches_for(registry, names, boxes, rng, side, seconds: float, moves: str) -> dict:
    """Match times for ``seconds``: ``moves`` 'none', or 1 % of the cameras per second 'interleaved'
    with the matches or made by a 'thread'."""
    mover = Mover(registry, names, 0 if moves == 'none' else len(names) * MOVING_SHARE, rng, side)
    threaded = moves == 'thread'
    stop = threading.Event()
    thread = None
    if threaded:

        def run() -> None:  # a batch every 5 ms: the rate holds, and the thread sleeps in between
            while not stop.wait(0.005):
                mover.catch_up()

        thread = threading.Thread(target=run, name='bench-mover', daemon=True)
        thread.start()
    clock, times, found = time.perf_counter_ns, [], 0
    deadline = time.perf_counter() + seconds
    try:
        while time.perf_counter() < deadline or len(times) < 20:
            if not threaded:
                mover.catch_up()
            box = boxes[len(times) % len(boxes)]
            started = clock()
            found += len(registry.match(box))
            times.append((clock() - started) / 1e3)
    finally:
        stop.set()
        if thread is not None:
            thread.join()
    return {
        'times': times,
        'moves': len(mover.times),
        'moves_per_s': len(mover.times) / (time.perf_counter() - mover.started),
        'matches_per_query': found / len(times),
    }


class GcTime:
    """Seconds spent in CPython's cyclic garbage collector while in the ``with`` block."""

    def __init__(self):
        self.seconds, self._started = 0.0, 0.0

    def _callback(self, phase: str, info: dict) -> None:
        if phase == 'start':
            self._started = time.perf_counter()
        else:
            self.seconds += time.perf_counter() - self._started

    def __enter__(self):
        gc.callbacks.append(self._callback)
        return self

    def __exit__(self, *exc) -> None:
        gc.callbacks.remove(self._callback)


def linear_scan(pairs, boxes, budget_s: float) -> tuple[list[float], list[list[str]]]:
    """The paper's Algorithm 1, every polygon tested: µs per match and the answers (within a budget)."""
    times, answers, spent = [], [], 0.0
    for box in boxes:
        started = time.perf_counter()
        region = region_geometry(box)
        answers.append(sorted(name for name, polygon in pairs if interiors_intersect(polygon, region)))
        elapsed = time.perf_counter() - started
        times.append(elapsed * 1e6)
        spent += elapsed
        if spent > budget_s:
            break
    return times, answers


def profile_top(function, lines: int = 10) -> str:
    """cProfile of ``function()``: the top lines by internal time."""
    profiler = cProfile.Profile()
    profiler.runcall(function)
    out = io.StringIO()
    pstats.Stats(profiler, stream=out).sort_stats('tottime').print_stats(lines)
    text = out.getvalue()
    start = text.find('   ncalls')
    return (text[start:] if start >= 0 else text).rstrip().replace(str(__file__.rsplit('/bench/', 1)[0]), '')


def measure(ctx: Context, n: int, rng: random.Random, scan_linear: bool, largest: bool) -> dict:
    """Everything at one size; at the largest, also the breakdowns and profiles."""
    side = math.sqrt(n / DENSITY)
    result: dict = {'n': n, 'floor_side_m': side}
    started = time.perf_counter()
    names = [f'/vs{i}/detect_object_boundary' for i in range(n)]
    fields = [camera(rng, side) for _ in range(n)]
    result['generate_s'] = time.perf_counter() - started

    ctx.progress(f'registry: register {n:,}')
    registry = Registry(lease=1e9)  # as the server builds it; leases never run out here
    clock, times = time.perf_counter_ns, [0.0] * n
    collecting = GcTime()
    started = time.perf_counter()
    with collecting:
        for i in range(n):
            begun = clock()
            registry.register(names[i], fields[i])
            times[i] = (clock() - begun) / 1e3
    result['register_total_s'] = time.perf_counter() - started
    result['register_gc_s'] = collecting.seconds
    # A full collection now, so that none falls into a timed window below (one takes seconds at 1M).
    started = time.perf_counter()
    gc.collect()
    result['gc_collect_s'] = time.perf_counter() - started
    result['register_us'] = spread(times)
    sample = fields[: ctx.pick(200, 2000, 5000)]
    del times, fields

    ctx.progress(f'registry: move among {n:,}')
    moved = [(name, camera(rng, side)) for name in rng.sample(names, min(n, ctx.pick(200, 2000, 5000)))]
    result['move_us'] = spread(timed(lambda move: registry.register(*move), moved))

    # Static matches in two windows, before and after the moving ones, pooled: a drift of the
    # machine's speed during the run weighs on both sides of the ratio alike.
    boxes = regions(rng, side, ctx.pick(200, 2000, 5000))
    seconds, rate = ctx.pick(0.15, 0.5, 1.0), n * MOVING_SHARE
    timed(registry.match, boxes[:200])  # warm-up
    ctx.progress(f'registry: match among {n:,}')
    static = matches_for(registry, names, boxes, rng, side, seconds, 'none')
    ctx.progress(f'registry: match among {n:,} while {rate:,.0f} move per second')
    moving = matches_for(registry, names, boxes, rng, side, 2 * seconds, 'interleaved')
    ctx.progress(f'registry: match among {n:,} while a thread moves {rate:,.0f} per second')
    thread = matches_for(registry, names, boxes, rng, side, 2 * seconds, 'thread')
    ctx.progress(f'registry: match among {n:,}, again')
    again = matches_for(registry, names, boxes, rng, side, seconds, 'none')
    result['match_us'] = spread(static['times'] + again['times'])
    result['matches_per_query'] = (static['matches_per_query'] + again['matches_per_query']) / 2
    for key, run in (('match_moving_us', moving), ('match_moving_thread_us', thread)):
        result[key] = {**spread(run.pop('times')), **run}

    if scan_linear:
        ctx.progress(f'registry: linear scan of {n:,}')
        pairs = [(entry.service_name, entry.polygon) for entry in registry.entries()]
        few = boxes[: ctx.pick(5, 30, 50)]
        linear_times, answers = linear_scan(pairs, few, budget_s=ctx.pick(0.3, 1.0, 10.0))
        result['linear_us'] = spread(linear_times)
        result['linear_agrees'] = answers == [registry.match(box) for box in few[: len(answers)]]
        del pairs

    if largest:
        ctx.progress(f'registry: breakdown at {n:,}')
        index = registry._index
        result['breakdown_us'] = {
            'match': spread(timed(registry.match, boxes))['p50'],
            'region_check': spread(timed(region_of_interest, boxes))['p50'],
            'index': spread(timed(index.query_box, boxes))['p50'],
            'register': result['register_us']['p50'],
            'validation': spread(timed(field_of_view_polygon, sample))['p50'],
        }
        result['profiles'] = {}
        if result['match_us']['p50'] > TARGET_US:
            result['profiles']['match'] = profile_top(lambda: [registry.match(box) for box in boxes[:500]])
        if result['register_us']['p50'] > TARGET_US:
            again = [(name, camera(rng, side)) for name in rng.sample(names, min(n, 2000))]
            result['profiles']['registration (moves)'] = profile_top(
                lambda: [registry.register(*move) for move in again]
            )
    return result


def run(ctx: Context) -> Section:
    sizes = ctx.pick([10, 1000], [10, 1000, 100_000], [10, 1000, 100_000, 1_000_000])
    rng = random.Random(16)
    measured, scan_linear = [], True
    for n in sizes:
        gc.collect()
        result = measure(ctx, n, rng, scan_linear, largest=n == sizes[-1])
        measured.append(result)
        if 'linear_us' in result and result['linear_us']['p50'] > LINEAR_LIMIT_S * 1e6:
            scan_linear = False  # the first size over 1 s per match: no larger size is scanned
        gc.collect()
    largest = measured[-1]
    return Section(
        NAME,
        TITLE,
        results={'sizes': measured},
        targets=targets(ctx, largest),
        markdown=report(ctx, measured),
        plots=[plot(ctx, measured)],
    )


def targets(ctx: Context, largest: dict) -> dict:
    n = largest['n']
    at = '' if n == 1_000_000 else f'at {n:,} ({ctx.size} size; 1M only in make bench); '
    ratio = largest['match_moving_us']['p50'] / largest['match_us']['p50']
    return {
        'match_1m_p50_us': target(largest['match_us']['p50'], TARGET_US, note=at + 'p50 of Registry.match'),
        'match_1m_moving_over_static': target(ratio, 2, note=at + 'p50s; moves interleaved with the matches'),
        'register_1m_us': target(
            largest['register_us']['p50'], TARGET_US, note=at + 'p50 of Registry.register'
        ),
    }


def report(ctx: Context, measured: list[dict]) -> str:
    rows = []
    for r in measured:
        linear = r.get('linear_us', {}).get('p50')
        rows.append(
            [
                f'{r["n"]:,}',
                r['register_us']['p50'],
                r['register_us']['mean'],
                r['move_us']['p50'],
                r['match_us']['p50'],
                r['match_us']['p99'],
                r['match_moving_us']['p50'],
                r['match_moving_thread_us']['p50'],
                '-' if linear is None else linear,
                '-' if linear is None else f'{linear / r["match_us"]["p50"]:,.0f}',
                round(r['matches_per_query'], 1),
            ]
        )
    header = [
        'N',
        'register p50',
        'register mean',
        'move p50',
        'match p50',
        'match p99',
        'match, 1 %/s moving, p50',
        'match, mover thread, p50',
        'linear scan p50',
        'linear / match',
        'matches per query',
    ]
    largest = measured[-1]
    n, match = largest['n'], largest['match_us']['p50']
    moving = largest['match_moving_us']['p50']
    linear = (
        f'{largest["linear_us"]["p50"]:,.0f} µs | ratio {largest["linear_us"]["p50"] / match:,.0f}'
        if 'linear_us' in largest
        else 'not measured (over 1 s at a smaller size)'
    )
    parts = largest['breakdown_us']
    text = [
        'Times in µs per call.\n',
        table(header, rows),
        f'\nAt N = {n:,}: match p50 {match:.1f} µs | the paper\'s linear scan {linear}. '
        f'While 1 % of the cameras move per second {moving:.1f} µs | static {match:.1f} µs | '
        f'ratio {moving / match:.2f} ({largest["match_moving_us"]["moves_per_s"]:,.0f} moves per second '
        f'made, {n * MOVING_SHARE:,.0f} due; the mover thread made '
        f'{largest["match_moving_thread_us"]["moves_per_s"]:,.0f}). '
        f'Registration p50 {largest["register_us"]["p50"]:.1f} µs '
        f'(mean {largest["register_us"]["mean"]:.1f} µs, '
        f'{largest["register_total_s"]:.1f} s for all {n:,}, of which {largest["register_gc_s"]:.1f} s in '
        f"CPython's garbage collector, which the mean includes and the p50 does not; making their "
        f'polygons took {largest["generate_s"]:.1f} s more).\n',
        f'\nBreakdown at N = {n:,} (p50s, µs): match {parts["match"]:.1f} = region check '
        f'{parts["region_check"]:.1f} + index {parts["index"]:.1f} + leases, algorithms and sorting; '
        f'registration {parts["register"]:.1f} = validation (shapely polygon, validity, area) '
        f'{parts["validation"]:.1f} + index insert and the entry.\n',
        '\nThe index is a grid of cells (a level per size of field of view), with the exact test in Python '
        'where it is sure (convex polygons: separating axes) and GEOS where it is not: no rebuild, so moves '
        'cost a match nothing. "1 %/s moving": the moves due are made between matches, only the match '
        'is timed; "mover thread": a thread makes them (as many as it gets the GIL for), and a match also '
        'waits for the GIL. '
        "The linear scan tests every polygon with shapely (the paper's Algorithm 1); "
        f'its answers agree with the index\'s: {all(r.get("linear_agrees", True) for r in measured)}.\n',
    ]
    for what, profile in largest['profiles'].items():
        text.append(
            f'\nProfile of {what} at N = {n:,} (cProfile, by internal time):\n\n```\n{profile}\n```\n'
        )
    text.append(
        '\nReproduce: `make bench` (to 1M), `.venv/bin/python -m bench.run --only registry --size quick`.\n'
    )
    return ''.join(text)


def plot(ctx: Context, measured: list[dict]) -> str:
    fig, axes, file_name = figure(ctx, 'registry-match')
    ns = [r['n'] for r in measured]
    scanned = [r for r in measured if 'linear_us' in r]
    axes.plot(
        [r['n'] for r in scanned], [r['linear_us']['p50'] for r in scanned], 'v-', label='linear scan (paper)'
    )
    axes.plot(ns, [r['match_us']['p50'] for r in measured], 'o-', label='match, static')
    axes.plot(ns, [r['match_moving_us']['p50'] for r in measured], 's--', label='match, 1 %/s moving')
    axes.plot(ns, [r['match_moving_thread_us']['p50'] for r in measured], 'x:', label='match, mover thread')
    axes.plot(ns, [r['register_us']['p50'] for r in measured], 'd-.', label='registration')
    axes.axhline(TARGET_US, color='grey', linewidth=0.8, label=f'target {TARGET_US:.0f} µs')
    axes.set_xscale('log')
    axes.set_yscale('log')
    axes.set_xlabel('registered fields of view')
    axes.set_ylabel('p50 per call (µs)')
    axes.set_title('Registry: index vs linear scan, static vs moving')
    axes.legend(fontsize=8)
    axes.grid(True, which='both', linewidth=0.3)
    return save(ctx, fig, file_name)
