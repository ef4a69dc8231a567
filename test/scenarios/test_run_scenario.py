"""scripts/run_scenario.sh as a user meets it: --help, bad options, no master, and
scripts/stop_scenario.sh cleaning up after a run whose script was killed.

The end-to-end output checks (no ``\\r`` or escape codes in a redirected log) ride on the
runs test_scenarios.py already makes.
"""

import os
import re
import signal
import subprocess
import time
from pathlib import Path

import pytest

from drvs.testing import RosHarness, wait_for
from drvs.testing.harness import REPO, free_port
from drvs.testing.netns import hosts_call, namespaces_of, unavailable

SCRIPT = 'scripts/run_scenario.sh'
STOP = 'scripts/stop_scenario.sh'
WORLD = 'worlds/localisation.yaml'
OPTIONS = [
    '--timeout',
    '--out',
    '--external-master',
    '--stay',
    '--camera-source',
    '--requests',
    '--fused',
    '--rviz',
    '--record',
    '--hosts',
    '--robot-link',
    '--gateway',
    '--gateway-bind',
    '--sites',
    '--help',
]


def run(argv: list[str], env: dict | None = None, timeout: float = 60.0) -> subprocess.CompletedProcess:
    """Run a script of the repository to its end, in a session of its own."""
    return subprocess.run(
        ['bash', *argv],
        cwd=REPO,
        env={**os.environ, **(env or {})},
        capture_output=True,
        text=True,
        timeout=timeout,
        start_new_session=True,
        stdin=subprocess.DEVNULL,
    )


def started(pid: int) -> int | None:
    """The process's start time (/proc/PID/stat field 22); None if it is gone or a zombie."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    except OSError:
        return None
    return None if fields[0] == 'Z' else int(fields[19])


def listed(out: Path) -> list[tuple[int, int, str]]:
    """DIR/pids as (pid, start time, name), in start order."""
    try:
        lines = (out / 'pids').read_text().splitlines()
    except FileNotFoundError:
        return []
    return [
        (int(p), int(s), n) for p, _, s, n in (line.split() for line in lines if not line.startswith('#'))
    ]


def runs(pid: int, start: int) -> bool:
    return started(pid) == start


@pytest.mark.parametrize('option', ['--help', '-h'])
def test_help_prints_every_option_on_stdout_and_exits_0(option):
    result = run([SCRIPT, option])
    assert result.returncode == 0, result.stderr
    assert result.stderr == ''
    assert result.stdout.startswith(f'usage: {SCRIPT} WORLD [--timeout S]')
    described = set(re.findall(r'^  (--[a-z-]+)', result.stdout, re.M)) | {'--help'}
    accepted = set(re.findall(r'^    (--[a-z-]+)\)', (REPO / SCRIPT).read_text(), re.M))
    assert described == set(OPTIONS) == accepted | {'--help'}
    assert 'scripts/stop_scenario.sh DIR' in result.stdout


@pytest.mark.parametrize(
    'argv, first_line',
    [
        (['--bogus'], 'run_scenario: unknown option --bogus'),
        ([], f'usage: {SCRIPT} WORLD'),
        ([WORLD, '--timeout'], f'usage: {SCRIPT} WORLD'),
        ([WORLD, 'worlds/tags.yaml'], f'usage: {SCRIPT} WORLD'),
    ],
    ids=['unknown option', 'no world', 'no value', 'two worlds'],
)
def test_a_usage_error_exits_2_with_the_usage_on_stderr(argv, first_line):
    result = run([SCRIPT, *argv])
    assert result.returncode == 2
    assert result.stdout == ''
    assert result.stderr.startswith(first_line)
    assert f'usage: {SCRIPT} WORLD' in result.stderr
    assert result.stderr.endswith(f'({SCRIPT} --help describes the options)\n')


@pytest.mark.parametrize(
    'options, message',
    [
        (['--requests', 'often'], '--requests is poll or watch, got often'),
        (['--camera-source', 'depth'], '--camera-source is render, topic or colour, got depth'),
        (['--timeout', 'soon'], '--timeout needs seconds, got soon'),
        (['--robot-link', '2mbit'], '--robot-link needs --hosts'),
        (
            ['--hosts', '--external-master'],
            '--hosts runs its own master on host master: not with --external-master',
        ),
        (['--gateway-bind', '127.0.0.1:8080'], '--gateway-bind needs --gateway'),
        (['--gateway', '--gateway-bind', 'anywhere'], '--gateway-bind needs HOST:PORT, got anywhere'),
    ],
    ids=[
        'requests',
        'camera-source',
        'timeout',
        'robot-link without hosts',
        'hosts with an external master',
        'gateway-bind without gateway',
        'gateway-bind without a port',
    ],
)
def test_a_bad_option_value_is_one_line_and_exit_2(tmp_path, options, message):
    result = run([SCRIPT, WORLD, *options, '--out', str(tmp_path)])
    assert (result.returncode, result.stdout, result.stderr) == (2, '', f'run_scenario: {message}\n')
    assert not (tmp_path / 'pids').exists()


def test_stop_scenario_removes_the_network_hosts_a_killed_run_left(tmp_path):
    reason = unavailable()
    if reason:
        pytest.skip(f'no network hosts here: {reason}')
    prefix = f'stoptest{os.getpid()}'
    for function, *args in (('hosts_init', prefix), ('hosts_add', 'master'), ('hosts_add', 'robot1')):
        hosts_call(function, *args, prefix=prefix)
    try:
        (tmp_path / 'hosts').write_text(f'{prefix}\n')  # as run_scenario.sh --hosts leaves it
        result = run([STOP, str(tmp_path)])
        assert (result.returncode, result.stdout) == (
            0,
            f'stop_scenario: removed the network hosts {prefix}-*\n',
        )
        assert namespaces_of(prefix) == []
        assert not (tmp_path / 'hosts').exists()
    finally:
        hosts_call('hosts_cleanup', prefix=prefix)


def start_script(argv: list[str], env: dict) -> subprocess.Popen:
    """A script of the repository started in a session of its own (:func:`run`, not awaited)."""
    return subprocess.Popen(
        ['bash', *argv],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        stdin=subprocess.DEVNULL,
    )


def finished(process: subprocess.Popen) -> subprocess.CompletedProcess:
    stdout, stderr = process.communicate(timeout=30)
    return subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr)


@pytest.fixture(scope='module')
def without_master(tmp_path_factory):
    """``case -> (result, out, ROS_MASTER_URI)`` of the runs with ``--external-master`` and no master
    there: each waits 3 s for one, so they start at once. Cases: ``silent`` (nothing listens at
    the URI), ``unset`` (no ROS_MASTER_URI: env.sh's default), ``stale`` (a pids file of a run
    whose processes are gone, in DIR)."""
    gone = subprocess.Popen(['true'])
    gone.wait()
    runs = {}
    for case in ('silent', 'unset', 'stale'):
        out = tmp_path_factory.mktemp(case)
        uri = f'http://127.0.0.1:{free_port()}/'  # nothing listens there
        env = {**os.environ, 'ROS_MASTER_URI': uri}
        if case == 'unset':
            del env['ROS_MASTER_URI']
        if case == 'stale':
            (out / 'pids').write_text(
                f'{gone.pid} {gone.pid} 1 run_scenario\n{gone.pid} {gone.pid} 1 robot\n'
            )
        runs[case] = start_script([SCRIPT, WORLD, '--external-master', '--out', str(out)], env), out, uri
    return {case: (finished(process), out, uri) for case, (process, out, uri) in runs.items()}


def test_external_master_that_does_not_answer_is_one_line_and_exit_2(without_master):
    result, out, uri = without_master['silent']
    assert result.returncode == 2
    assert result.stdout == ''
    assert result.stderr == (
        f'run_scenario: --external-master: no ROS master answers at {uri}; start roscore there, or point '
        'ROS_MASTER_URI at a running master (without --external-master this script starts its own)\n'
    )
    assert not (out / 'pids').exists()


def test_external_master_without_ros_master_uri_names_env_sh_default(without_master):
    result, _, _ = without_master['unset']
    if 'no ROS master answers' not in result.stderr:
        pytest.skip(f'a master answers at the default http://127.0.0.1:11311 here: {result.stderr}')
    assert result.returncode == 2
    assert result.stderr.startswith(
        'run_scenario: --external-master: no ROS master answers at http://127.0.0.1:11311 '
        "(ROS_MASTER_URI is not set: scripts/env.sh's default); start roscore there"
    )
    assert result.stderr.count('\n') == 1 and 'Traceback' not in result.stderr


def test_a_stale_pids_file_is_replaced(without_master):
    result, out, uri = without_master['stale']
    # Past the check of DIR: the run fails on the master, as it would in an unused DIR.
    assert result.returncode == 2
    assert result.stderr.startswith(f'run_scenario: --external-master: no ROS master answers at {uri};')
    assert not (out / 'pids').exists()


def test_stop_scenario_stops_what_is_listed_escalating_and_spares_a_reused_pid(tmp_path):
    """No ROS: sleeps stand in for nodes; one ignores SIGINT, one SIGINT and SIGTERM."""
    commands = {
        'rosmaster': 'trap "" INT; exec sleep 300',  # as a background rosmaster: SIGINT ignored
        'world_sim': 'exec sleep 300',
        'vs1': 'trap "" INT TERM; exec sleep 300',  # needs SIGKILL
        'robot': 'exec sleep 300',
    }
    processes = {
        name: subprocess.Popen(['bash', '-c', command], start_new_session=True)
        for name, command in commands.items()
    }
    other = subprocess.Popen(['sleep', '300'], start_new_session=True)  # not the run's: wrong start time
    try:
        for process in [*processes.values(), other]:  # exec'd into sleep, with its signals
            wait_for(lambda p=process: Path(f'/proc/{p.pid}/comm').read_text() == 'sleep\n', 10, 'sleep')
        gone = subprocess.Popen(['true'])
        gone.wait()
        lines = ['# a run', f'{gone.pid} {gone.pid} 1 run_scenario']
        lines += [f'{p.pid} 1 {started(p.pid)} {name}' for name, p in processes.items()]
        lines.append(f'{other.pid} 1 {started(other.pid) - 1} drvs_server')
        (tmp_path / 'pids').write_text('\n'.join(lines) + '\n')

        listing = run([STOP, '--list', str(tmp_path)])
        assert listing.returncode == 0
        assert listing.stdout == ''.join(f'{p.pid} {name}\n' for name, p in processes.items())

        result = run([STOP, str(tmp_path)])
        assert result.returncode == 0, result.stderr
        pid = {name: p.pid for name, p in processes.items()}
        assert result.stdout.splitlines() == [
            # SIGINT only to those that do not ignore it
            f'stop_scenario: vs1 (pid {pid["vs1"]}) did not stop on SIGTERM: sent SIGKILL',
            f'stop_scenario: stopped robot (pid {pid["robot"]}), vs1 (pid {pid["vs1"]}), '
            f'world_sim (pid {pid["world_sim"]}), rosmaster (pid {pid["rosmaster"]}) in {tmp_path}',
        ]
        for name, process in processes.items():
            assert process.wait(10) == -{'vs1': signal.SIGKILL, 'rosmaster': signal.SIGTERM}.get(
                name, signal.SIGINT
            ), name
        assert other.poll() is None
        assert not (tmp_path / 'pids').exists()

        again = run([STOP, str(tmp_path)])
        assert (again.returncode, again.stdout) == (
            0,
            f'stop_scenario: nothing was running: no {tmp_path}/pids\n',
        )
    finally:
        for process in [*processes.values(), other]:
            if process.poll() is None:
                process.kill()
            process.wait(10)


def test_stop_scenario_cleans_up_after_a_killed_run_and_a_second_run_is_refused(ros: RosHarness):
    out = ros.root / 'out'
    runner = ros.spawn('run_scenario', ['bash', SCRIPT, WORLD, '--timeout', '150', '--out', str(out)])

    def up():
        if not runner.running():
            raise AssertionError(f'run_scenario.sh ended early\n{runner.describe()}')
        try:  # the recorder writes it, from the robot's status: both are up
            return 'state moving' in (out / 'status.line').read_text()
        except FileNotFoundError:
            return False

    wait_for(up, 90, 'the robot to drive', interval=0.2, on_timeout=runner.describe)
    entries = listed(out)
    assert entries[0] == (runner.pid, started(runner.pid), 'run_scenario')
    nodes = entries[1:]
    assert [n for _, _, n in nodes] == [
        'rosmaster',
        'world_sim',
        'drvs_server',
        'vs1',
        'vs2',
        'recorder',
        'robot',
    ]
    assert all(runs(pid, start) for pid, start, _ in nodes), entries
    assert f'run_scenario: stop with Ctrl-C, or {STOP} {out} if this script is killed' in runner.log()

    second = run([SCRIPT, WORLD, '--out', str(out)])
    assert (second.returncode, second.stdout) == (2, '')
    assert second.stderr == (
        f'run_scenario: {out} is in use by another run (run_scenario pid {runner.pid}); '
        f'stop it with Ctrl-C there, or {STOP} {out}\n'
    )

    os.kill(runner.pid, signal.SIGKILL)  # the script only, not its process group
    runner.process.wait(10)
    killed = time.time_ns()
    # The run goes on without its script: the recorder writes status.line again (every 0.5 s).
    wait_for(
        lambda: (out / 'status.line').stat().st_mtime_ns > killed,
        20,
        'the recorder to write status.line after the script was killed',
        on_timeout=lambda: (out / 'recorder.log').read_text(errors='replace'),
    )
    assert all(runs(pid, start) for pid, start, _ in nodes), 'a node died with its script'
    second = run([SCRIPT, WORLD, '--out', str(out)])
    assert second.returncode == 2
    assert second.stderr == (
        f'run_scenario: {out} is in use: a killed run left {len(nodes)} process(es) running '
        f'(rosmaster pid {nodes[0][0]}, ...); stop them with {STOP} {out}\n'
    )

    result = run([STOP, str(out)])
    assert result.returncode == 0, result.stderr
    stopped = ', '.join(f'{name} (pid {pid})' for pid, _, name in reversed(nodes))
    assert result.stdout.splitlines()[-1] == f'stop_scenario: stopped {stopped} in {out}', result.stdout
    wait_for(
        lambda: not any(runs(pid, start) for pid, start, _ in nodes),
        20,
        'every process of the run to be gone',
        on_timeout=lambda: result.stdout,
    )
    assert not (out / 'pids').exists()
    recorder_log = (out / 'recorder.log').read_text()
    assert (out / 'summary.json').exists(), f'{result.stdout}\n{recorder_log}'  # stopped on SIGINT
