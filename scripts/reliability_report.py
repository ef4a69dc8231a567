#!/usr/bin/env python3
"""Run the reliability suites, then write their figures into docs/reliability.md.

    .venv/bin/python scripts/reliability_report.py           # small sizes (make reliability-report)
    .venv/bin/python scripts/reliability_report.py --soak    # the slow variants too
    .venv/bin/python scripts/reliability_report.py --soak --slow-log out/soak.jsonl  # (make soak)

The suites are test/live/test_faults.py, test_load.py, test_hostile_input.py,
test_security.py and test_master_restart.py; those not there yet are named in
the report and skipped. pytest runs with ``DRVS_RELIABILITY_LOG`` set to a
temporary file, in which each test leaves one line (drvs.testing.reliability_log);
a suite that fails to import is reported by pytest and the others still run;
drvs.testing.reliability_table turns the lines into Markdown. The page's block between
``<!-- reliability:begin -->`` and ``<!-- reliability:end -->`` gets the figures (one
heading level down); a page without the markers is written whole. ``--slow-log FILE``:
the slow variants already ran with their lines in FILE (``make soak`` runs them with
the rest of the slow suite); only the small ones run here, and FILE's lines are added.
Other arguments go to pytest. The exit status is pytest's (no tests collected counts
as success); the report is written either way.
"""

import argparse
import datetime
import os
import shlex
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path
from xml.etree import ElementTree

from drvs.testing.reliability_table import read_lines, replace_block, report, summarise, summary_table

REPO = Path(__file__).resolve().parents[1]
SUITES = [
    'test/live/test_faults.py',
    'test/live/test_load.py',
    'test/live/test_hostile_input.py',
    'test/live/test_security.py',
    'test/live/test_master_restart.py',
]
NO_TESTS_COLLECTED = 5


def commit() -> str:
    result = subprocess.run(
        ['git', 'rev-parse', '--short', 'HEAD'], cwd=REPO, capture_output=True, text=True, check=False
    )
    return result.stdout.strip() or 'unknown commit'


def pytest_results(junit: Path) -> tuple[Counter, list[str]]:
    """Tests passed, failed and skipped, and the names of the failed ones, from pytest's JUnit XML."""
    counts, failed = Counter(), []
    if not junit.exists() or junit.stat().st_size == 0:
        return counts, failed
    for case in ElementTree.parse(junit).getroot().iter('testcase'):
        if case.find('failure') is not None or case.find('error') is not None:
            counts['failed'] += 1
            failed.append(case.get('name') or case.get('classname') or '?')
        elif case.find('skipped') is not None:
            counts['skipped'] += 1
        else:
            counts['passed'] += 1
    return counts, failed


def embedded(page: str) -> str:
    """The report without its title and one heading level down, for the block of a page with its own."""
    lines = page.splitlines()
    if lines and lines[0].startswith('# '):
        lines = lines[1:]
    return '\n'.join('#' + line if line.startswith('## ') else line for line in lines).strip('\n')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--soak', action='store_true', help='include the slow (full-size) variants')
    parser.add_argument(
        '--slow-log', type=Path, help='JSON lines of slow variants that already ran (with --soak)'
    )
    parser.add_argument(
        '--output',
        type=Path,
        default=REPO / 'docs' / 'reliability.md',
        help='the report (docs/reliability.md)',
    )
    options, pytest_args = parser.parse_known_args()
    if options.slow_log and not options.soak:
        parser.error('--slow-log: only with --soak')

    present = [suite for suite in SUITES if (REPO / suite).exists()]
    notes = [f'`{suite}`: not there yet, not run' for suite in SUITES if suite not in present]
    marker = 'slow or not slow' if options.soak and not options.slow_log else 'not slow'
    slow_lines = []
    if options.slow_log:
        if options.slow_log.exists():
            slow_lines, unreadable = read_lines(options.slow_log)
            notes.append(f'slow variants: {len(slow_lines)} lines from `{options.slow_log}`')
            if unreadable:
                notes.append(f'{unreadable} unreadable lines in `{options.slow_log}` skipped')
        else:
            notes.append(f'slow variants: `{options.slow_log}` not found, none reported')

    with tempfile.TemporaryDirectory(prefix='drvs-reliability-') as folder:
        log = Path(folder) / 'reliability.jsonl'
        log.touch()
        junit = Path(folder) / 'junit.xml'
        env = {**os.environ, 'DRVS_RELIABILITY_LOG': str(log)}
        # A suite that does not import (being written) must not stop the others from running.
        command = [
            sys.executable,
            '-m',
            'pytest',
            '--continue-on-collection-errors',
            f'--junitxml={junit}',
            '-m',
            marker,
            *present,
            *pytest_args,
        ]
        print('running:', shlex.join(command), flush=True)
        status = subprocess.run(command, cwd=REPO, env=env, check=False).returncode if present else 0
        lines, unreadable = read_lines(log)
        counts, failed = pytest_results(junit)
    if counts:
        passed, failures, skipped = counts['passed'], counts['failed'], counts['skipped']
        notes.append(f'pytest ({marker}): {passed} passed, {failures} failed, {skipped} skipped')
    silent = [name for name in failed if name not in {line['test'] for line in lines}]
    if silent:  # a test that failed before writing its line (or a suite that did not import)
        notes.append('**Failed without a line in the table:** ' + ', '.join(f'`{name}`' for name in silent))
    if unreadable:
        notes.append(f'{unreadable} unreadable lines skipped')
    lines += slow_lines

    mode = 'full sizes (`--soak`)' if options.soak else 'small sizes'
    heading = (
        f'Generated by `scripts/reliability_report.py` on {datetime.date.today().isoformat()} at {commit()}, '
        f'{mode}, on a {os.cpu_count()}-core machine; pytest exit status {status}. '
        'Each row is one test; its numbers are counts, seconds, kB (rss) or open descriptors (fds).'
    )
    page = report(lines, heading, notes)
    options.output.parent.mkdir(parents=True, exist_ok=True)
    text = options.output.read_text() if options.output.exists() else ''
    replaced = replace_block(text, embedded(page))
    options.output.write_text(replaced if replaced is not None else page + '\n')
    print(f'wrote {options.output}')
    table = summary_table(summarise(lines))
    print(table)
    return 0 if status == NO_TESTS_COLLECTED else status


if __name__ == '__main__':
    sys.exit(main())
