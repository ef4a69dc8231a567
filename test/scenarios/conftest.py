"""The whole runs of the default suite, started two at a time: ``scenario_run(name)``.

A run of scripts/run_scenario.sh is half a minute of mostly waiting for its robots to
drive, at half a core to nearly a core (tag detection): two fit on two cores and end in
about the time of the longer one (with four at once, the tags run's cameras lost its
robot). When a test asks for a run of :data:`RUNS`, the run and its partner in
:data:`PAIRS` start, each on a master of its own (drvs.testing.scenario); each module
then checks its runs as it always did. The slow variants run one at a time.
"""

from __future__ import annotations

import contextlib

import pytest

from drvs.testing import RosHarness
from drvs.testing.netns import unavailable
from drvs.testing.scenario import ScenarioRun, start_scenario


def runs() -> dict[str, tuple[str, ...]]:
    """name -> (world, run_scenario.sh options) of the default suite's runs."""
    # The crossing with watches is the one across network hosts, where they can be made here.
    hosts = () if unavailable() else ('--hosts', '--robot-link', '2mbit')
    return {
        'obstacles': ('worlds/obstacles.yaml', '--camera-source', 'render', '--requests', 'watch'),
        'selectivity': ('worlds/selectivity.yaml', '--camera-source', 'render', '--requests', 'watch'),
        'tags': ('worlds/tags.yaml', '--camera-source', 'render', '--requests', 'poll'),
        'recorded': ('worlds/localisation.yaml', '--record'),  # test_record.py
        'crossing-watch': ('worlds/crossing.yaml', '--requests', 'watch', *hosts),  # test_fleet.py
        'crossing-poll': ('worlds/crossing.yaml', '--requests', 'poll'),
    }


PAIRS = (('obstacles', 'selectivity'), ('tags', 'recorded'), ('crossing-watch', 'crossing-poll'))
"""Runs that start together: about 1.1, 1.4 and 1.4 cores while their robots drive."""


@pytest.fixture(scope='session')
def scenario_run():
    """``scenario_run(name)``: the :class:`ScenarioRun` of :func:`runs` ``[name]``, started
    with its partner the first time either is asked for (it may still be running)."""
    with contextlib.ExitStack() as stack:
        started: dict[str, ScenarioRun] = {}

        def run(name: str) -> ScenarioRun:
            if name not in started:
                known = runs()
                for each in next(pair for pair in PAIRS if name in pair):
                    started[each] = start_scenario(stack.enter_context(RosHarness()), *known[each])
            return started[name]

        yield run
