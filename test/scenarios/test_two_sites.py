"""Two sites end to end: ``scripts/run_scenario.sh worlds/two_sites.yaml --sites``.

Site a and site b each have a ROS master and a drvs_server on a network host of its own, both
servers on one PostgreSQL database; site b's cameras run on master b and register with server b;
the robot starts at site a, on master a, and its station is at site b. With per-camera answers
(``--fused false``) the robot reaches its station without a collision, site b's cameras having
called it back across the sites. Slow: skipped with the reason where network hosts cannot be
made (not root) or PostgreSQL is not installed. The refusals of ``--sites``, and stop_scenario.sh
removing the database a killed run left, are fast.
"""

import glob
import json
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

from drvs.testing import RosHarness
from drvs.testing.harness import REPO
from drvs.testing.netns import namespaces_of, unavailable
from drvs.testing.scenario import start_scenario

WORLD = 'worlds/two_sites.yaml'
SCRIPT = 'scripts/run_scenario.sh'


def cannot_run() -> str | None:
    """Why a run across sites cannot be made here, or None."""
    reason = unavailable()
    if reason:
        return f'no network hosts here: {reason}'
    if not glob.glob('/usr/lib/postgresql/*/bin/pg_ctl'):
        return 'PostgreSQL is not installed: scripts/setup.sh --postgres'
    return None


def nodes_of(master_log) -> dict[str, str]:
    """node -> its address, from a master's log (each node registers its /rosout publisher)."""
    return dict(re.findall(r'\+PUB \[/rosout\] /(\w+) http://([\d.]+):', master_log.read_text()))


@pytest.mark.slow
@pytest.mark.parametrize('variant', ['per-camera', 'fused-simulated-time-camera-topics'])
def test_the_robot_at_site_a_reaches_its_station_at_site_b_through_site_b_cameras(ros: RosHarness, variant):
    """``per-camera``: each camera calls the robot back itself (``--fused false``), so site b's
    cameras call a robot at site a. The other: fused answers (site b's cameras call server a's
    fusion callback), the world on simulated time (``/clock`` reaches site b through the site
    link) and the cameras' images from sim_camera nodes on each site (``--camera-source topic``)."""
    reason = cannot_run()
    if reason:
        pytest.skip(reason)
    if variant == 'per-camera':
        world, options = WORLD, ('--fused', 'false')
    else:
        world, options = str(ros.root / 'two_sites_slow.yaml'), ('--camera-source', 'topic')
        Path(world).write_text((REPO / WORLD).read_text() + 'real_time_factor: 0.7\n')
    run = start_scenario(ros, world, '--sites', *options, timeout=200)
    code, logs = run.wait(), run.logs()
    summary = json.loads((run.out / 'summary.json').read_text())
    assert code == 0, logs
    assert summary['success'] is True and summary['collisions'] == 0, logs
    # Site b's cameras answered the robot at site a: their callbacks reached it (or, fused,
    # server a's fusion stage, which answers the robot).
    cameras = summary['vision_systems']
    assert cameras['vs_b1']['callbacks'] > 0 and cameras['vs_b2']['callbacks'] > 0, cameras
    (robot,) = summary['robots']
    if variant == 'per-camera':
        assert robot['callbacks'] >= cameras['vs_b1']['callbacks'] + cameras['vs_b2']['callbacks'], summary
    else:
        # Fused: server a's tracks (/drvs/objects) were measured against ground truth.
        assert summary['real_time_factor'] == 0.7 and summary['tracking']['periods'] > 0, summary
    # Each node on its site's master, from the host the run gave it.
    site_a, site_b = (
        nodes_of(run.out / 'ros_log' / 'master.log'),
        nodes_of(run.out / 'ros_log_b' / 'master.log'),
    )
    assert {'drvs', 'world_sim', 'scenario_recorder', 'robot', 'vs_a1', 'vs_a2'} <= set(site_a), site_a
    assert {'drvs', 'site_link', 'vs_b1', 'vs_b2'} <= set(site_b), site_b
    assert not {'vs_b1', 'vs_b2'} & set(site_a) and not {'robot', 'vs_a1', 'vs_a2', 'world_sim'} & set(site_b)
    assert site_a['drvs'] != site_b['drvs'] and site_a['vs_a1'] != site_b['vs_b1']
    if variant != 'per-camera':
        assert {'sim_vs_b1', 'sim_vs_b2'} <= set(site_b) and {'sim_vs_a1', 'sim_vs_a2'} <= set(site_a)
    # Everything removed: the hosts and the database.
    assert namespaces_of(f'drvs{run.runner.pid}') == [], 'a network host of the run is left'
    assert not (run.out / 'hosts').exists() and not (run.out / 'postgres').exists()


def run_script(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run(['bash', SCRIPT, *argv], cwd=REPO, capture_output=True, text=True, timeout=60)


def test_sites_with_an_external_master_is_refused(tmp_path):
    result = run_script(WORLD, '--sites', '--external-master', '--out', str(tmp_path))
    assert (result.returncode, result.stdout, result.stderr) == (
        2,
        '',
        'run_scenario: --sites runs a master per site: not with --external-master\n',
    )


def test_sites_on_a_world_of_one_site_is_refused(tmp_path):
    if unavailable():
        pytest.skip(f'no network hosts here: {unavailable()}')  # the script says that first
    result = run_script('worlds/obstacles.yaml', '--sites', '--out', str(tmp_path))
    assert (result.returncode, result.stdout, result.stderr) == (
        2,
        '',
        'run_scenario: --sites: no camera of '
        f'{REPO}/worlds/obstacles.yaml names its site (site: a, site: b, ...; worlds/README.md)\n',
    )
    assert not (tmp_path / 'pids').exists()


def test_stop_scenario_stops_and_removes_the_database_a_killed_run_left(tmp_path):
    if not glob.glob('/usr/lib/postgresql/*/bin/pg_ctl'):
        pytest.skip('PostgreSQL is not installed: scripts/setup.sh --postgres')
    folder = Path(tempfile.mkdtemp(prefix='drvs-sites.', dir='/tmp'))  # as run_scenario.sh --sites makes it
    try:
        started = subprocess.run(
            ['bash', 'scripts/postgres.sh', 'start', str(folder)], cwd=REPO, capture_output=True, text=True
        )
        assert started.returncode == 0, started.stderr
        (tmp_path / 'postgres').write_text(f'{folder}\n')
        result = subprocess.run(
            ['bash', 'scripts/stop_scenario.sh', str(tmp_path)], cwd=REPO, capture_output=True, text=True
        )
        assert (result.returncode, result.stdout) == (
            0,
            f'stop_scenario: stopped the database in {folder} and removed it\n',
        ), result.stderr
        assert not folder.exists() and not (tmp_path / 'postgres').exists()
        assert (tmp_path / 'postgres_server.log').exists()  # the cluster's log, kept with the run's
    finally:
        if folder.exists():
            subprocess.run(
                ['bash', 'scripts/postgres.sh', 'stop', str(folder)], cwd=REPO, capture_output=True
            )
            shutil.rmtree(folder, ignore_errors=True)
