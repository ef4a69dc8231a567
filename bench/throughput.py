"""Throughput: forwarded requests per second at saturation, against rospy's raw persistent-call rate.

What is measured: ``CLIENTS`` robot processes (``bench/nodes/load_client.py``) call
as fast as they are answered, each over one persistent connection per service.
The anchor, in the same run: the same clients against ``bench/nodes/echo.py``, a
DetectObjectBoundary service that answers at once — rospy's raw persistent-call
rate on this machine with this many callers. Then the same clients against the
DRVS server, which forwards to five light fake vision systems in one process
(``bench/nodes/ack_vision_systems.py``: they acknowledge and count, no frame, no
callback, so the server's forwarding is what saturates). Fan-out 1: each request
covers one vision system's field of view (the clients take the five in turn);
fan-out 5: each covers all five.

A *forwarded request* is one server → vision system DetectObjectBoundary call,
counted by the vision system when it arrives; at fan-out 5 one robot request is
five of them. Its rate is those counted in a window, per second.

The three phases (raw, fan-out 1, fan-out 5) take turns, ``cycles`` times, each a
short warm-up then a window, with a pause between phases for the server's queues
to drain: the load of the other users of a shared machine drifts, and a ratio of
rates measured side by side drifts less. The target is the median of the cycles'
ratios. The CPU time of every process (``/proc``) over each window, per call or
forward, shows where a forward's cost goes.

The server runs with its rate limit raised (one robot may send as fast as it is
answered), ``~busy_retry_after`` 10 ms (a client refused ``BUSY`` — the forward
queue of its vision system is full — waits that long: the queues stay full without
the clients idling for the default half second) and
``~max_pending_per_vision_system`` 100.
"""

from __future__ import annotations

import json
import os
import statistics
import time
from pathlib import Path

from bench.common import Context, Section, figure, save, table, target
from drvs.testing.harness import RosHarness, read_json_lines, wait_for

NAME = 'throughput'
TITLE = 'Throughput: forwarded requests per second, against the raw rospy call rate'

NODES = Path(__file__).resolve().parent / 'nodes'
CLIENT = NODES / 'load_client.py'
ECHO = NODES / 'echo.py'
FAKES = NODES / 'ack_vision_systems.py'
PLAIN = '/echo/detect_object_boundary'
DRVS = '/drvs/detect_object_boundary'
CLIENTS = 4
VISION_SYSTEMS = 5
SERVER_PARAMS = {
    'max_requests_per_s': 1e6,
    'burst': 1_000_000,
    'busy_retry_after': 0.01,
    'max_pending_per_vision_system': 100,
}
ONE_EACH = [[index + 0.25, 0.25, index + 0.75, 0.75] for index in range(VISION_SYSTEMS)]
ALL = [[0.25, 0.25, VISION_SYSTEMS - 0.25, 0.75]]
PHASES = (  # tag, service label, regions, what is counted
    ('raw', 'plain', ONE_EACH),
    ('fanout1', 'drvs', ONE_EACH),
    ('fanout5', 'drvs', ALL),
)


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` so far (all its threads), from ``/proc``."""
    with open(f'/proc/{pid}/stat') as handle:
        fields = handle.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def in_window(bins: dict, width: float, start: float, end: float) -> list:
    """The sums of the counts (a number or a list of numbers) of the bins inside [start, end)."""
    total = None
    for slot, counts in bins.items():
        if start <= int(slot) * width and (int(slot) + 1) * width <= end:
            counts = counts if isinstance(counts, list) else [counts]
            total = counts if total is None else [a + b for a, b in zip(total, counts, strict=True)]
    return total or [0, 0, 0]


def schedule(ctx: Context, begin: float) -> list[dict]:
    """The phases, in turn, ``cycles`` times: each a warm-up, then its window, then a pause."""
    cycles, window = ctx.pick(1, 3, 5), ctx.pick(0.5, 1.0, 3.0)
    warmup, pause = ctx.pick(0.2, 0.3, 0.5), ctx.pick(0.2, 0.3, 0.5)
    phases, at = [], begin
    for cycle in range(cycles):
        for tag, service, regions in PHASES:
            phases.append(
                {
                    'tag': tag,
                    'cycle': cycle,
                    'service': service,
                    'regions': regions,
                    'start': at,
                    'from': at + warmup,
                    'end': at + warmup + window,
                }
            )
            at += warmup + window + pause
    return phases


def run(ctx: Context) -> Section:
    fakes_out = ctx.work_dir / 'throughput-fakes.json'
    go = ctx.work_dir / 'throughput.go'
    outs = [ctx.work_dir / f'throughput-client{number}.jsonl' for number in range(CLIENTS)]
    with RosHarness() as ros:
        ctx.progress('throughput: starting the server, echo, fake vision systems and clients')
        server = ros.start_node('nodes/drvs_server', name='drvs', params=SERVER_PARAMS)
        echo = ros.start_node(ECHO, name='echo')
        fakes = ros.start_node(FAKES, name='fakes', params={'count': VISION_SYSTEMS, 'out': fakes_out})
        services = json.dumps({'plain': PLAIN, 'drvs': DRVS})
        expect = json.dumps([['drvs', ALL[0], VISION_SYSTEMS]])
        clients = [
            ros.start_node(
                CLIENT,
                name=f'load{number}',
                params={'services': services, 'expect': expect, 'out': out, 'go': go},
            )
            for number, out in enumerate(outs)
        ]
        processes = {'server': [server], 'echo': [echo], 'fakes': [fakes], 'clients': clients}

        def healthy(condition):
            def check():
                failed = [node.name for node in ros.nodes if node.process.poll() not in (None, 0)]
                if failed:
                    raise RuntimeError(f'{", ".join(failed)} failed\n{ros.describe()}')
                return condition()

            return check

        wait_for(healthy(lambda: all(read_json_lines(out) for out in outs)), 60, 'the clients to be ready')
        phases = schedule(ctx, time.time() + 0.2)
        go.with_suffix('.tmp').write_text(json.dumps({'phases': phases}))
        go.with_suffix('.tmp').rename(go)
        for phase in phases:
            ctx.progress(f'throughput: {phase["tag"]}, cycle {phase["cycle"] + 1}, {CLIENTS} clients')
            time.sleep(max(0.0, phase['from'] - time.time()))
            before = {name: sum(cpu_seconds(node.pid) for node in nodes) for name, nodes in processes.items()}
            time.sleep(max(0.0, phase['end'] - time.time()))
            phase['cpu_s'] = {
                name: sum(cpu_seconds(node.pid) for node in nodes) - before[name]
                for name, nodes in processes.items()
            }
        wait_for(healthy(lambda: not any(node.running() for node in clients)), 60, 'the clients to finish')
        if fakes.interrupt(20) != 0:
            raise RuntimeError(f'the fake vision systems failed\n{fakes.describe()}')
    counted = json.loads(fakes_out.read_text())
    client_bins = [read_json_lines(out)[-1] for out in outs]
    for phase in phases:
        span = (phase['from'], phase['end'])
        replies, accepted, refused = (
            sum(column)
            for column in zip(*(in_window(c['bins'], c['bin'], *span) for c in client_bins), strict=True)
        )
        phase.update(replies=replies, accepted=accepted, refused=refused)
        phase['forwards'] = in_window(counted['bins'], counted['bin'], *span)[0]
    return summarize(ctx, phases)


def summarize(ctx: Context, phases: list[dict]) -> Section:
    by_tag = {tag: [phase for phase in phases if phase['tag'] == tag] for tag, _, _ in PHASES}

    def rate(phase: dict) -> float:
        counted = phase['replies'] if phase['tag'] == 'raw' else phase['forwards']
        return counted / (phase['end'] - phase['from'])

    cycles = len(by_tag['raw'])
    ratios = {
        tag: [rate(by_tag[tag][cycle]) / rate(by_tag['raw'][cycle]) for cycle in range(cycles)]
        for tag in ('fanout1', 'fanout5')
    }
    summary = {}
    for tag, entries in by_tag.items():
        window = sum(phase['end'] - phase['from'] for phase in entries)
        units = sum(phase['replies'] if tag == 'raw' else phase['forwards'] for phase in entries)
        cpu = {name: sum(phase['cpu_s'][name] for phase in entries) for name in entries[0]['cpu_s']}
        summary[tag] = {
            'per_s': units / window,
            'requests_accepted_per_s': sum(phase['accepted'] for phase in entries) / window,
            'refused': sum(phase['refused'] for phase in entries),
            'cpu_us_per_unit': {
                name: seconds / units * 1e6 if units else None for name, seconds in cpu.items()
            },
            'median_ratio_to_raw': statistics.median(ratios[tag]) if tag in ratios else 1.0,
        }
    targets = {
        f'forwarded_rate_over_raw_rate_fanout{fanout}': target(
            summary[f'fanout{fanout}']['median_ratio_to_raw'], 0.5, at_most=False
        )
        for fanout in (1, 5)
    }
    labels = {
        'raw': 'raw: plain persistent calls',
        'fanout1': 'forwards, fan-out 1',
        'fanout5': 'forwards, fan-out 5',
    }
    rows = []
    for tag, entry in summary.items():
        cpu = entry['cpu_us_per_unit']
        rows.append(
            [
                labels[tag],
                entry['per_s'],
                entry['median_ratio_to_raw'],
                cpu['clients'],
                cpu['server'] if tag != 'raw' else cpu['echo'],
                cpu['fakes'] if tag != 'raw' else '',
                entry['refused'] if tag != 'raw' else '',
            ]
        )
    markdown = table(
        [
            'what',
            'per second',
            'ratio to raw (median of cycles)',
            'clients CPU µs / unit',
            'server (echo) CPU µs / unit',
            'fake vision systems CPU µs / unit',
            'refused BUSY',
        ],
        rows,
    )
    markdown += explanation(summary, cycles)
    fig, axes, name = figure(ctx, f'{NAME}-rates')
    raw_rate = summary['raw']['per_s']
    axes.bar(
        [labels[tag] for tag in summary],
        [entry['per_s'] for entry in summary.values()],
        color=['grey', 'tab:blue', 'tab:blue'],
    )
    axes.axhline(raw_rate / 2, color='red', linestyle='--', label='target: half the raw rate')
    axes.set_ylabel('calls or forwards per second')
    axes.set_title(f'{CLIENTS} clients, same machine, same run ({ctx.size})')
    axes.legend()
    plot = save(ctx, fig, name)
    return Section(
        NAME,
        TITLE,
        results={
            'clients': CLIENTS,
            'vision_systems': VISION_SYSTEMS,
            'summary': summary,
            'ratios_by_cycle': ratios,
            'phases': phases,
        },
        targets=targets,
        markdown=markdown,
        plots=[plot],
    )


def explanation(summary: dict, cycles: int) -> str:
    """A few sentences on what the numbers say, and how to measure them again."""
    raw, one, five = summary['raw'], summary['fanout1'], summary['fanout5']

    def cpu_sum(entry: dict, *names: str) -> float:
        return sum(entry['cpu_us_per_unit'][name] or 0.0 for name in names)

    def cpu(entry: dict, *names: str) -> str:
        return f'{cpu_sum(entry, *names):.0f} µs'

    forward = ('clients', 'server', 'fakes')
    text = [
        f'Unit: a call (raw) or a forward. {CLIENTS} client processes,',
        f'{cycles} cycle(s) of the three phases side by side.',
        'The CPU per unit is what bounds the rates, as every process of the run shares the same cores:',
        f'a raw call costs the clients and the echo service {cpu(raw, "clients", "echo")},',
        f'a forward at fan-out 1 costs the clients, the server and the vision systems {cpu(one, *forward)}',
        f'({cpu(five, *forward)} at fan-out 5, where one request feeds five forwards).',
        "The server reads the robot's call and writes its acknowledgement as the echo service does,",
        'then writes the forward and reads its acknowledgement:',
        'two calls for one, hence half the raw rate as the mark at fan-out 1.',
        'Forwards leave on the thread that queued them, or on the one that saw the previous forward',
        'to that vision system end, and one thread, the reply loop (`drvs.ros.service_client.ReplyLoop`),',
        'waits for all their replies: with a worker thread blocked on each forward, as before,',
        'the hand-overs of the interpreter lock between the threads cost the server more than the',
        "forwards themselves (perf: half of its CPU in the kernel's task switching).",
        "What is left per forward is rospy's (a thread per connection, a `setblocking` and a `recv`",
        "system call per message, genpy) and ours (checks, match, queue, the forward's send and read):",
        'see the step timings of the latency section.',
        f'Two plain calls cost {cpu_sum(raw, "clients", "echo") * 2:.0f} µs and a forward',
        f'{cpu_sum(one, *forward):.0f} µs: the',
        f'{cpu_sum(one, *forward) - 2 * cpu_sum(raw, "clients", "echo"):.0f} µs between them are',
        "DRVS's own work per request (the server's checks, registry match and queue, timed in the",
        'latency section) and its extra hand-overs between threads. Were they free, fan-out 1 would',
        'reach the mark of one half; the mark itself is the cost of two rospy calls in Python.',
        'What would remove the rest: a server in C++ (roscpp), where the per-call work that dominates',
        'here, on both sides of both calls, is compiled.',
        'Reproduce: `make bench`, or `.venv/bin/python -m bench.run --only throughput`',
        '(`--size quick` for the short run).',
    ]
    return '\n' + ' '.join(text) + '\n'
