"""A fleet end to end: several robots in one world, run by scripts/run_scenario.sh.

``worlds/crossing.yaml`` (two robots whose routes cross) runs with the robots' standing
requests (watches, their default) and again with the paper's one-shot requests
(``--requests poll``): every robot reaches its station both ways, the summary has a
sane row per robot and the figures, and the server receives at least ten times fewer
robot calls with watches. Then the same world with every part on a network host of its
own (``--hosts``; the watch run itself where network namespaces can be made, and
skipped with the reason where they cannot).
Slow: the crossing world on simulated time (``real_time_factor`` 0.5), recorded and
regenerated from its bag, and ``worlds/warehouse.yaml`` (six robots, 35 cameras).
"""

import json
import re
from pathlib import Path
from typing import NamedTuple

import pytest
from test_record import drvs_report

from drvs.sim.report import SERVER_FIGURES
from drvs.sim.world_file import load_world
from drvs.testing import RosHarness
from drvs.testing.harness import REPO
from drvs.testing.netns import namespaces_of, unavailable
from drvs.testing.scenario import ScenarioRun, start_scenario

CROSSING = 'worlds/crossing.yaml'
WAREHOUSE = 'worlds/warehouse.yaml'
ROW_KEYS = {
    'name',
    'reached',
    'state',
    'reason',
    'collided',
    'collisions',
    'elapsed',
    'arrival',
    'driven_length',
    'best_length',
    'replans',
    'requests',
    'watch_calls',
    'callbacks',
    'callback_bytes',
}


class Run(NamedTuple):
    code: int  # run_scenario.sh's exit code
    summary: dict
    logs: str  # its output and the tail of each log, for failure messages
    out: Path  # its DIR
    pid: int  # its process id


def finished(run: ScenarioRun) -> Run:
    """Wait for a started run to end; its :class:`Run`, its output checked."""
    code, out = run.wait(), run.out
    logs = run.logs()
    assert (out / 'summary.json').exists(), f'no summary.json\n{logs}'
    assert not (out / 'pids').exists(), 'DIR/pids left after the run'
    assert (out / 'run.png').read_bytes()[:4] == b'\x89PNG'
    summary = json.loads((out / 'summary.json').read_text())
    return Run(code, summary, logs, out, run.runner.pid)


def run_scenario(ros: RosHarness, world: str, *options: str, timeout: float = 150) -> Run:
    """Run ``run_scenario.sh world options`` into a folder of the harness's, to its end."""
    return finished(start_scenario(ros, world, *options, timeout=timeout))


def check_fleet_summary(summary: dict, world: str, logs: str) -> None:
    """Every robot reached; a sane row per robot; the figures of the server, cameras and CPU."""
    fleet = load_world(world)
    assert summary['reached'] is True, logs
    rows = summary['robots']
    assert [row['name'] for row in rows] == [robot.name for robot in fleet.robots]
    for row in rows:
        assert set(row) == ROW_KEYS, row
        assert row['reached'] is True and row['state'] == 'arrived', row
        assert 0 < row['elapsed'] == row['arrival'] <= summary['elapsed'], row
        assert row['driven_length'] >= row['best_length'] * 0.95 > 0, row
        assert row['replans'] >= 0 and row['collisions'] >= 0, row
        assert row['requests'] > 0 and row['callbacks'] > 0 and row['callback_bytes'] > row['callbacks'], row
    assert summary['elapsed'] == max(row['elapsed'] for row in rows)
    assert summary['replans'] == sum(row['replans'] for row in rows)
    assert set(summary['server']) == set(SERVER_FIGURES)
    assert summary['server']['forward_failures'] == 0
    assert set(summary['vision_systems']) == {camera.name for camera in fleet.vision_systems}
    assert sum(camera['callbacks'] for camera in summary['vision_systems'].values()) > 0
    # CPU of every node: the server, world_sim, the recorder, each robot and camera.
    nodes = {'drvs', 'world_sim', 'scenario_recorder', *(row['name'] for row in rows)}
    assert {f'/{node}' for node in nodes | set(summary['vision_systems'])} <= set(summary['cpu'])
    assert summary['real_time_factor'] == fleet.real_time_factor
    assert summary['wall_seconds'] > 0
    # Not the paper's single-robot keys: they belong to a row.
    assert not {'state', 'driven_length', 'best_length'} & set(summary)


def server_calls(summary: dict) -> int:
    """The calls the server received: one-shot requests and watch calls (all of them the robots')."""
    return summary['server']['requests'] + summary['server']['watch_requests']


@pytest.fixture(scope='module')
def crossing(scenario_run):
    """``crossing(requests)``: the crossing world's run with ``--requests requests``, made once
    (test/scenarios/conftest.py: both start together; the watch run is the one across network
    hosts, where they can be made here), shared by the rows test, the comparison and the
    network hosts test."""
    runs = {}

    def run(requests: str) -> Run:
        if requests not in runs:
            runs[requests] = finished(scenario_run(f'crossing-{requests}'))
        return runs[requests]

    return run


@pytest.mark.parametrize('requests', ['watch', 'poll'])
def test_crossing_every_robot_reaches_its_station_with_a_row_each(crossing, requests):
    run = crossing(requests)
    assert run.code == 0, run.logs
    check_fleet_summary(run.summary, CROSSING, run.logs)
    summary, rows = run.summary, run.summary['robots']
    if requests == 'watch':
        assert all(row['watch_calls'] == row['requests'] for row in rows), rows
        assert summary['server']['requests'] == 0 and summary['server']['watch_forwards'] > 0
        assert all(camera['watch_evaluations'] > 0 for camera in summary['vision_systems'].values())
    else:
        assert all(row['watch_calls'] == 0 for row in rows), rows
        assert summary['server']['watch_requests'] == 0 and summary['server']['forwards'] > 0


def test_with_watches_the_server_receives_ten_times_fewer_robot_calls_than_polling(crossing):
    watch, poll = crossing('watch'), crossing('poll')
    assert (watch.code, poll.code) == (0, 0), f'{watch.logs}\n{poll.logs}'
    calls = {'watch': server_calls(watch.summary), 'poll': server_calls(poll.summary)}
    assert 10 * calls['watch'] <= calls['poll'], calls


def test_crossing_across_network_hosts(crossing):
    reason = unavailable()
    if reason:
        pytest.skip(f'no network hosts here: {reason}')
    run = crossing('watch')
    assert run.code == 0, run.logs
    check_fleet_summary(run.summary, CROSSING, run.logs)
    # Each node registered from its host's address (the master's log): the master and the
    # server on one, world_sim and the recorder on another, the cameras (one group) on a
    # third, each robot on its own.
    master_log = (run.out / 'ros_log' / 'master.log').read_text()
    address = dict(re.findall(r'\+PUB \[/rosout\] /(\w+) http://([\d.]+):', master_log))
    hosts = [
        {'drvs'},
        {'world_sim', 'scenario_recorder'},
        {'vs1', 'vs2', 'vs3', 'vs4'},
        {'robot1'},
        {'robot2'},
    ]
    assert [{address[node] for node in host} for host in hosts] == [{address[min(host)]} for host in hosts]
    assert len({address[min(host)] for host in hosts}) == len(hosts), address
    assert namespaces_of(f'drvs{run.pid}') == [], 'a network host of the run is left'
    assert not (run.out / 'hosts').exists()


@pytest.mark.slow
def test_crossing_on_simulated_time_counts_ros_time_and_a_bag_gives_the_same_summary(ros: RosHarness):
    world = ros.root / 'crossing_slow.yaml'
    world.write_text((REPO / CROSSING).read_text() + 'real_time_factor: 0.5\n')
    run = run_scenario(ros, str(world), '--record', timeout=300)
    assert run.code == 0, run.logs
    check_fleet_summary(run.summary, str(world), run.logs)
    # Elapsed in simulated time, which runs at half the wall clock's pace.
    assert run.summary['real_time_factor'] == 0.5
    assert run.summary['wall_seconds'] > run.summary['elapsed'], run.summary
    again = ros.root / 'again'
    result = drvs_report(run.out / 'run.bag', '--out', again)
    assert result.returncode == 0, result.stderr
    assert json.loads((again / 'summary.json').read_text()) == run.summary


@pytest.mark.slow
def test_warehouse_every_robot_reaches_its_station(ros: RosHarness):
    world = load_world(WAREHOUSE)
    run = run_scenario(ros, WAREHOUSE, timeout=round(600 / world.real_time_factor))
    assert run.code == 0, run.logs  # no collision either: run_scenario.sh exits 1 on one
    check_fleet_summary(run.summary, WAREHOUSE, run.logs)
    assert (run.summary['success'], run.summary['collisions']) == (True, 0), run.summary['reason']
