"""`pip install .` from a fresh clone gives a working DRVS: every sub-package, the generated messages,
the nodes as commands.

The clone is ``git clone`` of this checkout (its HEAD) with the working tree's changes to tracked
files applied on top (``git diff HEAD --binary | git apply``), so the test checks the tree as it
would be committed, uncommitted edits included, while untracked files and generated code stay out
exactly as they would from a fresh clone. The venv is made from Debian's /usr/bin/python3 with
--system-site-packages (as scripts/setup.sh makes .venv), and pip builds and installs without
network (--no-build-isolation --no-deps --no-index).
"""

import os
import subprocess
from pathlib import Path

from drvs.testing.harness import REPO

SUB_PACKAGES = {
    'drvs.algorithms',
    'drvs.common',
    'drvs.gateway',
    'drvs.msg',
    'drvs.robot',
    'drvs.ros',
    'drvs.server',
    'drvs.sim',
    'drvs.srv',
    'drvs.testing',
    'drvs.tools',
    'drvs.vision',
}

# Imports each sub-package of the installed drvs; prints one line per package: its name and file.
SUB_PACKAGE_FILES = """
import importlib, pkgutil, drvs
for info in pkgutil.iter_modules(drvs.__path__, 'drvs.'):
    if info.ispkg:
        print(info.name, importlib.import_module(info.name).__file__)
"""


def run(command, cwd, **kwargs):
    result = subprocess.run(command, cwd=cwd, capture_output=True, text=True, **kwargs)
    assert (
        result.returncode == 0
    ), f'{" ".join(map(str, command))} (exit {result.returncode}):\n{result.stdout}{result.stderr}'
    return result.stdout


def clone(target: Path) -> Path:
    """A fresh clone of this checkout, with its uncommitted changes to tracked files applied."""
    run(['git', 'clone', '-q', str(REPO), str(target)], cwd=REPO)
    changes = subprocess.run(
        ['git', 'diff', 'HEAD', '--binary'], cwd=REPO, capture_output=True, check=True
    ).stdout
    if changes:
        subprocess.run(['git', 'apply', '--whitespace=nowarn'], cwd=target, input=changes, check=True)
    return target


def test_pip_install_from_a_fresh_clone_installs_every_sub_package_and_the_nodes(tmp_path):
    project = clone(tmp_path / 'clone')
    venv = tmp_path / 'venv'
    run(['/usr/bin/python3', '-m', 'venv', '--system-site-packages', str(venv)], cwd=tmp_path)
    # Nothing of the checkout on the path, no index to reach.
    env = {k: v for k, v in os.environ.items() if k not in ('PYTHONPATH', 'VIRTUAL_ENV')}
    env.update(PATH=f'{venv / "bin"}:{env["PATH"]}', PIP_NO_INDEX='1', PIP_DISABLE_PIP_VERSION_CHECK='1')
    python = venv / 'bin/python'
    run(
        [python, '-m', 'pip', 'install', '-q', '--no-build-isolation', '--no-deps', str(project)],
        cwd=tmp_path,
        env=env,
    )
    outside = tmp_path / 'elsewhere'
    outside.mkdir()

    check = venv / 'bin/drvs_check_world'
    assert (
        check.is_file()
    ), f'pip install . did not install the nodes as commands: {sorted(os.listdir(venv / "bin"))}'
    out = run(['drvs_check_world', str(project / 'worlds/obstacles.yaml')], cwd=outside, env=env)
    assert out == f'{project / "worlds/obstacles.yaml"}: ok\n'

    site = Path(
        run(
            [python, '-c', 'import sysconfig; print(sysconfig.get_path("purelib"))'], cwd=outside, env=env
        ).strip()
    )
    assert site.is_relative_to(venv)
    imported = dict(
        line.split() for line in run([python, '-c', SUB_PACKAGE_FILES], cwd=outside, env=env).splitlines()
    )
    assert set(imported) == SUB_PACKAGES
    elsewhere = [
        f'{name}: {path}' for name, path in imported.items() if not Path(path).is_relative_to(site / 'drvs')
    ]
    assert not elsewhere, 'sub-packages not imported from the venv:\n' + '\n'.join(elsewhere)
    # Every module, not only the packages' __init__ (pybullet, a PyPI wheel, is not in this venv).
    tracked = run(['git', 'ls-files', 'drvs/*.py'], cwd=project).split()
    missing = [name for name in tracked if not (site / name).is_file()]
    assert not missing, 'modules pip install . left out:\n' + '\n'.join(missing)
    pages = run(['git', 'ls-files', 'drvs/gateway/static/*'], cwd=project).split()  # package_data
    assert pages and not [
        name for name in pages if not (site / name).is_file()
    ], 'the floor-plan page is missing'
    for generated in ('drvs/msg/_RobotStatus.py', 'drvs/srv/_DetectObjectBoundary.py'):
        assert (site / generated).is_file()
