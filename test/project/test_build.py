"""Catkin-free generation of drvs.msg / drvs.srv: idempotent and follows edits.

That a plain (non-editable) ``pip install .`` generates them is test_packaging's business.
"""

import shutil
import subprocess
import sys

from drvs.testing.harness import REPO


def copy_project(target):
    """A copy of the tracked files (as a fresh clone has them), without generated code."""
    files = subprocess.run(['git', 'ls-files'], cwd=REPO, capture_output=True, text=True, check=True).stdout
    for name in files.split():
        source = REPO / name
        if source.is_file():
            (target / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target / name)
    return target


def generate(project):
    subprocess.run([sys.executable, 'setup.py', '--name'], cwd=project, check=True, capture_output=True)
    return {p.name: p.read_text() for p in sorted((project / 'drvs').glob('*/_[A-Z]*.py'))}


def test_generation_is_idempotent_and_follows_an_edited_srv(tmp_path):
    project = copy_project(tmp_path)
    first = generate(project)
    definitions = sorted((project / 'msg').glob('*.msg')) + sorted((project / 'srv').glob('*.srv'))
    assert len(definitions) >= 10  # 7 messages, 3 services
    assert set(first) == {f'_{path.stem}.py' for path in definitions}  # one module per definition
    assert generate(project) == first
    srv = project / 'srv/DetectObjectBoundary.srv'
    srv.write_text(srv.read_text().replace('string request_id', 'string request_id\nuint8 priority'))
    edited = generate(project)
    assert "'priority'" in edited['_DetectObjectBoundary.py']
    assert "'priority'" not in first['_DetectObjectBoundary.py']
