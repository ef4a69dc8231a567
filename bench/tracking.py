"""Tracking: the fusion stage's tracks measured against ground truth (issue 25, item 4).

Each world runs once through ``scripts/run_scenario.sh`` with a fused watcher beside it
(``bench/nodes/fused_watcher.py``: fused watches of the people's and the robots' models on the
whole floor, so that every person and robot is tracked whatever the robots themselves ask);
the scenario recorder matches every ``/drvs/objects`` message against ground truth and its
``summary.json`` carries the ``tracking`` block (:mod:`drvs.sim.tracking`; definitions in
docs/running-scenarios.md, "Tracking metrics"). This section puts the blocks side by side
and reports the issue's targets on the worst of the worlds: a table of measurements, not a
timed assertion.

Sizes: ``full`` runs ``worlds/overlap.yaml`` and ``worlds/warehouse.yaml``; ``quick`` the
overlap world only; ``tiny`` runs no scenario and draws the table from synthetic tracks of the
overlap world's people made here (:func:`synthetic_block`), which is not a measurement.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from bench.common import Context, Section, table, target
from drvs.sim.simulation import loop_of, position_on_loop
from drvs.sim.tracking import TrackPeriod, TrackPoint, evaluate
from drvs.sim.world_file import load_world
from drvs.testing.harness import REPO, RosHarness, WaitTimeout

NAME = 'tracking'
TITLE = 'Tracking: fused tracks against ground truth'
OVERLAP = 'worlds/overlap.yaml'
WAREHOUSE = 'worlds/warehouse.yaml'
WATCHER = REPO / 'bench' / 'nodes' / 'fused_watcher.py'
TINY_NOTE = 'tiny: synthetic tracks, no scenario run'
TARGETS = {
    'duplicates': ('tracking_duplicates', max),
    'idf1': ('tracking_idf1', min),
    'switches_per_100_track_seconds': ('tracking_switches_per_100_track_s', max),
    'position_error_p50_tagged_robots': ('tracking_error_p50_tagged_robots_m', max),
    'position_error_p50_people': ('tracking_error_p50_people_m', max),
}
"""The tracking block's target -> (this section's target name, the worst of several worlds)."""
COLUMNS = (
    ('MOTA', 'mota'),
    ('IDF1', 'idf1'),
    ('ID switches', 'switches'),
    ('fragmentations', 'fragmentations'),
    ('duplicates', 'duplicates'),
    ('switches / 100 track-s', 'switches_per_100_track_seconds'),
    ('error mean m', 'position_error_mean'),
    ('error p50 m', 'position_error_p50'),
    ('error p95 m', 'position_error_p95'),
    ('track-s', 'track_seconds'),
)


# -- a run ----------------------------------------------------------------------------------------
def watcher_argv(world: str) -> list[str]:
    """The fused watcher's command for ``world``: the people's and the robots' models, the whole floor."""
    loaded = load_world(REPO / world)
    shared = loaded.robots[0].colour_models
    algorithms = [shared[role] for role in ('human', 'robot') if role in shared]
    region = [0.0, 0.0, *loaded.floor_size]
    return [
        sys.executable,
        str(WATCHER),
        '__name:=fused_watcher',
        f'_algorithms:={json.dumps(algorithms)}',
    ] + [f'_region:={json.dumps(region)}']


def run_world(ctx: Context, world: str, timeout: float) -> dict:
    """Run ``world`` with the fused watcher beside it; what it left: code, summary, wall seconds, log."""
    out = ctx.work_dir / Path(world).stem
    out.mkdir(parents=True, exist_ok=True)
    label = Path(world).stem
    started = time.monotonic()
    summary_path = out / 'summary.json'
    summary_path.unlink(missing_ok=True)
    with RosHarness() as ros:
        argv = ['bash', str(REPO / 'scripts' / 'run_scenario.sh'), str(REPO / world), '--external-master']
        argv += ['--timeout', f'{timeout:g}', '--out', str(out)]
        ctx.progress(f'{label}: starting the scenario and the fused watcher')
        watcher = ros.spawn('fused_watcher', watcher_argv(world))
        runner = ros.spawn('run_scenario', argv)
        deadline = started + timeout + 300
        shown = ''
        while runner.running():
            if time.monotonic() > deadline:
                raise WaitTimeout(f'run_scenario.sh {label} still runs after {timeout + 300:.0f} s')
            line = _status_line(out)
            if line and line != shown:
                ctx.progress(f'{label}: {line} | {time.monotonic() - started:.0f} s')
                shown = line
            time.sleep(1.0)
        code = runner.process.returncode
        log_tail = runner.log(tail=30)
        watcher_log = watcher.log(tail=5)
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else None
    return {
        'world': world,
        'code': code,
        'summary': summary,
        'wall_seconds': round(time.monotonic() - started, 1),
        'log_tail': log_tail,
        'watcher_log': watcher_log,
    }


def _status_line(out: Path) -> str:
    try:
        return (out / 'status.line').read_text().strip()
    except OSError:
        return ''


# -- tiny: synthetic tracks -----------------------------------------------------------------------
def synthetic_block(seconds: float = 20.0, rate: float = 10.0) -> dict:
    """The tracking block of made-up tracks of the overlap world's people: their true walks plus
    3 cm of noise, one id swap half way. NOT A MEASUREMENT: it exercises the metrics and the table."""
    world = load_world(REPO / OVERLAP)
    people = [body for body in world.objects if body.kind == 'human']
    algorithm = world.robots[0].colour_models['human']
    rng = np.random.default_rng(25)
    stamps = np.arange(0.0, seconds, 1.0 / rate)
    truth, periods = {}, []
    for body in people:
        loop = loop_of(body.position, body.waypoints)
        truth[body.name] = [(t, *position_on_loop(loop, body.speed, t, body.loop)) for t in stamps]
    for i, t in enumerate(stamps):
        tracks = []
        for k, body in enumerate(people):
            _, x, y = truth[body.name][i]
            track_id = k + 1 if i < len(stamps) // 2 or k > 1 else 2 - k  # the first two swap half way
            dx, dy = rng.normal(0.0, 0.03, 2)
            tracks.append(TrackPoint(algorithm, track_id, x + dx, y + dy))
        periods.append(TrackPeriod(float(t), tuple(tracks)))
    return evaluate(world, truth, periods)


# -- the section ----------------------------------------------------------------------------------
def run(ctx: Context) -> Section:
    section = Section(NAME, TITLE)
    if ctx.size == 'tiny':
        ctx.progress('tracking: synthetic tracks (tiny: no scenario run)')
        runs = [
            {'world': OVERLAP, 'code': None, 'summary': {'tracking': synthetic_block()}, 'wall_seconds': 0.0}
        ]
    else:
        worlds = ctx.pick(None, [OVERLAP], [OVERLAP, WAREHOUSE])
        runs = [run_world(ctx, world, timeout=ctx.pick(0, 240, 600)) for world in worlds]
    blocks = {run['world']: (run['summary'] or {}).get('tracking') for run in runs}
    section.results['runs'] = [{k: v for k, v in run.items() if k != 'summary'} for run in runs]
    section.results['tracking'] = blocks
    measured = {world: block for world, block in blocks.items() if block and block.get('measured')}
    for key, (name, worst) in TARGETS.items():
        values = [block['targets'][key]['value'] for block in measured.values()]
        values = [value for value in values if value is not None]
        limit = next(iter(measured.values()))['targets'][key]['target'] if measured else _limit(key)
        at_most = worst is max
        if ctx.size == 'tiny':
            section.targets[name] = target(None, limit, at_most, note=TINY_NOTE)
        elif not values:
            section.targets[name] = target(None, limit, at_most, note=_why_not(runs, blocks))
        else:
            section.targets[name] = target(worst(values), limit, at_most)
    section.markdown = markdown(ctx, runs, blocks)
    return section


def _limit(key: str) -> float:
    from drvs.sim.tracking import TARGETS as LIMITS

    return LIMITS[key][0]


def _why_not(runs: list[dict], blocks: dict) -> str:
    """Why no world gave a value: each world's reason, in one line."""
    reasons = []
    for run in runs:
        block = blocks[run['world']]
        if block is None:
            reasons.append(f'{run["world"]}: no summary.json (exit code {run["code"]})')
        elif not block.get('measured'):
            reasons.append(f'{run["world"]}: {block["reason"]}')
        else:
            reasons.append(f'{run["world"]}: no such objects tracked')
    return '; '.join(reasons)


def _cell(value) -> object:
    return '—' if value is None else value


def world_table(block: dict) -> str:
    rows = [
        [row['algorithm'], row['kind'], *(_cell(row[key]) for _, key in COLUMNS)]
        for row in block['algorithms']
    ]
    rows.append(['all', '', *(_cell(block['overall'][key]) for _, key in COLUMNS)])
    return table(['algorithm', 'kind', *(header for header, _ in COLUMNS)], rows)


def markdown(ctx: Context, runs: list[dict], blocks: dict) -> str:
    if ctx.size == 'tiny':
        text = (
            '**Tiny size: no scenario ran; the table below is computed from synthetic tracks of the '
            "overlap world's people (their true walks, 3 cm of noise, one id swap), not a measurement.**\n\n"
        )
    else:
        text = (
            'Each world run by `scripts/run_scenario.sh` with `bench/nodes/fused_watcher.py` beside it '
            "(fused watches of the people's and the robots' models on the whole floor); the scenario "
            "recorder's `tracking` block of `summary.json`, every `/drvs/objects` message matched against "
            'ground truth (docs/running-scenarios.md, "Tracking metrics"). The targets take the worst '
            'world.\n\n'
        )
    for run in runs:
        block = blocks[run['world']]
        wall = f', {run["wall_seconds"]:.0f} s on the wall clock' if ctx.size != 'tiny' else ''
        text += f'### `{run["world"]}`\n\n'
        if block is None:
            said = [
                line for line in run.get('log_tail', '').splitlines() if line.startswith('run_scenario: ')
            ]
            text += (
                f'No summary.json (exit code {run["code"]}):\n\n```\n' + '\n'.join(said[-5:]) + '\n```\n\n'
            )
            continue
        if not block.get('measured'):
            text += f'Not measured: {block["reason"]}{wall}.\n\n'
            continue
        reached = (run['summary'] or {}).get('reached')
        how = [] if run['code'] is None else [f'exit code {run["code"]}']
        if reached is not None:
            how.append('every robot arrived' if reached else 'NOT every robot arrived')
        how_text = f' ({", ".join(how)}{wall})' if how else ''
        text += (
            f'{block["periods"]} periods of `/drvs/objects` over {block["span"]:.1f} s of ROS time, matched '
            f'within {block["gate"]} m{how_text}.\n\n'
        )
        text += world_table(block) + '\n'
        if block.get('not_measured'):
            text += 'Not measured: ' + '; '.join(f'`{a}`: {why}' for a, why in block['not_measured'].items())
            text += '\n\n'
    text += f'Again: `.venv/bin/python -m bench.run --only {NAME} --size quick` (overlap world only).\n'
    return text
