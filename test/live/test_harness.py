"""The harness itself: private masters, waits with deadlines, and nothing left behind."""

import os
import signal
import subprocess
import sys
import textwrap
import uuid

import pytest

from drvs.testing import RosHarness, WaitTimeout, processes_of_session, wait_for
from drvs.testing.harness import REPO, SESSION_VARIABLE


def test_each_harness_has_its_own_master_and_folders():
    with RosHarness() as first, RosHarness() as second:
        assert first.master.port != second.master.port
        assert first.root != second.root
        assert first.env['ROS_HOME'].startswith(str(first.root))
        assert first.env['ROS_LOG_DIR'].startswith(str(first.root))
        assert first.env['ROS_MASTER_URI'] == first.master.uri


def test_a_harness_on_a_shared_master_leaves_it_as_it_found_it():
    with RosHarness() as owner:
        owner.master.call('setParam', '/kept', 1)
        with RosHarness(master=owner.master) as guest:
            assert guest.env['ROS_MASTER_URI'] == owner.master.uri and guest.root != owner.root
            node = guest.start_node('test/nodes/echo_detect_boundary.py', name='echo')
            guest.wait_for_service('/echo/detect_object_boundary', node=node)
            os.killpg(node.pid, signal.SIGKILL)  # it cannot unregister
            node.process.wait(10)
            guest.master.call('setParam', '/added', 2)
            guest.master.call('setParam', '/kept', 3)
        assert not guest.root.exists() and not node.running()
        assert owner.master.lookup_service('/echo/detect_object_boundary') is None
        assert owner.master.nodes() == set()
        assert owner.master.call('getParam', '/') == {'kept': 1}
        assert owner.master.node.running()


def test_a_harness_in_a_run_that_ignores_sigint_still_stops_its_master_at_once():
    """A run started in the background (``make test &``) ignores SIGINT; the harness's children must not."""
    code = textwrap.dedent(
        """
        import signal, time
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        from drvs.testing import RosHarness
        harness = RosHarness()
        started = time.monotonic()
        harness.close()
        print(time.monotonic() - started)
        """
    )
    env = {**os.environ, 'DRVS_TEST_STOP_GRACE': '10'}
    result = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert float(result.stdout) < 5, 'the master sat out the grace after SIGINT'


def test_wait_for_service_shows_the_log_of_a_node_that_died(ros: RosHarness):
    node = ros.spawn('dies', [sys.executable, '-c', 'print("boom: no such camera"); raise SystemExit(3)'])
    with pytest.raises(WaitTimeout, match='boom: no such camera'):
        ros.wait_for_service('/never/there', timeout=10, node=node)


def test_wait_for_gives_up_at_its_deadline():
    with pytest.raises(WaitTimeout, match='timed out after 0.2 s waiting for the impossible'):
        wait_for(lambda: False, 0.2, 'the impossible')


def test_nothing_is_left_behind_when_tests_fail_or_time_out(tmp_path):
    """Run a small suite whose tests fail and hang; afterwards no process of it may remain."""
    suite = tmp_path / 'test_inner.py'
    suite.write_text(
        textwrap.dedent(f"""
        import sys, time
        import pytest

        def start(ros):
            node = ros.start_node({str(REPO / 'test/nodes/echo_detect_boundary.py')!r}, name='echo')
            ros.wait_for_service('/echo/detect_object_boundary', node=node)
            # a grandchild in the node's group that ignores SIGINT and SIGTERM
            ros.spawn('stubborn', [sys.executable, '-c',
                'import signal, time; signal.signal(signal.SIGINT, signal.SIG_IGN); '
                'signal.signal(signal.SIGTERM, signal.SIG_IGN); time.sleep(600)'])

        def test_fails(ros):
            start(ros)
            assert False, 'deliberate failure'

        @pytest.mark.timeout(8)
        def test_hangs(ros):
            start(ros)
            time.sleep(600)
    """)
    )
    (tmp_path / 'conftest.py').write_text((REPO / 'test/conftest.py').read_text())
    session = uuid.uuid4().hex
    # The stubborn grandchild ignores SIGINT and SIGTERM: a short grace gets to SIGKILL sooner.
    env = {**os.environ, SESSION_VARIABLE: session, 'DRVS_TEST_STOP_GRACE': '1'}
    result = subprocess.run(
        [
            sys.executable,
            '-m',
            'pytest',
            '-q',
            '-p',
            'no:cacheprovider',
            '-o',
            'timeout=60',
            '--rootdir',
            str(tmp_path),
            str(suite),
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=180,
        cwd=tmp_path,
    )
    assert '2 failed' in result.stdout, result.stdout + result.stderr
    assert 'LEFT BEHIND' not in result.stdout
    assert processes_of_session(session) == []
