"""Fixtures shared by the whole suite.

``postgres``: a private PostgreSQL cluster for the session (its ``dsn``), stopped and removed after it.
``ros``: a :class:`drvs.testing.RosHarness` per test — a private rosmaster on a
free port with its own ROS_HOME and log folder; every node started through it
is stopped at teardown, also when the test fails or times out. In a module marked
``shared_master`` (``pytestmark = pytest.mark.shared_master``) the tests share the
master of ``module_ros`` instead: each test's harness still has its own folder and
nodes, and leaves the master as it found it (the nodes that registered since are
forgotten, the parameters set back). ``graph``: ``ros``, with this process's
environment pointing at that master, so the test can call services itself.
"""

import os
import signal
import uuid

import pytest

from drvs.testing import RosHarness, processes_of_session
from drvs.testing.harness import SESSION_VARIABLE
from drvs.testing.postgres import PostgresCluster


def pytest_configure(config):
    # Every process the suite starts carries this marker, so the end-of-session
    # check (and test_harness) can find anything left behind.
    os.environ.setdefault(SESSION_VARIABLE, uuid.uuid4().hex)
    config.addinivalue_line(
        'markers',
        'shared_master: the tests of this module share one master (module_ros); see test/conftest.py',
    )


@pytest.fixture(scope='module')
def module_ros():
    """A harness for the whole module: the master its ``shared_master`` tests share."""
    with RosHarness() as harness:
        yield harness


@pytest.fixture
def ros(request):
    if request.node.get_closest_marker('shared_master'):
        harness = RosHarness(master=request.getfixturevalue('module_ros').master)
    else:
        harness = RosHarness()
    try:
        yield harness
    finally:
        harness.close()


@pytest.fixture(scope='session')
def postgres():
    """A private PostgreSQL cluster (drvs.testing.postgres), started by the first test that needs it and
    removed at the end of the session; each test empties the tables it uses."""
    with PostgresCluster() as cluster:
        yield cluster


@pytest.fixture
def graph(ros, monkeypatch):
    """The harness, with this process able to call the private master's services."""
    monkeypatch.setenv('ROS_MASTER_URI', ros.master.uri)
    monkeypatch.setenv('ROS_HOSTNAME', '127.0.0.1')
    return ros


def pytest_sessionfinish(session, exitstatus):
    """Fail the run if any process started by the suite outlived it (then kill it).

    With pytest-xdist only the controller looks, once every worker has ended: a worker that ends
    first would find the other workers' processes still running.
    """
    if hasattr(session.config, 'workerinput'):
        return
    left = processes_of_session(os.environ[SESSION_VARIABLE])
    if not left:
        return
    reporter = session.config.pluginmanager.get_plugin('terminalreporter')
    for pid in left:
        try:
            with open(f'/proc/{pid}/cmdline', 'rb') as handle:
                command = handle.read().replace(b'\0', b' ').decode(errors='replace')
        except OSError:
            command = '?'
        if reporter:
            reporter.write_line(f'LEFT BEHIND by the test suite: pid {pid}: {command}', red=True)
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    session.exitstatus = pytest.ExitCode.TESTS_FAILED
