"""The tiny benchmark run of test_bench.py, started in the background as the session begins.

test_bench.py's smoke test needs one run of every benchmark section at tiny size: about half
a minute of one core, whose times it does not look at. When that test is collected, the run
starts as soon as collection ends, alongside the unit tests (pyproject.toml's ``testpaths``
put them first; they look at no time either), and the test only waits for what is left.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from drvs.testing.harness import REPO

SMOKE_TEST = 'test/project/test_bench.py::test_every_section_runs_at_tiny_size_and_reports_its_targets'


class TinyBench:
    """``python -m bench.run --size tiny`` into a folder of its own, started at once."""

    def __init__(self):
        self.folder = Path(tempfile.mkdtemp(prefix='drvs-bench-'))
        self.out, self.work = self.folder / 'out', self.folder / 'work'
        self.out.mkdir()
        self.work.mkdir()
        self.started = time.monotonic()
        with open(self.folder / 'stdout', 'wb') as stdout, open(self.folder / 'stderr', 'wb') as stderr:
            self.process = subprocess.Popen(
                [
                    sys.executable,
                    '-m',
                    'bench.run',
                    '--size',
                    'tiny',
                    '--out',
                    str(self.out),
                    '--work',
                    str(self.work),
                ],
                cwd=REPO,
                stdout=stdout,
                stderr=stderr,
                stdin=subprocess.DEVNULL,
                start_new_session=True,  # its masters and nodes in one group, stopped together
            )

    def wait(self, timeout: float) -> tuple[int, str]:
        """(exit code, stdout + stderr) once the run ends, at most ``timeout`` s after it started."""
        self.process.wait(max(0.0, timeout - (time.monotonic() - self.started)))
        output = (self.folder / 'stdout').read_text(errors='replace')
        return self.process.returncode, output + (self.folder / 'stderr').read_text(errors='replace')

    def close(self) -> None:
        """Kill the run and everything it started (its process group), and remove its folder."""
        try:
            os.killpg(self.process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.process.wait(10)
        shutil.rmtree(self.folder, ignore_errors=True)


_started: list[TinyBench] = []


def pytest_collection_finish(session):
    # Under pytest-xdist every worker collects every test but runs only some: the run starts in
    # the test itself, on the worker that runs it (the other worker keeps the second core busy).
    if hasattr(session.config, 'workerinput'):
        return
    if not session.config.option.collectonly and any(item.nodeid == SMOKE_TEST for item in session.items):
        _started.append(TinyBench())


@pytest.fixture(scope='session')
def tiny_bench():
    """The :class:`TinyBench` started after collection (or, if none was, one started now)."""
    bench = _started.pop() if _started else TinyBench()
    try:
        yield bench
    finally:
        bench.close()


@pytest.hookimpl(tryfirst=True)
def pytest_sessionfinish(session, exitstatus):
    """A run started but never waited for (the session was cut short) is stopped before the
    suite looks for processes left behind."""
    while _started:
        _started.pop().close()
