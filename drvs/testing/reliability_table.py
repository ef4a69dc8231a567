"""The reliability suites' JSON lines turned into Markdown, for docs/reliability.md.

:func:`summarise` counts the lines (:mod:`drvs.testing.reliability_log`), :func:`summary_table`
renders the summary, :func:`report` adds a table per suite, and :func:`replace_block` puts
text between the ``<!-- reliability:begin -->`` and ``<!-- reliability:end -->`` markers;
``scripts/reliability_report.py`` runs the suites and writes the page.

>>> lines = [
...     {'suite': 'fault', 'test': 't1', 'what': 'kill -9', 'outcome': 'survived', 'recovery_seconds': 0.5},
...     {'suite': 'load', 'test': 't2', 'what': '2 x 3 x 10', 'outcome': 'held', 'lost': 0, 'requests': 20},
...     {'suite': 'hostile', 'test': 't3', 'what': 'bad fields', 'outcome': 'failed', 'inputs': 40},
... ]
>>> print(summary_table(summarise(lines)))
| Reliability | |
|---|---|
| Faults survived | 1 of 1 |
| Load held | 1 of 1 |
| Inputs tried | 40, in 1 test (1 failed) |
| Data lost | 0 callbacks, in 1 test that counts them |
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ['BEGIN', 'END', 'Summary', 'read_lines', 'replace_block', 'report', 'summarise', 'summary_table']

BEGIN, END = '<!-- reliability:begin -->', '<!-- reliability:end -->'
SUITE_TITLES = {
    'fault': 'Faults',
    'load': 'Load',
    'hostile': 'Hostile input',
    'master': 'Master restart',
}
PASSED = ('survived', 'held')
_FIXED = ('suite', 'test', 'what', 'outcome', 'duration_seconds', 'error')


@dataclass
class Tally:
    """Tests of one suite: how many passed (``survived`` / ``held``) of how many."""

    passed: int = 0
    total: int = 0

    def __str__(self) -> str:
        return f'{self.passed} of {self.total}' if self.total else 'not run'


@dataclass
class Summary:
    suites: dict[str, Tally] = field(default_factory=dict)
    inputs: int = 0
    input_tests: int = 0
    input_failures: int = 0
    lost: int = 0
    lost_tests: int = 0
    failed: list[str] = field(default_factory=list)  # 'suite: test' of each failed test

    def tally(self, suite: str) -> Tally:
        return self.suites.get(suite, Tally())


def read_lines(path: str | Path) -> tuple[list[dict], int]:
    """The JSON lines of ``path`` and how many lines could not be read (a test killed mid-write)."""
    lines, unreadable = [], 0
    for text in Path(path).read_text().splitlines():
        if not text.strip():
            continue
        try:
            line = json.loads(text)
        except ValueError:
            unreadable += 1
            continue
        if isinstance(line, dict) and line.get('suite') and line.get('test'):
            lines.append(line)
        else:
            unreadable += 1
    return lines, unreadable


def summarise(lines: Iterable[dict]) -> Summary:
    """Count tests passed per suite, inputs tried (``inputs``) and callbacks lost (``lost``)."""
    summary = Summary()
    for line in lines:
        suite = line['suite']
        tally = summary.suites.setdefault(suite, Tally())
        tally.total += 1
        passed = line.get('outcome') in PASSED
        tally.passed += passed
        if not passed:
            summary.failed.append(f'{suite}: {line["test"]}')
        inputs = line.get('inputs', line.get('inputs_tried'))
        if isinstance(inputs, int):
            summary.inputs += inputs
            summary.input_tests += 1
            summary.input_failures += not passed
        if isinstance(line.get('lost'), int):
            summary.lost += line['lost']
            summary.lost_tests += 1
    return summary


def _plural(count: int, word: str) -> str:
    return f'{count} {word}{"" if count == 1 else "s"}'


def summary_table(summary: Summary) -> str:
    """The table: faults survived, load held, inputs tried, data lost (and master restarts, if run)."""
    inputs = (
        f'{summary.inputs}, in {_plural(summary.input_tests, "test")}' if summary.input_tests else 'not run'
    )
    if summary.input_failures:
        inputs += f' ({summary.input_failures} failed)'
    lost = (
        f'{summary.lost} callbacks, in {_plural(summary.lost_tests, "test")} that count'
        f'{"s" if summary.lost_tests == 1 else ""} them'
        if summary.lost_tests
        else 'not measured'
    )
    rows = [
        ('Faults survived', str(summary.tally('fault'))),
        ('Load held', str(summary.tally('load'))),
        ('Inputs tried', inputs),
        ('Data lost', lost),
    ]
    if summary.tally('master').total:
        rows.append(('Master restarts survived', str(summary.tally('master'))))
    for suite in sorted(set(summary.suites) - set(SUITE_TITLES)):
        rows.append((f'{suite} passed', str(summary.tally(suite))))
    return '\n'.join(['| Reliability | |', '|---|---|', *(f'| {name} | {value} |' for name, value in rows)])


def _number(value) -> str:
    if isinstance(value, float):
        return f'{value:.3f}'.rstrip('0').rstrip('.')
    if isinstance(value, dict):
        return '{' + ', '.join(f'{key}: {_number(item)}' for key, item in value.items()) + '}'
    if isinstance(value, list):
        return '[' + ', '.join(_number(item) for item in value) + ']'
    return str(value)


def _cell(text: str) -> str:
    return text.replace('|', '\\|').replace('\n', ' ')


def _numbers(line: dict) -> str:
    """The line's numbers, ``before``/``after`` pairs joined: ``fds 17 → 17``."""
    keys = [key for key in line if key not in _FIXED]
    parts, done = [], set()
    for key in keys:
        if key in done:
            continue
        if key.endswith('_before') and (pair := key[: -len('_before')] + '_after') in line:
            parts.append(f'{key[: -len("_before")]} {_number(line[key])} → {_number(line[pair])}')
            done.add(pair)
        else:
            parts.append(f'{key} {_number(line[key])}')
    return '; '.join(parts)


def report(lines: list[dict], heading: str = '', notes: Iterable[str] = ()) -> str:
    """The whole Markdown page: the summary, then one table per suite with every test's numbers."""
    summary = summarise(lines)
    out = ['# Reliability', '']
    if heading:
        out += [heading, '']
    out += [summary_table(summary), '']
    out += [f'- {note}' for note in notes]
    if summary.failed:
        out += [f'- **Failed:** {", ".join(summary.failed)}']
    if notes or summary.failed:
        out.append('')
    suites = [s for s in SUITE_TITLES if s in summary.suites] + sorted(
        set(summary.suites) - set(SUITE_TITLES)
    )
    for suite in suites:
        out += [f'## {SUITE_TITLES.get(suite, suite)}', '']
        out += ['| Test | What | Outcome | Numbers | Seconds |', '|---|---|---|---|---|']
        for line in (line for line in lines if line['suite'] == suite):
            outcome = line.get('outcome', '?')
            if line.get('error'):
                outcome += f': {line["error"]}'
            seconds = line.get('duration_seconds')
            out.append(
                '| '
                + ' | '.join(
                    _cell(text)
                    for text in (
                        f'`{line["test"]}`',
                        str(line.get('what', '')),
                        outcome,
                        _numbers(line),
                        _number(seconds) if seconds is not None else '',
                    )
                )
                + ' |'
            )
        out.append('')
    return '\n'.join(out)


def replace_block(text: str, block: str) -> str | None:
    """``text`` with what lies between :data:`BEGIN` and :data:`END` replaced; None without markers.

    >>> replace_block('a\\n<!-- reliability:begin -->\\nold\\n<!-- reliability:end -->\\nb', 'new')
    'a\\n<!-- reliability:begin -->\\nnew\\n<!-- reliability:end -->\\nb'
    >>> replace_block('no markers', 'new') is None
    True
    """
    start = text.find(BEGIN)
    end = text.find(END, start + len(BEGIN)) if start >= 0 else -1
    if start < 0 or end < 0:
        return None
    return text[: start + len(BEGIN)] + '\n' + block.strip('\n') + '\n' + text[end:]
