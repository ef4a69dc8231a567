"""scripts/run_scenario.sh from a test: started on a :class:`RosHarness`, then awaited.

Without ``--hosts`` (or ``--sites``) a run uses the harness's master (``--external-master``);
with it, the run makes its own on a network host. test/scenarios/conftest.py starts the default suite's
runs two at a time with these.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from drvs.testing.harness import NodeProcess, RosHarness, wait_for

SCRIPT = 'scripts/run_scenario.sh'


@dataclass(frozen=True)
class ScenarioRun:
    """A started ``run_scenario.sh``: its process, its DIR (``--out``), world and ``--timeout``."""

    runner: NodeProcess
    out: Path
    world: str
    timeout: float

    def wait(self) -> int:
        """Its exit code, once it has ended (at most ``timeout`` and a minute and a half)."""
        wait_for(
            lambda: not self.runner.running(),
            self.timeout + 90,
            f'{SCRIPT} {self.world} to finish',
            interval=0.5,
            on_timeout=self.runner.describe,
        )
        return self.runner.process.returncode

    def logs(self, tail: int = 1500) -> str:
        """Its output and the last ``tail`` characters of each log in DIR, for failure messages."""
        return self.runner.describe() + ''.join(
            f'\n--- {log.name} ---\n{log.read_text(errors="replace")[-tail:]}'
            for log in sorted(self.out.glob('*.log'))
        )


def start_scenario(ros: RosHarness, world: str, *options: str, timeout: float = 150) -> ScenarioRun:
    """``run_scenario.sh world options`` started into a new folder of the harness's."""
    out = ros.root / f'out{len(ros.nodes)}'
    master = [] if {'--hosts', '--sites'} & set(options) else ['--external-master']
    argv = ['bash', SCRIPT, world, *master, *options, '--timeout', str(timeout), '--out', str(out)]
    return ScenarioRun(ros.spawn('run_scenario', argv), out, world, timeout)
