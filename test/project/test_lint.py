"""Style never drifts: ruff lint and format checks are part of the suite (configured in pyproject.toml)."""

import subprocess
import sys
from pathlib import Path

import pytest

from drvs.testing.harness import REPO

RUFF = Path(sys.executable).parent / 'ruff'


@pytest.mark.parametrize('args', [['check', '.'], ['format', '--check', '.']])
def test_ruff(args):
    result = subprocess.run([str(RUFF), *args], cwd=REPO, capture_output=True, text=True)
    assert (
        result.returncode == 0
    ), f'ruff {" ".join(args)} (fix with `make format`):\n{result.stdout}{result.stderr}'
