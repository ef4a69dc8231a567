"""Algorithm plugins: test/plugin_example (``dark:LEVEL``) installed as a user would, found by every
process at start, run by a vision system and checked by the server.

The example package is installed into this venv for the module's tests and uninstalled after
them, also when they fail. Processes started meanwhile see it: what each of them loads is
checked in fresh interpreters and nodes, never in this one (whose metadata may be cached).
"""

import importlib.util
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest
from shapely.geometry import Polygon

from drvs.algorithms import AlgorithmError
from drvs.common.status import ACCEPTED, INVALID, UNSUPPORTED
from drvs.sim.world_file import load_world
from drvs.testing import read_json_lines, wait_for
from drvs.testing.detect import detect
from drvs.testing.harness import parse_echo
from drvs.vision.frame import Frame

pytestmark = pytest.mark.shared_master  # see test/conftest.py

REPO = Path(__file__).resolve().parents[2]
PLUGIN = REPO / 'test' / 'plugin_example'
DISTRIBUTION = 'drvs-example-plugin'
WORLD = 'test/worlds/small.yaml'
CALLBACK = '/robot/callback_coordinates'
CRATE_REGION = (0.8, 0.6, 1.6, 1.4)  # around the crate (x 1.0-1.4, y 0.8-1.2); nothing else dark in it
BROKEN = (
    'algorithm plugin broken = drvs_example_plugin:Missing does not load: '
    "AttributeError: module 'drvs_example_plugin' has no attribute 'Missing'"
)


def pip(*args: str) -> subprocess.CompletedProcess:
    """This venv's pip, offline."""
    return subprocess.run(
        [sys.executable, '-m', 'pip', '--disable-pip-version-check', '--no-input', *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )


def fresh_python(code: str) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter of this venv: it finds the plugins as a starting node does."""
    return subprocess.run(
        [sys.executable, '-c', textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO,
    )


@pytest.fixture(scope='module')
def plugin():
    """test/plugin_example installed (editable) into this venv for the module's tests."""
    pip('uninstall', '-y', DISTRIBUTION)  # a leftover of an interrupted run, if any
    try:
        result = pip('install', '--no-index', '--no-build-isolation', '--no-deps', '-e', str(PLUGIN))
        assert result.returncode == 0, result.stdout + result.stderr
        result = fresh_python(
            """
            import importlib.metadata, json
            entry_points = importlib.metadata.entry_points(group='drvs.algorithms')
            print(json.dumps({e.name: e.value for e in entry_points}))
            """
        )
        assert result.returncode == 0, result.stderr
        assert json.loads(result.stdout) == {
            'dark': 'drvs_example_plugin:Dark',
            'broken': 'drvs_example_plugin:Missing',
        }
        yield
    finally:
        result = pip('uninstall', '-y', DISTRIBUTION)
        assert result.returncode == 0, result.stdout + result.stderr


@pytest.fixture(scope='module')
def dark_module():
    """The example's module, imported from its file (no installation needed)."""
    spec = importlib.util.spec_from_file_location('drvs_example_plugin', PLUGIN / 'drvs_example_plugin.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# -- the algorithm itself -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ('params', 'message'),
    [
        ('', 'algorithm: dark needs LEVEL, an integer 0-255, e.g. dark:100'),
        ('bright', "algorithm: dark LEVEL must be an integer 0-255, got 'bright'"),
        ('1.5', "algorithm: dark LEVEL must be an integer 0-255, got '1.5'"),
        ('100:5', "algorithm: dark LEVEL must be an integer 0-255, got '100:5'"),
        ('256', 'algorithm: dark LEVEL must be in 0-255, got 256'),
        ('-1', 'algorithm: dark LEVEL must be in 0-255, got -1'),
    ],
)
def test_dark_refuses_bad_levels_naming_the_problem(dark_module, params, message):
    with pytest.raises(AlgorithmError) as error:
        dark_module.Dark().parse(params)
    assert str(error.value) == message


def test_dark_outlines_the_regions_darker_than_the_level_on_their_pixel_edges(dark_module):
    image = np.full((60, 80, 3), 255, np.uint8)
    cv2.rectangle(image, (10, 20), (29, 39), (60, 60, 60), -1)  # columns 10-29, rows 20-39: dark
    cv2.rectangle(image, (50, 5), (69, 24), (150, 150, 150), -1)  # grey 150: not below 100
    cv2.rectangle(image, (50, 40), (53, 43), (0, 0, 0), -1)  # 16 pixels: below the 20-pixel minimum
    dark = dark_module.Dark()
    (found,) = dark.detect(Frame(image, None, None, 0.0), dark.parse('100'))
    assert found.label == 'dark'
    assert (found.area, found.height, found.keep_order) == (400.0, None, False)
    assert found.confidence == 0.0  # a plugin that does not say: unknown
    assert Polygon(found.outline).bounds == (10.0, 20.0, 30.0, 40.0)
    assert len(dark.detect(Frame(image, None, None, 0.0), dark.parse('151'))) == 2
    assert dark.detect(Frame(image, None, None, 0.0), dark.parse('60')) == []  # below, not at


def test_the_tutorial_shows_the_example_as_it_is():
    section = (REPO / 'docs' / 'tutorials' / 'adding-an-algorithm.md').read_text()
    code = section.split('```python\n', 1)[1].split('```', 1)[0]
    assert code == (PLUGIN / 'drvs_example_plugin.py').read_text()
    entry_point = '[project.entry-points."drvs.algorithms"]\ndark = "drvs_example_plugin:Dark"\n'
    assert entry_point in section.split('```toml\n', 1)[1].split('```', 1)[0]
    assert entry_point in (PLUGIN / 'pyproject.toml').read_text()


# -- discovery --------------------------------------------------------------------------------------


def test_a_fresh_interpreter_loads_the_plugin_and_leaves_out_the_broken_one(plugin):
    result = fresh_python(
        """
        import json, logging
        logging.basicConfig(format='%(levelname)s %(name)s: %(message)s')
        from drvs.algorithms import load_algorithms, parse_algorithm
        algorithms = load_algorithms()
        dark = algorithms.get('dark')
        print(json.dumps({
            'names': algorithms.names(),
            'syntax': dark.syntax,
            'params': algorithms.parse('dark:100').params,
            'shared': parse_algorithm('dark:7').params,
        }))
        """
    )
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout) == {
        'names': ['apriltag', 'colour', 'dark', 'elevation', 'foreground', 'motion'],
        'syntax': 'dark:LEVEL',
        'params': 100,
        'shared': 7,
    }
    assert f'ERROR rosout.drvs.algorithms: {BROKEN}' in result.stderr.splitlines()


# -- end to end -------------------------------------------------------------------------------------


def registry_entry(ros, service: str) -> dict | None:
    """The server's registry entry of ``service`` (from the latched ~registry topic), or None."""
    result = ros.run('rostopic echo -n 1 /drvs/registry', timeout=30)
    if result.returncode != 0:
        return None
    registry = parse_echo(result.stdout.split('\n---')[0])
    return next((e for e in registry['vision_systems'] if e['service_name'] == service), None)


def test_a_vision_system_runs_the_plugin_and_the_server_checks_its_parameters(plugin, graph):
    ros, world = graph, load_world(WORLD)
    server = ros.start_node('nodes/drvs_server', name='drvs')
    ros.wait_for_service('/drvs/detect_object_boundary', node=server)
    vs1 = ros.start_node('nodes/vision_system', name='vs1', params={'world': WORLD})
    output = ros.root / 'callbacks.jsonl'
    recorder = ros.start_node('test/nodes/callback_recorder.py', name='recorder', params={'output': output})
    ros.wait_for_service(CALLBACK, node=recorder)

    # Both found the plugin at start, and said which one they could not load.
    entry = wait_for(
        lambda: registry_entry(ros, '/vs1/detect_object_boundary'),
        30,
        'vs1 to register',
        on_timeout=ros.describe,
    )
    assert 'dark' in entry.get('algorithms', []), entry
    assert BROKEN in vs1.log() and BROKEN in server.log()

    # dark:100 is forwarded to vs1, which finds the crate (grey 60 on a white floor) where it stands.
    reply = detect('/drvs/detect_object_boundary', 'dark:100', CRATE_REGION, 'crate')
    assert (reply.accepted, reply.status, reply.vision_systems) == (True, ACCEPTED, 1), reply.message
    (callback,) = wait_for(
        lambda: [c for c in read_json_lines(output) if c['request_id'] == 'crate'],
        30,
        'the callback for dark:100',
        on_timeout=ros.describe,
    )
    assert (callback['algorithm'], callback['vision_system']) == ('dark:100', '/vs1/detect_object_boundary')
    (outline,) = (Polygon(points) for points in callback['objects'])
    truth = Polygon(world.objects[0].footprint())
    assert outline.centroid.distance(truth.centroid) <= 0.03  # 160x120: about 2 cm a pixel
    assert outline.intersection(truth).area / outline.union(truth).area >= 0.8

    # The label, as a user sees it (drvs_ask prints each object's label before its bounds).
    roi = ' '.join(str(v) for v in CRATE_REGION)
    result = ros.run(f'drvs_ask dark:100 --roi {roi} --wait 2')  # it waits all of --wait
    assert result.returncode == 0, result.stdout + result.stderr
    assert [line.split()[:2] for line in result.stdout.splitlines() if line.startswith('  [')] == [
        ['[0]', 'dark']
    ]

    # The server knows the plugin too, so it refuses bad parameters itself, with the plugin's words.
    reply = detect('/drvs/detect_object_boundary', 'dark:999', CRATE_REGION, 'bad')
    assert (reply.accepted, reply.status, reply.vision_systems, reply.message) == (
        False,
        INVALID,
        0,
        'algorithm: dark LEVEL must be in 0-255, got 999',
    )
    # Routing by capability: the plugin's name is among those the registered vision systems run.
    reply = detect('/drvs/detect_object_boundary', 'sift:1', CRATE_REGION, 'unknown')
    assert (reply.accepted, reply.status, reply.message) == (
        False,
        UNSUPPORTED,
        "algorithm: no registered vision system runs 'sift'; "
        'available: apriltag, colour, dark, elevation, foreground, motion',
    )
    assert vs1.running() and server.running()
