"""``make bench``: run the benchmark sections and write bench/results/latest.{json,md} and their plots.

    .venv/bin/python -m bench.run [--size tiny|quick|full] [--only NAME ...] [--out DIR] [--readme]

Each section (a module of this package, see :mod:`bench.common`) measures one of the
issue's figures next to the anchor it is compared with, in the same run. A section that
raises is reported as failed (with its traceback in latest.json) and the others still
run; the exit status is then 1. ``--only`` runs some sections and merges them into the
existing latest.json, so one figure can be measured again without the rest.
``--readme`` puts the summary into README.md between its performance markers.
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import json
import math
import os
import platform
import shutil
import sys
import tempfile
import time
import traceback
from pathlib import Path

from bench.common import SIZES, Context, Section

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / 'bench' / 'results'
# In the order of the items: Table 1, the constrained link, latency, throughput,
# the registry, vision, the planner, the fleet.
SECTIONS = ('wire', 'link', 'latency', 'throughput', 'registry', 'vision', 'planner', 'fleet')
README_BEGIN, README_END = '<!-- performance:begin -->', '<!-- performance:end -->'


class Progress:
    """The status line ``[3/8 latency 0:42] latency: 10 vision systems``, in place on a terminal."""

    def __init__(self, total: int, stream=sys.stderr):
        self.total, self.stream = total, stream
        self.index, self.name, self.started = 0, '', time.monotonic()
        self.tty = stream.isatty()
        self.width = 0

    def section(self, index: int, name: str) -> None:
        self.index, self.name = index, name
        self('starting')

    def __call__(self, message: str) -> None:
        elapsed = int(time.monotonic() - self.started)
        line = f'[{self.index}/{self.total} {self.name} {elapsed // 60}:{elapsed % 60:02d}] {message}'
        if self.tty:
            self.stream.write('\r' + line.ljust(self.width)[: max(self.width, len(line))])
            self.width = len(line)
        else:
            self.stream.write(line + '\n')
        self.stream.flush()

    def done(self, message: str) -> None:
        if self.tty:
            self.stream.write('\n')
        self(message)
        if self.tty:
            self.stream.write('\n')
            self.width = 0


def machine() -> dict:
    """What the numbers were measured on."""
    load = os.getloadavg()
    return {
        'cpus': os.cpu_count(),
        'platform': platform.platform(),
        'python': platform.python_version(),
        'load_average_at_start': [round(value, 2) for value in load],
    }


def run_section(name: str, ctx: Context) -> dict:
    """Run one section; its entry for latest.json (with ``error`` when it raised)."""
    started = time.monotonic()
    try:
        module = importlib.import_module(f'bench.{name}')
        section: Section = module.run(ctx)
        entry = {
            'title': section.title,
            'results': section.results,
            'targets': section.targets,
            'markdown': section.markdown,
            'plots': section.plots,
        }
    except Exception:
        title = getattr(sys.modules.get(f'bench.{name}'), 'TITLE', name)
        entry = {'title': title, 'results': {}, 'targets': {}, 'markdown': '', 'plots': []}
        entry['error'] = traceback.format_exc()
    entry.update(size=ctx.size, seconds=round(time.monotonic() - started, 1))
    entry['measured'] = datetime.datetime.now(datetime.UTC).isoformat(timespec='seconds')
    return entry


def merged(previous: dict | None, sections: dict, size: str) -> dict:
    """latest.json: the sections just run, plus the earlier ones not run again."""
    report = {'sections': {}}
    if previous:
        report['sections'].update(previous.get('sections', {}))
    report['sections'].update(sections)
    report['sections'] = {name: report['sections'][name] for name in SECTIONS if name in report['sections']}
    report['generated'] = datetime.datetime.now(datetime.UTC).isoformat(timespec='seconds')
    report['size'] = size
    report['machine'] = machine()
    report['targets'] = {}
    for entry in report['sections'].values():
        for target_name, value in entry['targets'].items():
            report['targets'][target_name] = value
    return report


def jsonable(value):
    """``value`` with NaN and infinities as None and numpy scalars as Python numbers."""
    if isinstance(value, dict):
        return {str(key): jsonable(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(item) for item in value]
    if hasattr(value, 'item') and callable(value.item):  # numpy scalar
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if value is None or isinstance(value, bool | int | float | str):
        return value
    return str(value)


def _value(value) -> str:
    if value is None:
        return 'not measured'
    if isinstance(value, float):
        return f'{value:.3g}' if abs(value) < 1e4 else f'{value:,.0f}'
    return str(value)


def targets_table(report: dict) -> str:
    lines = ['| target | measured | limit | met |', '|---|---|---|---|']
    for name, entry in report['targets'].items():
        limit = ('≤ ' if entry.get('at_most', True) else '≥ ') + _value(entry['target'])
        met = 'yes' if entry['met'] else 'no'
        note = f" ({entry['note']})" if entry.get('note') else ''
        lines.append(f"| `{name}` | {_value(entry['value'])}{note} | {limit} | {met} |")
    return '\n'.join(lines) + '\n'


def markdown(report: dict, plot_prefix: str = '') -> str:
    """latest.md (``plot_prefix`` is prepended to the plots' file names, for README.md)."""
    machine_text = report['machine']
    met = sum(entry['met'] for entry in report['targets'].values())
    parts = [
        '# DRVS benchmarks\n',
        f"Generated {report['generated']} by `make bench` (size {report['size']}) on "
        f"{machine_text['cpus']} CPUs, {machine_text['platform']}, Python {machine_text['python']}, "
        f"load average {machine_text['load_average_at_start'][0]} at the start. "
        'Timings are noisy on a shared machine: each is reported next to an anchor measured in the '
        'same run, and the targets are ratios where the issue allows.\n',
        f"## Targets\n\n{met} of {len(report['targets'])} met.\n\n" + targets_table(report),
    ]
    for name, entry in report['sections'].items():
        text = f"## {entry['title']}\n\n"
        text += (
            f"Section `{name}`, size {entry['size']}, {entry['seconds']} s, measured {entry['measured']}. "
        )
        text += f'Again: `.venv/bin/python -m bench.run --only {name}`.\n\n'
        if entry.get('error'):
            text += 'This section failed:\n\n```\n' + entry['error'].strip() + '\n```\n'
        text += entry['markdown'].strip() + '\n'
        for plot in entry['plots']:
            text += f'\n![{plot}]({plot_prefix}{plot})\n'
        parts.append(text)
    return '\n'.join(parts)


def readme_section(report: dict) -> str:
    """README.md's Performance section: latest.md one heading level down, plots linked from the repo root."""
    text = markdown(report, plot_prefix='bench/results/')
    lines = []
    for line in text.splitlines():
        if line.startswith('# DRVS benchmarks'):
            continue
        lines.append('#' + line if line.startswith('## ') else line)
    body = '\n'.join(lines).strip()
    return (
        f'{README_BEGIN}\n'
        '<!-- generated by `make bench` (bench/run.py --readme) from bench/results/latest.md: '
        'do not edit -->\n'
        f'{body}\n{README_END}'
    )


def update_readme(report: dict, path: Path) -> None:
    text = path.read_text()
    begin, end = text.find(README_BEGIN), text.find(README_END)
    if begin < 0 or end < begin:
        raise SystemExit(f'{path}: no {README_BEGIN} ... {README_END} markers to write the section between')
    path.write_text(text[:begin] + readme_section(report) + text[end + len(README_END) :])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--size', choices=SIZES, default='full')
    parser.add_argument('--only', nargs='+', choices=SECTIONS, metavar='NAME', help=', '.join(SECTIONS))
    parser.add_argument('--out', type=Path, default=RESULTS, help='where latest.json, latest.md and plots go')
    parser.add_argument('--work', type=Path, help='scratch folder (default: a temporary one, removed)')
    parser.add_argument('--readme', action='store_true', help="write the summary into README.md's markers")
    args = parser.parse_args(argv)

    names = args.only or list(SECTIONS)
    args.out.mkdir(parents=True, exist_ok=True)
    latest = args.out / 'latest.json'
    previous = json.loads(latest.read_text()) if args.only and latest.exists() else None
    work = args.work or Path(tempfile.mkdtemp(prefix='drvs-bench-'))
    work.mkdir(parents=True, exist_ok=True)
    progress = Progress(len(names))
    sections = {}
    try:
        for index, name in enumerate(names, 1):
            progress.section(index, name)
            section_work = work / name
            section_work.mkdir(exist_ok=True)
            ctx = Context(args.size, args.out, section_work, progress)
            sections[name] = entry = run_section(name, ctx)
            missed = [target for target, value in entry['targets'].items() if not value['met']]
            met = len(entry['targets']) - len(missed)
            verdict = f'{met} of {len(entry["targets"])} targets met' if entry['targets'] else 'no targets'
            if entry.get('error'):
                verdict = 'FAILED'
            if missed:
                verdict += f', missed: {", ".join(missed)}'
            progress.done(f'{entry["seconds"]} s, {verdict}')
            # Written after every section: an interrupted run keeps what it measured.
            report = write(args, merged(previous, sections, args.size))
    finally:
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)

    if args.readme:
        update_readme(report, REPO / 'README.md')
    failed = [name for name, entry in sections.items() if entry.get('error')]
    print(f'wrote {latest} and latest.md' + (f'; FAILED sections: {", ".join(failed)}' if failed else ''))
    for name in failed:
        print(f'--- {name} ---\n{sections[name]["error"]}', file=sys.stderr)
    return 1 if failed else 0


def write(args, report: dict) -> dict:
    """latest.json and latest.md in ``args.out``; the report as written (JSON-able)."""
    report = jsonable(report)
    (args.out / 'latest.json').write_text(json.dumps(report, indent=1, allow_nan=False) + '\n')
    (args.out / 'latest.md').write_text(markdown(report))
    return report


if __name__ == '__main__':
    sys.exit(main())
