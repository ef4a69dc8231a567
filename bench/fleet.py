"""Fleet: the robots' traffic with standing requests (watches) against the paper's polling.

The same world runs twice through ``scripts/run_scenario.sh``, once with every robot on
``--requests watch`` and once on ``--requests poll``; each run's ``summary.json`` gives,
per robot, the calls it sent to the server (``requests``, of them ``watch_calls``), the
callbacks it received and their serialized bytes, and its arrival; the server's
counters give the calls it received. Counting in the nodes is exact (each counts its own
service calls), so no capture is needed; the wire-level bytes of a callback are the
``wire`` section's.

What the target counts: *server calls* (one-shot requests plus WatchObjectBoundary
calls, as drvs_server counted them, the final cancels included) rather than every robot
message. Callbacks are the answers, the outlines the robot needs, and in both modes
most of them report what moved since the last period (the robot itself, the other
robots, the people): watches remove the questions, not the answers. The total of robot
messages (server calls + callbacks) and the callback bytes are reported beside it.

Sizes: ``full`` runs ``worlds/warehouse.yaml`` (six robots, 35 cameras, about three
minutes a run on two cores); ``quick`` runs ``worlds/crossing.yaml`` and takes the watch
run from the ``link`` section when it ran the same world with the same options in this
``make bench`` (its folder next to this section's); ``tiny`` runs no scenario (far over
its budget) and draws the table and the plot from a canned summary, which is not a
measurement. With network namespaces (root) the runs are across the fleet issue's
hosts with the first robot on a 2 Mbit/s link (``--hosts --robot-link 2mbit``, as the
``link`` section); without them on this host.
"""

from __future__ import annotations

import json
import os
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

from bench.common import Context, Section, figure, save, table, target
from drvs.sim.world_file import load_world
from drvs.testing.harness import REPO, RosHarness, WaitTimeout
from drvs.testing.netns import unavailable

NAME = 'fleet'
TITLE = 'Fleet: robot traffic with watches against polling'
CROSSING = 'worlds/crossing.yaml'
WAREHOUSE = 'worlds/warehouse.yaml'
SCRIPTS = REPO / 'scripts'
ROBOT_LINK = '2mbit'
MODES = ('watch', 'poll')
TARGET = 10.0  # watches: at least ten times fewer robot messages (server calls) than polling
TINY_NOTE = 'tiny: no scenario run'

# A canned pair of summaries for the tiny size (CI smoke): the shape of summary.json with
# round made-up numbers. NOT A MEASUREMENT: it only exercises the table and plot code.
FIXTURE_NOT_A_MEASUREMENT = {
    mode: {
        'reached': True,
        'elapsed': 20.0,
        'wall_seconds': 20.0,
        'real_time_factor': 1.0,
        'robots': [
            {
                'name': name,
                'reached': True,
                'arrival': 20.0,
                'requests': requests,
                'watch_calls': requests if mode == 'watch' else 0,
                'callbacks': callbacks,
                'callback_bytes': callbacks * 200,
            }
            for name, requests, callbacks in (
                ('robot1', 20 if mode == 'watch' else 300, 300 if mode == 'watch' else 500),
                ('robot2', 20 if mode == 'watch' else 300, 300 if mode == 'watch' else 500),
            )
        ],
        'server': {
            'requests': 0 if mode == 'watch' else 600,
            'watch_requests': 50 if mode == 'watch' else 0,
        },
    }
    for mode in MODES
}


# -- running a scenario --------------------------------------------------------------------------
@dataclass
class ScenarioRun:
    """One ``run_scenario.sh`` run: how it was started, how it ended, what it left."""

    world: str  # relative to the repository
    requests: str
    options: list[str]
    code: int | None  # run_scenario.sh's exit code (0: every robot arrived)
    summary: dict | None  # its summary.json; None if it wrote none
    wall_seconds: float
    out: Path
    # With --robot-link: (monotonic s, rx bytes, tx bytes) of the first robot's eth0, sampled.
    link_samples: list[tuple[float, int, int]] = field(default_factory=list)
    log_tail: str = ''
    failed_attempts: list[dict] = field(default_factory=list)  # earlier runs in which a robot did not arrive

    def meta(self) -> dict:
        return {
            'world': self.world,
            'requests': self.requests,
            'options': self.options,
            'code': self.code,
            'wall_seconds': self.wall_seconds,
            'link_samples': self.link_samples,
            'log_tail': self.log_tail,
            'failed_attempts': self.failed_attempts,
        }

    def save(self) -> None:
        (self.out / 'run.json').write_text(json.dumps(self.meta()))

    @classmethod
    def load(cls, out: Path) -> ScenarioRun | None:
        """A run saved in ``out`` (run.json and summary.json), or None if there is none."""
        try:
            meta = json.loads((out / 'run.json').read_text())
        except (OSError, ValueError):
            return None
        summary_path = out / 'summary.json'
        summary = json.loads(summary_path.read_text()) if summary_path.exists() else None
        samples = [tuple(sample) for sample in meta.pop('link_samples')]
        return cls(summary=summary, out=out, link_samples=samples, **meta)


def scenario_options() -> list[str]:
    """``--hosts --robot-link 2mbit`` where network namespaces can be made here, else none."""
    return [] if unavailable() else ['--hosts', '--robot-link', ROBOT_LINK]


def link_counters(namespace: str) -> tuple[int, int] | None:
    """(rx, tx) bytes of eth0 in ``namespace``; None if it does not exist (yet, or any more)."""
    shown = subprocess.run(
        ['ip', '-n', namespace, '-j', '-s', 'link', 'show', 'dev', 'eth0'],
        capture_output=True,
        text=True,
        timeout=10,
    )
    if shown.returncode != 0:
        return None
    stats = json.loads(shown.stdout)[0]['stats64']
    return stats['rx']['bytes'], stats['tx']['bytes']


def run_scenario(ctx: Context, world: str, requests: str, options: list[str], timeout: float) -> ScenarioRun:
    """Run ``scripts/run_scenario.sh world --requests requests options`` to its end.

    The out folder is ``ctx.work_dir/<world>-<requests>``. Progress comes from the
    script's status line; with ``--robot-link`` the first robot's link counters are
    sampled every half second (its host is namespace ``drvs<script pid>-<robot>``).
    Everything the script started is stopped, also when this raises.
    """
    out = ctx.work_dir / f'{Path(world).stem}-{requests}'
    out.mkdir(parents=True, exist_ok=True)
    label = f'{Path(world).stem} {requests}'
    first_robot = load_world(REPO / world).robots[0].name
    try:
        with RosHarness() as ros:
            master = [] if '--hosts' in options else ['--external-master']
            argv = ['bash', str(SCRIPTS / 'run_scenario.sh'), str(REPO / world), '--requests', requests]
            argv += [*master, *options, '--timeout', f'{timeout:g}', '--out', str(out)]
            ctx.progress(f'{label}: starting the scenario')
            started = time.monotonic()
            (out / 'status.line').unlink(missing_ok=True)  # an earlier attempt's
            runner = ros.spawn('run_scenario', argv)
            samples: list[tuple[float, int, int]] = []
            overrun = ''
            try:
                _follow(ctx, runner, out, label, f'drvs{runner.pid}-{first_robot}', options, timeout, samples)
            except WaitTimeout as error:  # reported as a failed run, which run_to_arrival repeats
                overrun = 'run_scenario: ' + str(error).splitlines()[0]
            finally:
                if runner.running():
                    try:
                        runner.interrupt(timeout=60)  # Ctrl-C: the script stops its nodes and hosts
                    except WaitTimeout:
                        pass  # ros.close() signals the group harder
                log_tail = runner.log(tail=30) + (f'\n{overrun}' if overrun else '')
                code = runner.process.returncode
    finally:
        if (out / 'pids').exists() or (out / 'hosts').exists():  # a run that could not clean up
            subprocess.run(['bash', str(SCRIPTS / 'stop_scenario.sh'), '--quiet', str(out)], check=False)
    summary_path = out / 'summary.json'
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else None
    run = ScenarioRun(
        world,
        requests,
        list(options),
        code,
        summary,
        round(time.monotonic() - started, 1),
        out,
        samples,
        log_tail,
    )
    run.save()
    return run


def _follow(
    ctx: Context,
    runner,
    out: Path,
    label: str,
    namespace: str,
    options: list[str],
    timeout: float,
    samples: list,
) -> None:
    """Until the script ends, show its status line and, with ``--robot-link``, append the limited
    robot's link counters to ``samples`` (s since the start, rx, tx).

    :raises WaitTimeout: if the script still runs long after its own timeout (which counts
        from the robots' start: its start-up, up to a minute and more on a loaded machine,
        and its stop come on top).
    """
    shown, shown_at = '', 0.0
    started = time.monotonic()
    deadline = started + timeout + 300
    while runner.running():
        now = time.monotonic()
        if now > deadline:
            raise WaitTimeout(f'run_scenario.sh {label} still runs after {now - started:.0f} s')
        if '--robot-link' in options:
            counters = link_counters(namespace)
            if counters:
                samples.append((round(now - started, 3), *counters))
        line = _status_line(out)
        if line and (line != shown or now - shown_at > 5):
            ctx.progress(f'{label}: {line} | {now - started:.0f} s')
            shown, shown_at = line, now
        time.sleep(0.5)


def run_to_arrival(
    ctx: Context, world: str, requests: str, options: list[str], timeout: float, attempts: int = 2
) -> ScenarioRun:
    """:func:`run_scenario`, again (up to ``attempts`` runs) while a robot does not arrive.

    On this shared two-core machine a run can fail because the machine is overloaded (a
    robot that hears no fix of itself for 5 s gives up); each failed attempt is kept in
    the last run's ``failed_attempts`` and reported.
    """
    failed = []
    for attempt in range(1, attempts + 1):
        run = run_scenario(ctx, world, requests, options, timeout)
        if run.code == 0 or attempt == attempts:
            break
        failed.append(failure(run))
        ctx.progress(f'{Path(world).stem} {requests}: attempt {attempt} failed ({failed[-1]["why"]}); again')
    run.failed_attempts = failed
    run.save()
    return run


def failure(run: ScenarioRun) -> dict:
    """What went wrong in a run that did not end with every robot arrived, in one line."""
    if run.summary is None:
        said = [line for line in run.log_tail.splitlines() if line.startswith('run_scenario: ')]
        why = f'exit code {run.code}, no summary.json' + (f': {said[-1]}' if said else '')
    else:
        why = (
            '; '.join(
                f'{row["name"]} {row["state"]}' + (f': {row["reason"]}' if row.get('reason') else '')
                for row in run.summary['robots']
                if not row['reached']
            )
            or f'exit code {run.code}'
        )
    load = [round(value, 1) for value in os.getloadavg()]
    return {'code': run.code, 'wall_seconds': run.wall_seconds, 'why': why, 'load_average': load}


def _status_line(out: Path) -> str:
    try:
        return (out / 'status.line').read_text().strip()
    except OSError:
        return ''


def shared_watch_run(ctx: Context, world: str, options: list[str]) -> ScenarioRun | None:
    """The ``link`` section's watch run of this ``make bench``, if it ran ``world`` with ``options``."""
    run = ScenarioRun.load(ctx.work_dir.parent / 'link' / f'{Path(world).stem}-watch')
    if run is None or run.world != world or run.options != options or run.code != 0:
        return None
    return run


# -- the comparison ------------------------------------------------------------------------------
def totals(summary: dict) -> dict:
    """A run's traffic: server calls (the server's count), callbacks and their bytes (the robots')."""
    rows = summary['robots']
    server = summary['server']
    server_calls = server['requests'] + server['watch_requests']
    callbacks = sum(row['callbacks'] for row in rows)
    robot_seconds = sum(row.get('elapsed') or row['arrival'] or 0.0 for row in rows)
    return {
        'reached': bool(summary['reached']),
        'robots': len(rows),
        'arrived': sum(bool(row['reached']) for row in rows),
        'elapsed': summary['elapsed'],
        'server_calls': server_calls,
        'robot_requests': sum(row['requests'] for row in rows),
        'watch_calls': sum(row['watch_calls'] for row in rows),
        'callbacks': callbacks,
        'callback_bytes': sum(row['callback_bytes'] for row in rows),
        'robot_messages': server_calls + callbacks,
        'robot_seconds': robot_seconds,  # the robots' mission times (ROS s) summed
        'server_calls_per_robot_second': server_calls / robot_seconds if robot_seconds else None,
    }


def ratio(poll: float, watch: float) -> float | None:
    return poll / watch if watch else None


def compare(summaries: dict[str, dict]) -> dict:
    """Per robot and in total, both modes side by side, and the poll / watch ratios."""
    watch, poll = totals(summaries['watch']), totals(summaries['poll'])
    rows = {}
    poll_rows = {row['name']: row for row in summaries['poll']['robots']}
    for row in summaries['watch']['robots']:
        other = poll_rows.get(row['name'], {})
        rows[row['name']] = {
            key: {'watch': row.get(key), 'poll': other.get(key)}
            for key in ('reached', 'arrival', 'requests', 'watch_calls', 'callbacks', 'callback_bytes')
        }
    return {
        'totals': {'watch': watch, 'poll': poll},
        'ratios': {
            'server_calls': ratio(poll['server_calls'], watch['server_calls']),
            'robot_messages': ratio(poll['robot_messages'], watch['robot_messages']),
            'callbacks': ratio(poll['callbacks'], watch['callbacks']),
            'callback_bytes': ratio(poll['callback_bytes'], watch['callback_bytes']),
            'server_calls_per_robot_second': ratio(
                poll['server_calls_per_robot_second'] or 0.0, watch['server_calls_per_robot_second'] or 0.0
            ),
        },
        'robots': rows,
    }


def robots_table(comparison: dict) -> str:
    def kb(value):
        return None if value is None else value / 1000

    rows = []
    for name, row in comparison['robots'].items():
        rows.append(
            [
                name,
                f"{_arrival(row['arrival']['watch'])} / {_arrival(row['arrival']['poll'])}",
                f"{row['requests']['watch']} / {row['requests']['poll']}",
                row['watch_calls']['watch'],
                f"{row['callbacks']['watch']} / {row['callbacks']['poll']}",
                f"{kb(row['callback_bytes']['watch']):.1f} / {kb(row['callback_bytes']['poll']):.1f}",
            ]
        )
    header = [
        'robot',
        'arrival s (watch / poll)',
        'calls to server',
        'of them watch calls',
        'callbacks',
        'callback kB',
    ]
    return table(header, rows)


def _arrival(value) -> str:
    return 'not arrived' if value is None else f'{value:.1f}'


def totals_table(comparison: dict) -> str:
    watch, poll = comparison['totals']['watch'], comparison['totals']['poll']
    ratios = comparison['ratios']
    rows = [
        ['server calls (server count)', poll['server_calls'], watch['server_calls'], ratios['server_calls']],
        ['callbacks received', poll['callbacks'], watch['callbacks'], ratios['callbacks']],
        [
            'robot messages (calls + callbacks)',
            poll['robot_messages'],
            watch['robot_messages'],
            ratios['robot_messages'],
        ],
        ['callback bytes', poll['callback_bytes'], watch['callback_bytes'], ratios['callback_bytes']],
        [
            'robots arrived',
            f"{poll['arrived']} of {poll['robots']}",
            f"{watch['arrived']} of {watch['robots']}",
            '',
        ],
        [
            'server calls per robot-second',
            poll['server_calls_per_robot_second'],
            watch['server_calls_per_robot_second'],
            ratios['server_calls_per_robot_second'],
        ],
        ['robot-seconds (missions summed)', poll['robot_seconds'], watch['robot_seconds'], ''],
        ['last arrival s', poll['elapsed'], watch['elapsed'], ''],
    ]
    return table(['all robots', 'poll', 'watch', 'poll / watch'], [[_cell(v) for v in row] for row in rows])


def _cell(value):
    return '—' if value is None else value


def plot(ctx: Context, comparison: dict, subtitle: str) -> str:
    """Bars per robot, watch against poll: calls to the server, callbacks, callback kB."""
    fig, _axes, name = figure(ctx, f'{NAME}-robots')
    fig.clf()
    fig.set_size_inches(11, 4)
    names = list(comparison['robots'])
    panels = (('requests', 'calls to the server', 1), ('callbacks', 'callbacks received', 1))
    panels += (('callback_bytes', 'callback kB', 1000),)
    width = 0.4
    for index, (key, label, scale) in enumerate(panels, 1):
        axes = fig.add_subplot(1, 3, index)
        for offset, mode, colour in ((-width / 2, 'watch', 'tab:blue'), (width / 2, 'poll', 'tab:orange')):
            values = [(comparison['robots'][robot][key][mode] or 0) / scale for robot in names]
            axes.bar([i + offset for i in range(len(names))], values, width, label=mode, color=colour)
        axes.set_xticks(range(len(names)), names, rotation=45 if len(names) > 3 else 0)
        axes.set_title(label)
        if index == 1:
            fig.legend(*axes.get_legend_handles_labels(), loc='upper right')
    fig.suptitle(f'Per robot, watches against polling ({subtitle})')
    return save(ctx, fig, name)


# -- the section ---------------------------------------------------------------------------------
def run(ctx: Context) -> Section:
    section = Section(NAME, TITLE)
    reason = unavailable()
    if ctx.size == 'tiny':
        ctx.progress('fleet: canned summaries (tiny: no scenario run)')
        summaries, world, note = FIXTURE_NOT_A_MEASUREMENT, None, TINY_NOTE
        runs = {}
    else:
        world = ctx.pick(None, CROSSING, WAREHOUSE)
        options = scenario_options()
        timeout = ctx.pick(0, 90, 600)
        runs = {}
        if ctx.size == 'quick':
            runs['watch'] = shared_watch_run(ctx, world, options)
            if runs['watch'] is not None:
                ctx.progress("fleet: the watch run is the link section's")
        for mode in MODES:
            if runs.get(mode) is None:
                runs[mode] = run_to_arrival(ctx, world, mode, options, timeout)
        summaries = {mode: run.summary for mode, run in runs.items()}
        note = ''
    section.results['world'] = world
    section.results['hosts'] = 'not used: ' + reason if reason else f'--hosts --robot-link {ROBOT_LINK}'
    if any(summary is None for summary in summaries.values()):
        missing = [mode for mode, summary in summaries.items() if summary is None]
        section.results['runs'] = {mode: run_record(run) for mode, run in runs.items()}
        why = f'no summary.json from the {" and ".join(missing)} run'
        section.targets['watch_message_ratio'] = target(None, TARGET, at_most=False, note=why)
        section.markdown = f'Not measured: {why}.\n\n'
        for mode in missing:
            said = [line for line in runs[mode].log_tail.splitlines() if line.startswith('run_scenario: ')]
            section.markdown += (
                f'The {mode} run (exit code {runs[mode].code}):\n\n```\n' + '\n'.join(said) + '\n```\n'
            )
            for attempt in runs[mode].failed_attempts:
                section.markdown += f'\nAn attempt before it: {attempt["why"]}.\n'
        return section
    comparison = compare(summaries)
    section.results.update(comparison)
    section.results['runs'] = {mode: run_record(run) for mode, run in runs.items()}
    value = None if ctx.size == 'tiny' else comparison['ratios']['server_calls']
    incomplete = [mode for mode in MODES if not comparison['totals'][mode]['reached']]
    if incomplete and not note:
        # Counts of a run whose robots gave up (or drove on far longer) are not the same mission's.
        note = f'not every robot arrived in the {" and ".join(incomplete)} run: counts not comparable'
        value = None
    section.targets['watch_message_ratio'] = target(value, TARGET, at_most=False, note=note)
    subtitle = 'canned summary, not a measurement' if ctx.size == 'tiny' else Path(world).name
    section.plots.append(plot(ctx, comparison, subtitle))
    section.markdown = markdown(ctx, world, comparison, runs, reason)
    return section


def slower_robots(comparison: dict, factor: float = 1.5) -> str:
    """A paragraph on the robots whose watch mission took ``factor`` times their polling one, if any."""
    slow = []
    for name, row in comparison['robots'].items():
        watch, poll = row['arrival']['watch'], row['arrival']['poll']
        if watch and poll and watch > factor * poll:
            slow.append(f'{name} ({watch:.0f} s against {poll:.0f} s, {row["requests"]["watch"]} calls)')
    if not slow:
        return ''
    return (
        f'With watches {", ".join(slow)} took far longer than polling (run.png of the run shows where). '
        'While a robot stands still, `changes_only` reports nothing of it, so it renews its `self` '
        'watch as its keep-alive every quarter of `~fix_timeout` (1.25 s): the longer the mission, '
        'the more calls, and counts over missions of different lengths favour the shorter one; the '
        'calls per robot-second above compare the rates.\n\n'
    )


def run_record(run: ScenarioRun) -> dict:
    """What latest.json keeps of a run: how it was run and how it ended."""
    keys = ('code', 'wall_seconds', 'options', 'failed_attempts')
    return {key: value for key, value in run.meta().items() if key in keys}


def markdown(ctx: Context, world: str | None, comparison: dict, runs: dict, reason: str | None) -> str:
    ratios = comparison['ratios']
    watch, poll = comparison['totals']['watch'], comparison['totals']['poll']
    if ctx.size == 'tiny':
        head = (
            '**Tiny size: no scenario ran; the tables and the plot below are drawn from a canned '
            'summary in bench/fleet.py, not a measurement.**\n\n'
        )
    else:
        where = (
            f'across network hosts (`--hosts`), the first robot on a {ROBOT_LINK} link'
            if not reason
            else f'on this host (no network hosts: {reason})'
        )
        shared = " (the watch run is the `link` section's)" if runs['watch'].out.parent.name == 'link' else ''
        head = (
            f'`{world}` run twice by `scripts/run_scenario.sh`, {where}: every robot with watches '
            f'(`--requests watch`, the default) and with the paper\'s polling (`--requests poll`){shared}. '
            f'Wall time: watch {runs["watch"].wall_seconds:.0f} s, '
            f'poll {runs["poll"].wall_seconds:.0f} s.\n\n'
        )
        for mode, run in runs.items():
            for attempt in run.failed_attempts:
                head += (
                    f'A {mode} run before this one failed ({attempt["why"]}; load average '
                    f'{attempt["load_average"][0]}) and was run again.\n\n'
                )
    text = head
    text += (
        f'**Server calls: poll {poll["server_calls"]} | watch {watch["server_calls"]} | ratio '
        f'{_ratio_text(ratios["server_calls"])}** (target ≥ {TARGET:g}; `watch_message_ratio`). '
        f'All robot messages (server calls + callbacks): poll {poll["robot_messages"]} | watch '
        f'{watch["robot_messages"]} | ratio {_ratio_text(ratios["robot_messages"])}.\n\n'
    )
    incomplete = [mode for mode in MODES if not comparison['totals'][mode]['reached']]
    if incomplete and ctx.size != 'tiny':
        text += (
            f'**Not every robot arrived in the {" and ".join(incomplete)} run**: the counts are not '
            "the same mission's, so the target is not reported.\n\n"
        )
    text += totals_table(comparison) + '\n'
    text += slower_robots(comparison)
    text += 'Per robot, watch / poll (the robots count their calls until their last status, before '
    text += 'cancelling their watches: the server count above includes the cancels):\n\n'
    text += robots_table(comparison) + '\n'
    text += (
        'The target counts server calls (the issue-15 figure): a watch replaces the one-shot request '
        'every control tick with a call per role, a renewal every 10 s and a move when the robot '
        'leaves its region, so the calls no longer grow with the polling rate. Callbacks are the '
        'answers, the outlines the robot needs: polling, a camera calls back only when it found '
        'something; watching, with `changes_only`, the static obstacles and the station are reported '
        'once (and at a renewal), but the robot itself, the other robots and the people move every '
        'period and are reported every period in both modes. So callbacks fall only '
        f'{_ratio_text(ratios["callbacks"])}× here, and all robot messages cannot fall tenfold without '
        'the robot learning less; '
        'fewer callbacks would need a camera to send the roles it reports on one frame in one '
        'callback (a change of CallbackCoordinates).\n\n'
    )
    text += (
        f'Again: `make bench` (warehouse) or `.venv/bin/python -m bench.run --only {NAME} --size quick` '
        '(crossing).\n'
    )
    return text


def _ratio_text(value: float | None) -> str:
    return '—' if value is None else f'{value:.1f}'
