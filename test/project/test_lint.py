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


def test_test_modules_have_unique_basenames():
    """pytest imports test modules by basename (prepend mode): two files of one name in different
    folders stop the whole collection ("import file mismatch")."""
    root = Path(__file__).resolve().parents[1]
    seen: dict[str, list[str]] = {}
    for path in sorted(root.rglob('test_*.py')):
        seen.setdefault(path.name, []).append(str(path.relative_to(root)))
    assert {name: paths for name, paths in seen.items() if len(paths) > 1} == {}
