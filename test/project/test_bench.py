"""The benchmark harness (`make bench`) at tiny sizes: a smoke test, not a measurement.

Every section runs end to end and reports its targets in the shape latest.json
promises; nothing here looks at a time.
"""

import json
import math
import sys
import types

import pytest

from bench import run as bench_run
from bench.common import Context, Section, percentile, spread, target
from drvs.testing.harness import REPO

TARGETS = {
    'wire': [
        'callback_bytes_one_object',
        'image_to_drvs_bytes_10x50_photo',
        'robot_cpu_image_over_drvs',
        'robot_cpu_image_over_drvs_fused',
    ],
    'latency': ['ack_over_plain_call', 'first_callback_over_three_calls'],
    'throughput': ['forwarded_rate_over_raw_rate_fanout1', 'forwarded_rate_over_raw_rate_fanout5'],
    'registry': ['match_1m_p50_us', 'match_1m_moving_over_static', 'register_1m_us'],
    'registry_db': [],
    'replicas': [],
    'sites': [],
    'vision': ['segment_project_800x600_ms'],
    'planner': ['dstar_repair_speedup'],
    'fleet': ['watch_message_ratio'],
    'tracking': ['tracking_duplicates', 'tracking_idf1', 'tracking_switches_per_100_track_s'],
    'gateway': [
        'gateway_first_callback_over_ros',
        'gateway_sse_delivery_p50_ms',
        'gateway_listener_kib',
        'gateway_tokens_rate_over_open',
    ],
}


@pytest.fixture(scope='module')
def tiny(tiny_bench):
    """One run of every section at tiny size (started in the background: test/project/conftest.py):
    (exit code, latest.json, latest.md, out folder, stdout and stderr)."""
    code, output = tiny_bench.wait(240)
    out = tiny_bench.out
    report = json.loads((out / 'latest.json').read_text()) if (out / 'latest.json').exists() else {}
    text = (out / 'latest.md').read_text() if (out / 'latest.md').exists() else ''
    return code, report, text, out, output


def test_every_section_runs_at_tiny_size_and_reports_its_targets(tiny):
    code, report, text, out, output = tiny
    assert code == 0, output
    assert list(report['sections']) == list(bench_run.SECTIONS), output
    for name, entry in report['sections'].items():
        assert 'error' not in entry, entry.get('error')
        assert entry['size'] == 'tiny' and entry['markdown'].strip(), name
        assert f"## {entry['title']}" in text
        for plot in entry['plots']:
            assert (out / plot).read_bytes()[:8] == b'\x89PNG\r\n\x1a\n', plot
        assert set(TARGETS.get(name, [])) <= set(entry['targets']), (name, entry['targets'])
    for name, entry in report['targets'].items():
        assert set(entry) >= {'value', 'target', 'met'}, name
        value, limit = entry['value'], entry['target']
        if value is None:
            assert entry['met'] is False and entry.get('note'), name
        else:
            assert entry['met'] == (value <= limit if entry['at_most'] else value >= limit), name
    last, n = bench_run.SECTIONS[-1], len(bench_run.SECTIONS)
    assert f'[1/{n} wire' in output and f'[{n}/{n} {last}' in output  # the progress line


def test_a_section_that_raises_is_reported_and_the_run_fails(monkeypatch, tmp_path):
    broken = types.ModuleType('bench.planner')
    broken.TITLE = 'Planner'
    broken.run = lambda ctx: 1 / 0
    monkeypatch.setitem(sys.modules, 'bench.planner', broken)
    quiet = types.ModuleType('bench.vision')
    quiet.run = lambda ctx: Section('vision', 'Vision', {'x': math.nan}, {'t': target(3.0, 5.0)}, 'text')
    monkeypatch.setitem(sys.modules, 'bench.vision', quiet)

    code = bench_run.main(['--size', 'tiny', '--only', 'vision', 'planner', '--out', str(tmp_path)])

    assert code == 1
    report = json.loads((tmp_path / 'latest.json').read_text())
    assert 'ZeroDivisionError' in report['sections']['planner']['error']
    assert report['sections']['vision']['results'] == {'x': None}  # NaN is not JSON
    assert report['targets'] == {'t': {'value': 3.0, 'target': 5.0, 'met': True, 'at_most': True}}
    assert 'This section failed' in (tmp_path / 'latest.md').read_text()


def test_only_merges_into_the_earlier_results(monkeypatch, tmp_path):
    for name, value in (('vision', 1.0), ('planner', 20.0)):
        module = types.ModuleType(f'bench.{name}')
        module.run = lambda ctx, name=name, value=value: Section(name, name, {}, {name: target(value, 2.0)})
        monkeypatch.setitem(sys.modules, f'bench.{name}', module)
    assert bench_run.main(['--size', 'tiny', '--only', 'vision', 'planner', '--out', str(tmp_path)]) == 0
    assert bench_run.main(['--size', 'quick', '--only', 'planner', '--out', str(tmp_path)]) == 0
    report = json.loads((tmp_path / 'latest.json').read_text())
    assert {name: entry['size'] for name, entry in report['sections'].items()} == {
        'vision': 'tiny',
        'planner': 'quick',
    }
    assert (report['targets']['vision']['met'], report['targets']['planner']['met']) == (True, False)


def test_the_docs_are_rewritten_between_their_markers_only(tmp_path):
    report = bench_run.merged(None, {'vision': {**_entry('Vision'), 'plots': ['vision-stages.png']}}, 'quick')
    page, readme = tmp_path / 'performance.md', tmp_path / 'README.md'
    (begin, end), (readme_begin, readme_end) = bench_run.PAGE_MARKERS, bench_run.README_MARKERS
    page.write_text(f'# P\n\nbefore\n\n{begin}\nold\n{end}\n\nafter\n')
    readme.write_text(f'# R\n\n{readme_begin}\nold\n{readme_end}\n\nafter\n')
    bench_run.update_docs(report, page, readme)
    text = page.read_text()
    assert text.startswith(f'# P\n\nbefore\n\n{begin}\n') and text.endswith(f'\n{end}\n\nafter\n')
    assert 'old' not in text and '### Vision' in text and '### Targets' in text
    assert '](../bench/results/vision-stages.png)' in text
    met = sum(entry['met'] for entry in report['targets'].values())
    headline = readme.read_text()
    assert f"**{met} of {len(report['targets'])} benchmark targets met**" in headline
    assert headline.startswith(f'# R\n\n{readme_begin}\n') and headline.endswith(f'\n{readme_end}\n\nafter\n')
    bench_run.update_docs(report, page, readme)
    assert (page.read_text(), readme.read_text()) == (text, headline)
    readme.write_text('# R\n')
    with pytest.raises(SystemExit, match='no <!-- targets:begin --> ... <!-- targets:end --> markers'):
        bench_run.update_docs(report, page, readme)


def _entry(title):
    return {
        'title': title,
        'results': {},
        'targets': {},
        'markdown': 'measured',
        'plots': [],
        'size': 'quick',
        'seconds': 1.0,
        'measured': 'now',
    }


def test_statistics_helpers():
    assert percentile([3, 1, 2, 4], 50) == 2.5
    assert percentile([1, 2, 3, 4, 5], 100) == 5
    assert spread([1.0])['p99'] == 1.0
    assert target(None, 5.0, note='not at this size')['met'] is False
    assert target(12.0, 10.0, at_most=False)['met'] is True
    ctx = Context('quick', REPO, REPO)
    assert ctx.pick(1, 2, 3) == 2
