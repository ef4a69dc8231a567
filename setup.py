"""Install the drvs package, generating drvs.msg and drvs.srv with Debian's genpy.

No catkin: running this file runs genpy's ``genmsg_py.py`` and
``gensrv_py.py`` on ``msg/*.msg`` and ``srv/*.srv``, resolving std_msgs and
geometry_msgs from Debian's definitions in /usr/share. The generated modules
are written into the source tree (so editable installs see them) and are
ignored by git.
"""

import glob
import os
import shutil
import subprocess
import sys

from setuptools import find_packages, setup

HERE = os.path.dirname(os.path.abspath(__file__))
GENPY = '/usr/lib/genpy'
SHARE = '/usr/share'
DEPENDENCIES = ('std_msgs', 'geometry_msgs')


def _python_with_genpy():
    """Return an interpreter that can import genpy (Debian's, normally)."""
    try:
        import genpy  # noqa: F401

        return sys.executable
    except ImportError:
        return '/usr/bin/python3'


def generate_interfaces():
    """Generate drvs/msg and drvs/srv from msg/ and srv/ (idempotent)."""
    includes = ['-I', 'drvs:' + os.path.join(HERE, 'msg')]
    for dep in DEPENDENCIES:
        path = os.path.join(SHARE, dep, 'msg')
        if not os.path.isdir(path):
            sys.exit(
                f'drvs: {path} not found: install the Debian package ros-{dep.replace("_", "-")}'
                ' (scripts/setup.sh does it)'
            )
        includes += ['-I', f'{dep}:{path}']
    python = _python_with_genpy()
    for kind, script in (('msg', 'genmsg_py.py'), ('srv', 'gensrv_py.py')):
        tool = os.path.join(GENPY, script)
        if not os.path.isfile(tool):
            sys.exit(
                f'drvs: {tool} not found: install the Debian package python3-genpy'
                ' (scripts/setup.sh does it)'
            )
        out = os.path.join(HERE, 'drvs', kind)
        shutil.rmtree(out, ignore_errors=True)  # a removed definition leaves nothing stale
        sources = sorted(glob.glob(os.path.join(HERE, kind, f'*.{kind}')))
        for source in sources:
            subprocess.run([python, tool, '-p', 'drvs', *includes, '-o', out, source], check=True)
        subprocess.run([python, tool, '--initpy', '-p', 'drvs', '-o', out], check=True)


def node_scripts():
    """nodes/*, installed as commands on the environment's PATH (``drvs_check_world`` ...)."""
    nodes = os.path.join(HERE, 'nodes')
    return sorted(
        os.path.join('nodes', name) for name in os.listdir(nodes) if os.path.isfile(os.path.join(nodes, name))
    )


# Every setuptools step (metadata, build, editable) needs the generated packages
# to exist, so they are made before setup() looks for them.
generate_interfaces()

setup(
    name='drvs',
    version='0.1.0',
    description='Distributed Robotic Vision Service (ROS 1)',
    packages=find_packages(include=['drvs', 'drvs.*']),
    package_data={'drvs.gateway': ['static/*']},  # the floor-plan page of drvs_gateway
    scripts=node_scripts(),
    python_requires='>=3.11',
)
