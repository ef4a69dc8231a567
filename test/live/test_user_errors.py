"""A user's mistake is one clean message and exit code 2, never a traceback (issue 14).

Every node started with a bad parameter (or world file, or folder) against one private
master: exit code 2, the exact message naming the parameter, no ``Traceback``. A value
left on the parameter server says where it came from; an unknown private parameter is
a warning with the nearest name and the node keeps running. Bad options of the
commands, and drvs_ask without a master, exit cleanly too.

Each case is a process importing rospy (1-2 s): all of them start at once, in a module
fixture, and each test waits for its own; the errors come while reading parameters,
before any node does real work.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from drvs.testing import RosHarness
from drvs.testing.harness import REPO, free_port

WORLD = 'test/worlds/small.yaml'
ORIGIN = (
    ' (from the parameter server, not from this command line: left by an earlier run, a launch file '
    'or `rosparam set`; clear it with `rosparam delete {}`)'
)

# id -> (executable, node name, private parameters, the exact message block after "[FATAL] [time]: ")
NODE_CASES = {
    'drvs_server': (
        'nodes/drvs_server',
        'srv_bad',
        {'lease': 0},
        'drvs_server: ~lease: must be positive, got 0.0',
    ),
    'drvs_server cross-field': (
        'nodes/drvs_server',
        'srv_eject',
        {'ejection_time': 20, 'max_ejection_time': 10},
        'drvs_server: ~max_ejection_time: must be at least ~ejection_time (20.0), got 10.0',
    ),
    'vision_system': (
        'nodes/vision_system',
        'vs_bad',
        {'world': WORLD, 'source': 'file', 'workers': 0},
        "vision_system:\n  ~source: must be one of render, topic, got 'file'\n"
        '  ~workers: must be at least 1, got 0',
    ),
    'vision_system reference': (
        'nodes/vision_system',
        'vs_ref',
        {'world': WORLD, 'camera': 'vs1', 'reference': 'test/worlds/none.png'},
        'vision_system: ~reference: test/worlds/none.png: cannot read it as an image '
        '(no such file, or not a format OpenCV reads)',
    ),
    'world_sim': (
        'nodes/world_sim',
        'ws_bad',
        {'world': WORLD, 'rate': 'abc', 'cmd_timeout': -1},
        "world_sim:\n  ~rate: expected a number, got 'abc'\n  ~cmd_timeout: must be positive, got -1.0",
    ),
    'world_sim world file': (
        'nodes/world_sim',
        'ws_file',
        {'world': 'test/worlds/none.yaml'},
        'world_sim: test/worlds/none.yaml: cannot read the world file: No such file or directory',
    ),
    'blind_robot': (
        'nodes/blind_robot',
        'robot_bad',
        {'world': WORLD, 'resolution': 0, 'once': 2},
        'blind_robot:\n  ~resolution: must be positive, got 0.0\n  ~once: expected true or false, got 2',
    ),
    'scenario_recorder no world': (
        'nodes/scenario_recorder',
        'rec_world',
        {'out': '/tmp'},
        'scenario_recorder: ~world: required, not given (add _world:=VALUE to the command line)',
    ),
    'scenario_recorder bad out': (
        'nodes/scenario_recorder',
        'rec_out',
        {'world': WORLD, 'out': '/proc/drvs/out'},
        'scenario_recorder: ~out: cannot write to the folder /proc/drvs/out: No such file or directory',
    ),
    'sim_camera': (
        'nodes/sim_camera',
        'cam_bad',
        {'world': WORLD, 'jpeg_quality': 0},
        'sim_camera: ~jpeg_quality: must be 1 to 100, got 0',
    ),
    'sim_camera camera name': (
        'nodes/sim_camera',
        'cam_name',
        {'world': WORLD, 'cameras': 'vs9'},
        f"sim_camera: ~cameras: no vision system named 'vs9' in {WORLD} (known: vs1, vs2, rover)",
    ),
    'left on the server': (
        'nodes/world_sim',
        'ws_left',
        {'world': WORLD},
        "world_sim: ~rate: expected a number, got 'fast'" + ORIGIN.format('/ws_left/rate'),
    ),
}
LEFT_ON_SERVER = {'/ws_left/rate': 'fast'}

# id -> (argv after the interpreter, the exact last line of stderr)
COMMAND_CASES = {
    'drvs_ask --wait -1': (
        ['nodes/drvs_ask', 'colour:0,0,150,80,80,255', '--wait', '-1'],
        'drvs_ask: error: argument --wait: -1: must be a finite number at least 0',
    ),
    'drvs_ask --timeout 0': (
        ['nodes/drvs_ask', 'colour:0,0,150,80,80,255', '--timeout', '0'],
        'drvs_ask: error: argument --timeout: 0: must be a finite number greater than 0',
    ),
    'drvs_ask --roi 2 0 1 1': (
        ['nodes/drvs_ask', 'colour:0,0,150,80,80,255', '--roi', '2', '0', '1', '1'],
        'drvs_ask: error: argument --roi: region_of_interest: min_x 2 is greater than max_x 1',
    ),
    'drvs_ask --roi 0 0 x 1': (
        ['nodes/drvs_ask', 'colour:0,0,150,80,80,255', '--roi', '0', '0', 'x', '1'],
        "drvs_ask: error: argument --roi: 'x' is not a number",
    ),
    'drvs_ask _timeout:=[': (
        ['nodes/drvs_ask', 'colour:0,0,150,80,80,255', '_timeout:=[1,'],
        "drvs_ask: ~timeout: cannot read '[1,' as YAML (expected the node content, but found '<stream end>')",
    ),
    'drvs_calibrate --timeout -1': (
        [
            'nodes/drvs_calibrate',
            '--image',
            'x.png',
            '--fx',
            '1',
            '--fy',
            '1',
            '--cx',
            '1',
            '--cy',
            '1',
            '--timeout',
            '-1',
        ],
        'drvs_calibrate: error: --timeout -1.0: must be positive (see --help)',
    ),
    'drvs_report no bag': (
        ['nodes/drvs_report', 'no/such/run.bag'],
        'drvs_report: no/such/run.bag: no such file',
    ),
    'drvs_report --bogus': (
        ['nodes/drvs_report', 'run.bag', '--bogus'],
        'drvs_report: error: unrecognized arguments: --bogus',
    ),
}

MASTER_TIMEOUT = 1.0


@pytest.fixture(scope='module')
def started():
    """Every case started at once: (harness, {id: node}, {id: Popen}, the drvs_ask without a master)."""
    with RosHarness() as ros:
        for name, value in LEFT_ON_SERVER.items():
            ros.master.call('setParam', name, value)
        nodes = {
            case: ros.start_node(executable, name=name, params=params)
            for case, (executable, name, params, _) in NODE_CASES.items()
        }
        nodes['unknown'] = ros.start_node('nodes/drvs_server', name='srv_typo', params={'forward_timout': 2})
        env = {**ros.env, 'ROS_MASTER_URI': f'http://127.0.0.1:{free_port()}/'}
        commands = {
            case: subprocess.Popen(
                [sys.executable, *argv],
                cwd=REPO,
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            for case, (argv, _) in COMMAND_CASES.items()
        }
        no_master = subprocess.Popen(
            [
                sys.executable,
                'nodes/drvs_ask',
                'colour:0,0,150,80,80,255',
                '--master-timeout',
                str(MASTER_TIMEOUT),
            ],
            cwd=REPO,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        no_master.uri = env['ROS_MASTER_URI']
        try:
            yield ros, nodes, commands, no_master
        finally:
            for process in [*commands.values(), no_master]:
                if process.poll() is None:
                    process.kill()
                process.communicate()


def fatal_block(log: str) -> str:
    """The message of the ``[FATAL]`` line and the indented lines after it."""
    lines = log.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith('[FATAL]'))
    block = [lines[start].split(']: ', 1)[1]]
    block += [line for line in lines[start + 1 :] if line.startswith('  ')]
    return '\n'.join(block)


@pytest.mark.parametrize('case', list(NODE_CASES))
def test_a_bad_parameter_is_one_message_naming_it_and_exit_code_2(started, case):
    _, nodes, _, _ = started
    node = nodes[case]
    code = node.process.wait(60)
    log = node.log()
    assert code == 2, node.describe()
    assert 'Traceback' not in log, log
    assert fatal_block(log) == NODE_CASES[case][3]


def test_an_unknown_private_parameter_is_a_warning_with_a_suggestion_and_the_node_runs(started):
    ros, nodes, _, _ = started
    node = nodes['unknown']
    ros.wait_for_service('/srv_typo/detect_object_boundary', node=node, timeout=60)
    assert node.running()
    assert (
        'drvs_server: unknown parameter ~forward_timout (ignored): did you mean ~forward_timeout?'
        in node.log()
    )


@pytest.mark.parametrize('case', list(COMMAND_CASES))
def test_a_bad_option_is_one_line_and_exit_code_2(started, case):
    _, _, commands, _ = started
    stdout, stderr = commands[case].communicate(timeout=60)
    assert commands[case].returncode == 2, stdout + stderr
    assert 'Traceback' not in stdout + stderr
    expected = COMMAND_CASES[case][1]
    if expected is None:
        assert stderr.startswith('drvs_ask: invalid command-line parameters: '), stderr
    else:
        assert stderr.splitlines()[-1] == expected


def test_drvs_ask_without_a_master_gives_up_after_its_master_timeout(started):
    _, _, _, process = started
    _, stderr = process.communicate(timeout=MASTER_TIMEOUT + 20)  # a generous bound, not a speed test
    assert process.returncode == 6
    assert stderr == (
        f'drvs_ask: no ROS master at {process.uri} (Connection refused; tried for 1 s): start one with '
        "`roscore`, or `source scripts/env.sh`, or set ROS_MASTER_URI to the running master's URI\n"
    )


@pytest.mark.parametrize('node', sorted(path.name for path in (REPO / 'nodes').iterdir()))
def test_a_node_run_by_a_python_without_drvs_says_to_source_env_sh(node):
    """Debian's python3 without the project on its path: one line, exit 2, not an ImportError traceback."""
    env = {key: value for key, value in os.environ.items() if key != 'PYTHONPATH'}
    result = subprocess.run(
        ['/usr/bin/python3', f'nodes/{node}'], cwd=REPO, env=env, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 2, result.stderr
    assert result.stderr == (
        f"nodes/{node}: No module named 'drvs': run `source scripts/env.sh` first (make setup makes it)\n"
    )
