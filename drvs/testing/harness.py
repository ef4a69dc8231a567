"""A rostest-style harness for pytest, without roslaunch or catkin.

Each :class:`RosHarness` owns a temporary folder, a private ``rosmaster`` on a
free port (with its own ROS_HOME and log directory there) and every node it
started as a subprocess in its own process group. :meth:`RosHarness.close`
stops them all together: SIGINT, wait, SIGTERM, wait, SIGKILL to each group. Every
process carries the environment variable ``DRVS_TEST_SESSION`` so that
:func:`processes_of_session` can prove nothing was left behind.

A harness can instead share another's master (``RosHarness(master=...)``, the
``ros`` fixture of a module marked ``shared_master``): it then owns only its folder
and its nodes, and on closing makes the master forget every node that registered
after it opened and sets the parameters back, so the next test finds the master as
this one did.

Nothing here imports rospy: the harness talks to the master over XML-RPC.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
import xmlrpc.client
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[2]
SESSION_VARIABLE = 'DRVS_TEST_SESSION'
CALLER_ID = '/drvs_test_harness'


class WaitTimeout(AssertionError):
    """A condition did not become true before its deadline."""


def free_port() -> int:
    """Return a TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(('127.0.0.1', 0))
        return sock.getsockname()[1]


def wait_for(
    condition: Callable[[], object],
    timeout: float,
    what: str,
    interval: float = 0.05,
    on_timeout: Callable[[], str] | None = None,
):
    """Poll ``condition`` until it returns a truthy value, which is returned.

    :raises WaitTimeout: after ``timeout`` seconds, naming ``what`` and adding
        ``on_timeout()`` (for example a node's log) to the message.
    """
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() >= deadline:
            detail = on_timeout() if on_timeout else ''
            raise WaitTimeout(
                f'timed out after {timeout:.1f} s waiting for {what}' + (f'\n{detail}' if detail else '')
            )
        time.sleep(interval)


def freeze(pid: int, timeout: float = 10.0) -> None:
    """SIGSTOP ``pid`` and wait until every thread of it has stopped (``kill`` returns before they
    have: on a busy machine a thread may still answer one more request)."""
    os.kill(pid, signal.SIGSTOP)

    def stopped() -> bool:
        try:
            states = [
                _thread_state(f'/proc/{pid}/task/{task}/stat') for task in os.listdir(f'/proc/{pid}/task')
            ]
        except FileNotFoundError:
            return True  # gone: it answers nothing either
        return all(state in ('T', 't', None) for state in states)

    wait_for(stopped, timeout, f'process {pid} to stop', interval=0.005)


def _thread_state(path: str) -> str | None:
    try:
        with open(path) as stat:
            return stat.read().rsplit(')', 1)[1].split()[0]
    except (FileNotFoundError, IndexError):
        return None


def processes_of_session(session: str) -> list[int]:
    """PIDs of live processes whose environment carries ``DRVS_TEST_SESSION=session``."""
    marker = f'{SESSION_VARIABLE}={session}'.encode()
    found = []
    for entry in os.listdir('/proc'):
        if not entry.isdigit() or int(entry) == os.getpid():
            continue
        try:
            with open(f'/proc/{entry}/environ', 'rb') as handle:
                environ = handle.read().split(b'\0')
            with open(f'/proc/{entry}/stat', 'rb') as handle:
                state = handle.read().rsplit(b')', 1)[1].split()[0]
        except OSError:
            continue
        if marker in environ and state != b'Z':
            found.append(int(entry))
    return found


STOP_GRACE = float(os.environ.get('DRVS_TEST_STOP_GRACE', '5'))
"""Seconds a process gets after SIGINT, and again after SIGTERM, before the next signal."""


def _stop_groups(processes: Iterable[subprocess.Popen], grace: float = STOP_GRACE) -> None:
    """SIGINT, wait, SIGTERM, wait, SIGKILL the process groups of ``processes``, all at once.

    A rospy node takes most of a second to exit after SIGINT; stopping the nodes of a
    test together costs that once, not once per node.
    """
    processes = list(processes)
    running = processes
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
        running = [process for process in running if process.poll() is None]
        if not running:
            break
        for process in running:
            try:
                os.killpg(process.pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + grace
        for process in running:
            try:
                process.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                continue
    # Children of a leader that outlived it still belong to its group.
    for process in processes:
        try:
            os.killpg(process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        if process.poll() is None:
            process.wait(grace)


def _default_sigint() -> None:
    """In the child before it runs: SIGINT as a terminal gives it. A test run started in the
    background (``make test &``, some CI runners) ignores SIGINT, and its children would
    inherit that: rosmaster would sit out each stop's grace, and a bash script could not trap it."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class NodeProcess:
    """A process started by the harness, with its combined output in ``log_path``."""

    def __init__(self, name: str, argv: list[str], env: Mapping[str, str], log_path: Path, cwd: Path):
        self.name = name
        self.argv = argv
        self.log_path = log_path
        self._log = open(log_path, 'wb')  # noqa: SIM115 - closed in stop()
        self.process = subprocess.Popen(
            argv,
            env=dict(env),
            cwd=cwd,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
            preexec_fn=_default_sigint,
        )

    @property
    def pid(self) -> int:
        return self.process.pid

    def running(self) -> bool:
        return self.process.poll() is None

    def log(self, tail: int = 60) -> str:
        """The last ``tail`` lines of the process's output."""
        try:
            lines = self.log_path.read_text(errors='replace').splitlines()
        except OSError:
            return ''
        return '\n'.join(lines[-tail:])

    def describe(self) -> str:
        status = 'running' if self.running() else f'exited with {self.process.returncode}'
        return f'--- {self.name} ({status}), {self.log_path} ---\n{self.log()}'

    def interrupt(self, timeout: float = 10.0) -> int:
        """Send SIGINT (Ctrl-C) only and wait for a clean exit; return the exit code.

        :raises WaitTimeout: with the node's log, if it is still running after ``timeout``.
        """
        if self.running():
            os.killpg(self.process.pid, signal.SIGINT)
        try:
            return self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            message = f'{self.name} still runs {timeout:g} s after SIGINT\n{self.describe()}'
            raise WaitTimeout(message) from None

    def stop(self) -> None:
        stop_all([self])

    def _close_log(self) -> None:
        self._log.close()


def stop_all(nodes: Iterable[NodeProcess]) -> None:
    """Stop ``nodes`` together (see :func:`_stop_groups`) and close their logs."""
    nodes = list(nodes)
    _stop_groups(node.process for node in nodes)
    for node in nodes:
        node._close_log()


class RosMaster:
    """A private rosmaster on a free port, reached over XML-RPC.

    :meth:`restart` replaces it with a new master process on the same port, as a
    crashed and restarted roscore would (every registration is lost). Every master
    process it started is in ``processes``, and in the harness's nodes for cleanup.
    """

    def __init__(self, harness: RosHarness):
        self._harness = harness
        self.port = free_port()
        self.uri = f'http://127.0.0.1:{self.port}/'
        self.processes: list[NodeProcess] = []
        self._spawn()  # sets self.node
        wait_for(self._answers, 20.0, f'rosmaster on port {self.port}', on_timeout=self.node.describe)

    def _spawn(self) -> NodeProcess:
        self.node = self._harness.spawn('rosmaster', ['rosmaster', '--core', '-p', str(self.port)], ros=False)
        self.processes.append(self.node)
        return self.node

    def _answers(self) -> bool:
        if not self.node.running():
            raise WaitTimeout(f'rosmaster exited early\n{self.node.describe()}')
        return self._pings()

    def _pings(self) -> bool:
        try:
            return self._raw_call('getPid')[0] == 1
        except OSError:
            return False

    @property
    def pid(self) -> int:
        """The pid the master reports (``getPid``)."""
        return self.call('getPid')

    def kill(self) -> None:
        """SIGKILL the master's process group and reap it: a crash, no clean shutdown."""
        node = self.node
        if node.running():
            try:
                os.killpg(node.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        node.process.wait(10)
        node.stop()  # closes its log; the group is gone

    def restart(self, timeout: float = 20.0) -> int:
        """Kill -9 the master and start a new one on the same port; return the new master's pid."""
        self.kill()
        return self.start_again(timeout)

    def start_again(self, timeout: float = 20.0) -> int:
        """Start a new master on the same port after :meth:`kill`; return its pid once it answers.

        The port can stay taken for a moment (an outgoing connection may get it
        as its local port), and rosmaster then waits forever without serving
        ("Unable to start XML-RPC server"): such a process is stopped and
        another one started, until one answers or ``timeout`` passes.
        """
        if self.node.running():
            raise RuntimeError(f'rosmaster on port {self.port} is still running: kill() it first')
        self._spawn()

        def up() -> bool:
            node = self.node
            if not node.running() or 'Unable to start XML-RPC server' in node.log():
                node.stop()
                self._spawn()
                return False
            return self._pings()

        wait_for(
            up, timeout, f'a new rosmaster on port {self.port}', interval=0.1, on_timeout=self.node.describe
        )
        return self.pid

    def _raw_call(self, method: str, *args) -> list:
        with xmlrpc.client.ServerProxy(self.uri) as proxy:
            return getattr(proxy, method)(CALLER_ID, *args)

    def call(self, method: str, *args):
        """Call a master API method; return its value or raise RuntimeError with its message."""
        code, message, value = self._raw_call(method, *args)
        if code != 1:
            raise RuntimeError(f'master {method}{args}: {message}')
        return value

    def lookup_service(self, name: str) -> str | None:
        code, _, uri = self._raw_call('lookupService', name)
        return uri if code == 1 else None

    def system_state(self) -> tuple[list, list, list]:
        """(publishers, subscribers, services), each a list of [name, [nodes]]."""
        return tuple(self.call('getSystemState'))

    def nodes(self) -> set[str]:
        """Names of the nodes that hold a registration (publisher, subscriber or service)."""
        return {node for kind in self.system_state() for _, nodes in kind for node in nodes}

    def snapshot(self) -> tuple[set[str], dict]:
        """(registered nodes, parameter tree), for :meth:`restore`."""
        return self.nodes(), self.call('getParam', '/')

    def restore(self, snapshot: tuple[set[str], dict]) -> None:
        """Unregister everything of the nodes that registered since ``snapshot`` (stopped nodes
        killed before they could unregister leave their names behind) and set its parameters back."""
        known, parameters = snapshot
        publishers, subscribers, services = self.system_state()
        with xmlrpc.client.ServerProxy(self.uri) as proxy:
            for node in sorted(self.nodes() - known):
                code, _, api = proxy.lookupNode(CALLER_ID, node)
                if code != 1:
                    continue
                for topic, nodes in publishers:
                    if node in nodes:
                        proxy.unregisterPublisher(node, topic, api)
                for topic, nodes in subscribers:
                    if node in nodes:
                        proxy.unregisterSubscriber(node, topic, api)
                for service, nodes in services:
                    if node in nodes and (uri := self.lookup_service(service)):
                        proxy.unregisterService(node, service, uri)
        self.call('setParam', '/', parameters)

    def subscriptions_of(self, node: str) -> list[str]:
        """Topic names the node ``node`` subscribes to, from the master's record."""
        return sorted(topic for topic, nodes in self.system_state()[1] if node in nodes)


class RosHarness:
    """Owns a temporary folder, a private master and the nodes started against it.

    With ``master``, another harness's master is used instead of starting one: this
    harness's :meth:`close` stops its own nodes and leaves the master as it found it
    (:meth:`RosMaster.restore`); the master itself is the other harness's to stop,
    restart or kill. Use as a context manager, or call :meth:`close`; the pytest fixture
    ``ros`` in ``test/conftest.py`` does it for every test.
    """

    def __init__(self, session: str | None = None, keep: bool = False, master: RosMaster | None = None):
        self.session = session or os.environ.get(SESSION_VARIABLE) or uuid.uuid4().hex
        self.root = Path(tempfile.mkdtemp(prefix='drvs-test-'))
        self.keep = keep
        self.nodes: list[NodeProcess] = []
        (self.root / 'ros_home').mkdir()
        (self.root / 'log').mkdir()
        self.master: RosMaster | None = master
        self._found = master.snapshot() if master is not None else None
        if master is None:
            try:
                self.master = RosMaster(self)
            except BaseException:
                self.close()
                raise

    # -- environment -------------------------------------------------------------------------
    @property
    def env(self) -> dict[str, str]:
        """The environment a process needs to join this harness's ROS graph."""
        env = dict(os.environ)
        for key in ('ROS_IP', 'ROS_NAMESPACE'):
            env.pop(key, None)
        env.update(
            {
                SESSION_VARIABLE: self.session,
                'ROS_HOME': str(self.root / 'ros_home'),
                'ROS_LOG_DIR': str(self.root / 'log'),
                'ROS_HOSTNAME': '127.0.0.1',
                'ROS_PACKAGE_PATH': str(REPO)
                + (':' + env['ROS_PACKAGE_PATH'] if env.get('ROS_PACKAGE_PATH') else ''),
                'PYTHONPATH': str(REPO) + (':' + env['PYTHONPATH'] if env.get('PYTHONPATH') else ''),
                'PYTHONUNBUFFERED': '1',
            }
        )
        if self.master is not None:
            env['ROS_MASTER_URI'] = self.master.uri
        return env

    # -- processes ---------------------------------------------------------------------------
    def spawn(
        self, name: str, argv: list[str], ros: bool = True, env: Mapping[str, str] | None = None
    ) -> NodeProcess:
        """Start ``argv`` in its own process group with its output logged; tracked for cleanup."""
        full_env = self.env if ros else {**self.env, 'ROS_MASTER_URI': ''}
        full_env.update(env or {})
        log_path = self.root / 'log' / f'{name.strip("/").replace("/", "_")}-{len(self.nodes)}.out'
        node = NodeProcess(name, argv, full_env, log_path, REPO)
        self.nodes.append(node)
        return node

    def start_node(
        self,
        executable: str | os.PathLike,
        name: str | None = None,
        params: Mapping[str, object] | None = None,
        args: Iterable[str] = (),
        remap: Mapping[str, str] | None = None,
        env: Mapping[str, str] | None = None,
    ) -> NodeProcess:
        """Start a Python node with ROS arguments: ``__name:=``, ``_param:=value``, remappings.

        ``executable`` is a path relative to the repository (``nodes/drvs_server``) or
        absolute; it runs under this interpreter (the project's venv).
        """
        path = Path(executable)
        if not path.is_absolute():
            path = REPO / path
        argv = [sys.executable, str(path), *args]
        if name:
            argv.append(f'__name:={name}')
        for key, value in (remap or {}).items():
            argv.append(f'{key}:={value}')
        for key, value in (params or {}).items():
            argv.append(f'_{key}:={_param_text(value)}')
        return self.spawn(name or path.name, argv, env=env)

    def wait_for_service(self, service: str, timeout: float = 30.0, node: NodeProcess | None = None) -> str:
        """Wait until the master knows ``service``; return its URI.

        Fails early, with the node's log, if ``node`` exits before that.
        """

        def ready():
            if node is not None and not node.running():
                raise WaitTimeout(f'{node.name} exited before providing {service}\n{node.describe()}')
            return self.master.lookup_service(service)

        return wait_for(ready, timeout, f'service {service}', on_timeout=self.describe)

    def describe(self) -> str:
        """Every process's status and log tail, for failure messages."""
        return '\n'.join(node.describe() for node in self.nodes)

    def run(self, command: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
        """Run a shell command with this graph's environment (and scripts/env.sh sourced)."""
        script = f'source {REPO}/scripts/env.sh && {command}'
        return subprocess.run(
            ['bash', '-c', script],
            env=self.env,
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=timeout,
            start_new_session=True,
        )

    # -- teardown ----------------------------------------------------------------------------
    def close(self) -> None:
        """Stop every node, then the master (or restore a shared one); remove the folder unless kept."""
        owned = self.master is not None and self._found is None
        masters = self.master.processes if owned else []
        stop_all(node for node in reversed(self.nodes) if not any(node is master for master in masters))
        if owned:
            stop_all(reversed(masters))
        elif self.master is not None and self.master.node.running():
            self.master.restore(self._found)
        if not self.keep:
            shutil.rmtree(self.root, ignore_errors=True)

    def __enter__(self) -> RosHarness:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _param_text(value: object) -> str:
    """Render a private parameter the way rospy parses ``_name:=value`` (YAML)."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    return str(value)


def read_json_lines(path: str | os.PathLike) -> list[dict]:
    """Every complete JSON line of ``path`` (none if it does not exist yet)."""
    import json

    try:
        text = Path(path).read_text()
    except FileNotFoundError:
        return []
    return [json.loads(line) for line in text.splitlines() if line.endswith('}')]


class _EchoLoader(yaml.SafeLoader):
    """YAML as ``rostopic echo`` prints it: its ``nan``, ``inf`` and ``-inf`` are floats."""


_EchoLoader.add_implicit_resolver('tag:yaml.org,2002:float', re.compile(r'^(?:[-+]?inf|nan)$'), list('-+in'))


def echo(ros: RosHarness, topic: str, timeout: float = 30.0) -> dict:
    """One message of ``topic`` as ``rostopic echo -n 1`` prints it, parsed (YAML -> dict).

    A time is ``{'secs', 'nsecs'}`` (see :func:`seconds`), a geometry_msgs/Polygon
    ``{'points': [{'x', 'y', 'z'}, ...]}`` (see :func:`points`), NaN a float NaN.
    """
    result = ros.run(f'rostopic echo -n 1 {topic}', timeout=timeout)
    assert result.returncode == 0, f'rostopic echo -n 1 {topic}: {result.stderr}'
    return parse_echo(result.stdout.split('\n---')[0])


def parse_echo(text: str) -> dict:
    """A message printed as ``rostopic echo`` does (``genpy.message.strify_message``) -> dict."""
    return yaml.load(text, Loader=_EchoLoader)


def seconds(time: dict) -> float:
    """An echoed time (``{'secs', 'nsecs'}``) in seconds."""
    return time['secs'] + time['nsecs'] * 1e-9


def points(polygon: dict) -> list[list[float]]:
    """An echoed geometry_msgs/Polygon as ``[[x, y], ...]``."""
    return [[point['x'], point['y']] for point in polygon['points']]
