"""Types where they pay: mypy (basic mode, configured in pyproject.toml) over the pure packages."""

import subprocess
import sys

import pytest

from drvs.testing.harness import REPO


def test_mypy_over_the_pure_packages():
    try:
        import mypy  # noqa: F401  (Debian's python3-mypy: scripts/setup.sh installs it)
    except ImportError:
        pytest.fail('mypy is not installed: run `make setup` (Debian package python3-mypy)')
    result = subprocess.run([sys.executable, '-m', 'mypy'], cwd=REPO, capture_output=True, text=True)
    assert (
        result.returncode == 0
    ), f'mypy (see [tool.mypy] in pyproject.toml):\n{result.stdout}{result.stderr}'
