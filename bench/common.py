"""What every benchmark section shares: the run's size, the result it returns, small statistics.

A section is a module of this package with ``NAME``, ``TITLE`` and ``run(ctx) -> Section``.
:mod:`bench.run` calls them in turn and writes ``bench/results/latest.{json,md}``.
Timings are compared as ratios against an anchor measured in the same run (the
machines are shared and noisy); a section never asserts a time.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

SIZES = ('tiny', 'quick', 'full')


@dataclass
class Context:
    """One run of the benchmarks: how big, where the plots go, where scratch files go."""

    size: str  # 'tiny' (CI smoke), 'quick' (make bench QUICK=1, about 3 minutes), 'full'
    out_dir: Path  # plots (PNG) are written here; name them <section>-<what>.png
    work_dir: Path  # scratch: logs, bags, generated worlds
    progress: Callable[[str], None] = print  # one short line: what is being measured now

    def pick(self, tiny, quick, full):
        """The value for this run's size."""
        return {'tiny': tiny, 'quick': quick, 'full': full}[self.size]


def target(value: float | None, limit: float, at_most: bool = True, note: str = '') -> dict:
    """A target as latest.json reports it: ``{"value", "target", "met"}`` (+ ``"at_most"``, ``"note"``).

    ``value`` None means not measured in this run (``met`` is then false and ``note`` says why).
    """
    met = value is not None and (value <= limit if at_most else value >= limit)
    entry = {'value': value, 'target': limit, 'met': bool(met), 'at_most': at_most}
    if note:
        entry['note'] = note
    return entry


@dataclass
class Section:
    """What a section measured: JSON-able results, its targets, its part of latest.md, its plots."""

    name: str
    title: str
    results: dict = field(default_factory=dict)
    targets: dict[str, dict] = field(default_factory=dict)
    markdown: str = ''  # tables and a few sentences; each figure next to its anchor
    plots: list[str] = field(default_factory=list)  # file names in ctx.out_dir


def percentile(values: Sequence[float], q: float) -> float:
    """The q-th percentile (0..100) by linear interpolation between closest ranks."""
    ordered = sorted(values)
    if not ordered:
        return math.nan
    rank = (len(ordered) - 1) * q / 100
    low, high = math.floor(rank), math.ceil(rank)
    return ordered[low] + (ordered[high] - ordered[low]) * (rank - low)


def spread(values: Sequence[float]) -> dict:
    """``{"n", "p50", "p99", "mean"}`` of a sample."""
    return {
        'n': len(values),
        'p50': percentile(values, 50),
        'p99': percentile(values, 99),
        'mean': statistics.fmean(values) if values else math.nan,
    }


def table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A Markdown table; floats get three significant digits."""

    def cell(value):
        if isinstance(value, float):
            return f'{value:.3g}' if abs(value) < 1e4 else f'{value:,.0f}'
        return str(value)

    lines = ['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)]
    lines += ['| ' + ' | '.join(cell(value) for value in row) + ' |' for row in rows]
    return '\n'.join(lines) + '\n'


def figure(ctx: Context, name: str):
    """A new matplotlib figure and the file name it will be saved as (Agg backend, no display)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(figsize=(7, 4.5))
    return fig, axes, f'{name}.png'


def save(ctx: Context, fig, file_name: str) -> str:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(ctx.out_dir / file_name, dpi=90)
    plt.close(fig)
    return file_name
