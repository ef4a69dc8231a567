"""Replicas: forwarded requests per second with 1, 2 and 3 servers on one registry database, and the
time a client takes to get an answer again after kill -9 of the replica it was asking.

Three ``drvs_server`` replicas share a private PostgreSQL cluster (scripts/postgres.sh); five light
fake vision systems in one process (``bench/nodes/ack_vision_systems.py``) register through the
first, the others match them from their caches. ``CLIENTS`` robot processes
(``bench/nodes/load_client.py``) call as fast as they are answered, at fan-out 1, each client
asking replica ``client % k`` in the phase of ``k`` replicas; the phases take turns, ``cycles``
times, and a rate is the forwards the vision systems counted in a phase's window, per second. All
of it on the machine of the run: with more replicas than cores they share the same CPUs, so the
rates say what one machine gives, not what three hosts would.

Failover: this process asks the second replica in a loop (through
:class:`drvs.common.failover.ServerList`, the third next); the replica is killed (SIGKILL) and the
time from the kill to the next accepted answer, from the third, is reported, ``repeats`` times (a
killed replica is started again between two). Its connection is refused at once (the host is up):
a dead host would add the client's deadline.

Run alone: ``.venv/bin/python -m bench.run --only replicas`` (``--size quick``). docs/registry.md.
"""

from __future__ import annotations

import json
import os
import signal
import statistics
import time

from bench.common import Context, Section, table
from bench.throughput import CLIENT, FAKES, ONE_EACH, SERVER_PARAMS, VISION_SYSTEMS, cpu_seconds, in_window
from drvs.testing.harness import RosHarness, read_json_lines, wait_for

NAME = 'replicas'
TITLE = 'Replicas: requests per second with 1, 2 and 3 servers on one database, and failover time'

REPLICAS = ('drvs', 'drvs_r1', 'drvs_r2')
CLIENTS = 3


def service(replica: str) -> str:
    return f'/{replica}/detect_object_boundary'


def run(ctx: Context) -> Section:
    from drvs.testing.postgres import PostgresCluster

    cycles, window = ctx.pick(1, 2, 3), ctx.pick(0.5, 1.0, 3.0)
    warmup, pause = ctx.pick(0.2, 0.3, 0.5), ctx.pick(0.2, 0.3, 0.5)
    fakes_out = ctx.work_dir / 'replicas-fakes.json'
    go = ctx.work_dir / 'replicas.go'
    clients_count = ctx.pick(2, CLIENTS, CLIENTS)
    outs = [ctx.work_dir / f'replicas-client{number}.jsonl' for number in range(clients_count)]
    with PostgresCluster() as cluster, RosHarness() as ros:
        ctx.progress('replicas: starting three servers on one database, fake vision systems, clients')
        params = {**SERVER_PARAMS, 'registry': cluster.dsn}
        servers = {name: ros.start_node('nodes/drvs_server', name=name, params=params) for name in REPLICAS}
        for name, node in servers.items():
            ros.wait_for_service(service(name), node=node)
        fakes = ros.start_node(FAKES, name='fakes', params={'count': VISION_SYSTEMS, 'out': fakes_out})
        # A client that stays (until its own go file) for the failover requests' callback service.
        keeper_out, keeper_go = ctx.work_dir / 'replicas-keeper.jsonl', ctx.work_dir / 'replicas-keeper.go'
        keeper = ros.start_node(
            CLIENT,
            name='keeper',
            params={'services': '{}', 'expect': '[]', 'out': keeper_out, 'go': keeper_go},
        )
        clients = []
        for number, out in enumerate(outs):
            services = {f'k{k}': service(REPLICAS[number % k]) for k in (1, 2, 3)}
            expect = [[label, ONE_EACH[0], 1] for label in services]
            clients.append(
                ros.start_node(
                    CLIENT,
                    name=f'load{number}',
                    params={
                        'services': json.dumps(services),
                        'expect': json.dumps(expect),
                        'out': out,
                        'go': go,
                    },
                )
            )
        wait_for(
            lambda: all(read_json_lines(out) for out in [*outs, keeper_out]), 90, 'the clients to be ready'
        )
        phases, at = [], time.time() + 0.2
        for cycle in range(cycles):
            for k in (1, 2, 3):
                phases.append(
                    {
                        'k': k,
                        'cycle': cycle,
                        'service': f'k{k}',
                        'regions': ONE_EACH,
                        'start': at,
                        'from': at + warmup,
                        'end': at + warmup + window,
                    }
                )
                at += warmup + window + pause
        go.with_suffix('.tmp').write_text(json.dumps({'phases': phases}))
        go.with_suffix('.tmp').rename(go)
        for phase in phases:
            ctx.progress(f'replicas: {phase["k"]} replica(s), cycle {phase["cycle"] + 1}')
            time.sleep(max(0.0, phase['from'] - time.time()))
            before = sum(cpu_seconds(node.pid) for node in servers.values())
            time.sleep(max(0.0, phase['end'] - time.time()))
            phase['server_cpu_s'] = sum(cpu_seconds(node.pid) for node in servers.values()) - before
        wait_for(lambda: not any(node.running() for node in clients), 60, 'the clients to finish')
        ctx.progress('replicas: failover after kill -9')
        repeats = ctx.pick(1, 3, 5)
        failovers = [failover(ros, servers, params, again=n + 1 < repeats) for n in range(repeats)]
        keeper_go.write_text(json.dumps({'phases': []}))
        wait_for(lambda: not keeper.running(), 30, 'the keeper client to finish')
        if fakes.interrupt(20) != 0:
            raise RuntimeError(f'the fake vision systems failed\n{fakes.describe()}')
    counted = json.loads(fakes_out.read_text())
    for phase in phases:
        phase['forwards'] = in_window(counted['bins'], counted['bin'], phase['from'], phase['end'])[0]
    return summarize(phases, failovers, clients_count)


def failover(ros: RosHarness, servers: dict, params: dict, again: bool) -> dict:
    """Ask the second replica in a loop, kill it, time the next accepted answer (from the third);
    ``again``: start the second again for the next time."""
    from drvs.common.failover import ServerList, moves_on
    from drvs.msg import BoundingBox
    from drvs.ros.service_client import ServiceCallError, ServiceClient
    from drvs.srv import DetectObjectBoundary, DetectObjectBoundaryRequest

    os.environ['ROS_MASTER_URI'] = ros.master.uri
    os.environ.setdefault('ROS_HOSTNAME', '127.0.0.1')
    order = ServerList([service(REPLICAS[1]), service(REPLICAS[2])])
    clients = {name: ServiceClient(name, DetectObjectBoundary, 1.0) for name in order.servers}
    request = DetectObjectBoundaryRequest(
        algorithm='colour:0,0,150,80,80,255',
        region_of_interest=BoundingBox(*ONE_EACH[0]),
        callback_service='/keeper/callback_coordinates',
        request_id='failover',
    )

    def ask() -> bool:
        try:
            reply = clients[order.current].call(request)
        except ServiceCallError:
            order.failed()
            return False
        if moves_on(reply.status):
            order.failed()
            return False
        return reply.vision_systems == 1

    def second_answers() -> bool:
        try:
            return clients[service(REPLICAS[1])].call(request).vision_systems == 1
        except ServiceCallError:
            return False

    try:
        wait_for(second_answers, 30, 'an answer from the second replica')
        order = ServerList([service(REPLICAS[1]), service(REPLICAS[2])])  # asking the second now
        victim = servers[REPLICAS[1]]
        os.killpg(victim.pid, signal.SIGKILL)
        killed = time.monotonic()
        failed_calls = 0
        while not ask():
            failed_calls += 1
        seconds = time.monotonic() - killed
        answered_by = order.current
        if answered_by != service(REPLICAS[2]) or failed_calls == 0:
            raise RuntimeError(f'failover: answered by {answered_by} after {failed_calls} failed calls')
    finally:
        for client in clients.values():
            client.close()
    victim.process.wait(10)
    if again:
        servers[REPLICAS[1]] = ros.start_node('nodes/drvs_server', name=REPLICAS[1], params=params)
        ros.wait_for_service(service(REPLICAS[1]), node=servers[REPLICAS[1]])
    return {'ms': seconds * 1e3, 'failed_calls': failed_calls, 'answered_by': answered_by}


def summarize(phases: list[dict], failovers: list[dict], clients: int) -> Section:
    results = {}
    for k in (1, 2, 3):
        mine = [phase for phase in phases if phase['k'] == k]
        window = sum(phase['end'] - phase['from'] for phase in mine)
        forwards = sum(phase['forwards'] for phase in mine)
        results[f'replicas_{k}'] = {
            'forwards_per_s': forwards / window,
            'per_cycle': [phase['forwards'] / (phase['end'] - phase['from']) for phase in mine],
            'server_cpu_us_per_forward': sum(p['server_cpu_s'] for p in mine) / forwards * 1e6
            if forwards
            else None,
        }
    times = [entry['ms'] for entry in failovers]
    results['failover'] = {'ms': times, 'p50_ms': statistics.median(times), 'runs': failovers}
    rows = [
        [k, results[f'replicas_{k}']['forwards_per_s'], results[f'replicas_{k}']['server_cpu_us_per_forward']]
        for k in (1, 2, 3)
    ]
    text = (
        f'{clients} clients at fan-out 1, each asking replica `client % k`; forwards counted by the '
        f'vision systems, per second of the windows ({os.cpu_count()} CPUs: every process of the run '
        'shares them).\n\n'
        + table(['replicas', 'forwards/s', "servers' CPU µs per forward"], rows)
        + f'\n\nFailover after kill -9 of the replica a client was asking: the next accepted answer, from '
        f'the next replica in its list, {statistics.median(times):.1f} ms after the kill (median of '
        f'{len(times)}: {", ".join(f"{t:.1f}" for t in times)} ms; the killed replica\'s port refuses '
        'at once, a dead host would add the client\'s deadline).\n'
    )
    return Section(NAME, TITLE, results=results, markdown=text)
