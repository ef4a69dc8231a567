"""The import contract (docs/architecture.md): which package may import what, checked two ways.

Statically, every import statement of every module under drvs/ (those inside functions too) is
held against the rules below; dynamically, every module outside drvs.sim and the simulation glue
is imported in a subprocess where pybullet cannot be imported. A failure names the module, the
line and the import.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest

from drvs.testing.harness import REPO

PURE = (
    'drvs.common',
    'drvs.server',
    'drvs.vision',
    'drvs.robot',
    'drvs.gateway',
    'drvs.sim',
    'drvs.algorithms',
)
ROLES = ('drvs.server', 'drvs.vision', 'drvs.robot', 'drvs.gateway')
COMMON = 'drvs.common'
COMMON_MAY_IMPORT = ('drvs.common', 'drvs.algorithms')
# ROS's Python libraries; any top-level package named *_msgs or *_srvs is a message package too.
ROS_LIBRARIES = frozenset(
    {
        'rospy',
        'genpy',
        'genmsg',
        'rosgraph',
        'roslib',
        'rospkg',
        'rosbag',
        'rosservice',
        'rostopic',
        'rosnode',
        'rosmsg',
        'tf',
        'tf2_ros',
        'cv_bridge',
        'image_geometry',
        'message_filters',
        'actionlib',
    }
)
NOT_FOR_PURE = ('drvs.ros', 'drvs.msg', 'drvs.srv', 'drvs.tools')
PYBULLET = ('pybullet', 'pybullet_data', 'pybullet_utils')
# Outside drvs.sim, only these modules may import pybullet (directly or through drvs.sim):
PYBULLET_GLUE = (
    'drvs.ros.world_sim',  # the world_sim node steps the simulation
    'drvs.ros.sim_camera',  # the sim_camera node renders the scene
    'drvs.ros.render_source',  # a vision system's frames rendered from the scene (no real camera)
    'drvs.testing.tags',  # tests render printed tags through the scene
)

RULE_ROS = 'pure packages never import ROS, drvs.ros, drvs.msg, drvs.srv or drvs.tools'
RULE_ROLES = 'drvs.server, drvs.vision, drvs.robot and drvs.gateway never import one another'
RULE_COMMON = 'drvs.common imports only drvs.common and drvs.algorithms'
RULE_PYBULLET = 'nothing but drvs.sim and the simulation glue imports pybullet'


@dataclass(frozen=True)
class Violation:
    module: str
    line: int
    statement: str
    rule: str

    def __str__(self) -> str:
        return f'{self.module}:{self.line}: `{self.statement}` breaks "{self.rule}"'


def within(name: str, packages: tuple[str, ...] | str) -> bool:
    """Whether dotted ``name`` is one of ``packages`` or inside one."""
    if isinstance(packages, str):
        packages = (packages,)
    return any(name == p or name.startswith(p + '.') for p in packages)


def imported_names(node: ast.Import | ast.ImportFrom, module: str, is_package: bool) -> list[str]:
    """The dotted names an import statement reaches (``from a import b`` reaches ``a.b``)."""
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    base = node.module or ''
    if node.level:  # relative: resolve against the importing module's package
        parts = module.split('.')
        package = parts if is_package else parts[:-1]
        package = package[: len(package) - (node.level - 1)]
        base = '.'.join(package + ([base] if base else []))
    if base == '__future__':
        return []
    return [base if alias.name == '*' else f'{base}.{alias.name}' for alias in node.names]


def is_ros(name: str) -> bool:
    top = name.split('.')[0]
    return top in ROS_LIBRARIES or top.endswith(('_msgs', '_srvs')) or within(name, NOT_FOR_PURE)


def broken_rules(module: str, name: str) -> list[str]:
    """The rules that ``module`` importing ``name`` breaks."""
    rules = []
    if within(module, PURE) and is_ros(name):
        rules.append(RULE_ROS)
    role = next((r for r in ROLES if within(module, r)), None)
    if role and within(name, ROLES) and not within(name, role):
        rules.append(RULE_ROLES)
    if within(module, COMMON) and within(name, 'drvs') and not within(name, COMMON_MAY_IMPORT):
        rules.append(RULE_COMMON)
    if within(name, PYBULLET) and not within(module, 'drvs.sim') and module not in PYBULLET_GLUE:
        rules.append(RULE_PYBULLET)
    return rules


def violations(module: str, source: str, is_package: bool = False) -> list[Violation]:
    """Every import statement of ``source`` (module ``module``) that breaks a rule."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Import | ast.ImportFrom):
            continue
        rules = {
            rule for name in imported_names(node, module, is_package) for rule in broken_rules(module, name)
        }
        for rule in sorted(rules):
            found.append(Violation(module, node.lineno, ast.unparse(node), rule))
    return found


def drvs_modules() -> list[tuple[str, Path]]:
    """(dotted name, path) of every module under drvs/, generated ones included."""
    modules = []
    for path in sorted((REPO / 'drvs').rglob('*.py')):
        parts = path.relative_to(REPO).with_suffix('').parts
        if parts[-1] == '__init__':
            parts = parts[:-1]
        modules.append(('.'.join(parts), path))
    return modules


def test_every_import_statement_keeps_the_contract():
    found = []
    for module, path in drvs_modules():
        found += violations(module, path.read_text(), is_package=path.name == '__init__.py')
    assert not found, 'imports that break the contract (docs/architecture.md):\n' + '\n'.join(map(str, found))


BREAKERS = [
    ('drvs.robot.bad', 'import rospy', RULE_ROS),
    ('drvs.sim.bad', 'from sensor_msgs.msg import Image', RULE_ROS),
    ('drvs.algorithms.bad', 'def f():\n    from drvs.ros import node', RULE_ROS),
    ('drvs.vision.bad', 'from drvs import msg', RULE_ROS),
    ('drvs.server.bad', 'import drvs.tools.ask', RULE_ROS),
    ('drvs.server.bad', 'from drvs.robot.perception import Fix', RULE_ROLES),
    ('drvs.robot.bad', 'def f():\n    import drvs.vision.camera', RULE_ROLES),
    ('drvs.vision.bad', 'from ..server import registry', RULE_ROLES),
    ('drvs.common.bad', 'from drvs.sim.world import World', RULE_COMMON),
    ('drvs.common', 'from .. import vision', RULE_COMMON),
    ('drvs.vision.bad', 'import pybullet as p', RULE_PYBULLET),
    ('drvs.ros.frame_sources', 'import pybullet_data', RULE_PYBULLET),
    ('drvs.testing.harness', 'from pybullet import connect', RULE_PYBULLET),
]


@pytest.mark.parametrize(('module', 'source', 'rule'), BREAKERS)
def test_the_checker_reports_each_rule_by_name(module, source, rule):
    found = violations(module, source, is_package=module == 'drvs.common')
    assert [v.rule for v in found] == [rule], found
    assert str(found[0]).startswith(f'{module}:{found[0].line}: `')


def test_the_checker_lets_the_allowed_imports_pass():
    allowed = textwrap.dedent(
        """
        from __future__ import annotations
        import numpy, cv2
        from drvs.common.status import BUSY
        from drvs.algorithms import parse_algorithm
        from . import status
        """
    )
    assert violations('drvs.common.ok', allowed) == []
    assert violations('drvs.algorithms.ok', 'def f():\n    from drvs.vision.optics import CameraModel') == []
    assert violations('drvs.sim.ok', 'import pybullet\nfrom drvs.vision.frame import Frame') == []
    assert violations('drvs.ros.world_sim', 'import pybullet\nimport rospy') == []


# Imports every module it is given with pybullet unimportable; prints {module: chain} as JSON.
PROBE = """
import importlib, json, sys, traceback
for name in %(blocked)r:
    sys.modules[name] = None
repo = %(repo)r
failed = {}
for module in %(modules)r:
    try:
        importlib.import_module(module)
    except Exception as error:
        chain = [
            f'{frame.filename[len(repo) + 1:]}:{frame.lineno}: {frame.line}'
            for frame in traceback.extract_tb(error.__traceback__)
            if frame.filename.startswith(repo + '/drvs/')
        ]
        failed[module] = chain + [f'{type(error).__name__}: {error}']
print(json.dumps(failed))
"""


def test_everything_but_the_simulation_imports_without_pybullet():
    modules = [m for m, _ in drvs_modules() if not within(m, 'drvs.sim') and m not in PYBULLET_GLUE]
    assert 'drvs.ros.node' in modules and 'drvs.vision.frame' in modules
    probe = PROBE % {'blocked': PYBULLET, 'repo': str(REPO), 'modules': modules}
    result = subprocess.run(
        [sys.executable, '-c', probe], cwd=REPO, capture_output=True, text=True, timeout=240
    )
    assert result.returncode == 0, result.stderr
    failed = json.loads(result.stdout.splitlines()[-1])
    report = [f'{module}:\n    ' + '\n    '.join(chain) for module, chain in failed.items()]
    assert not failed, 'modules that reach pybullet (or fail to import) without it:\n' + '\n'.join(report)
