"""Test support: a private rosmaster per test, nodes as subprocesses, waits with deadlines."""

from drvs.testing.clock import ManualClock
from drvs.testing.harness import (
    NodeProcess,
    RosHarness,
    RosMaster,
    WaitTimeout,
    free_port,
    processes_of_session,
    read_json_lines,
    wait_for,
)

__all__ = [
    'ManualClock',
    'NodeProcess',
    'RosHarness',
    'RosMaster',
    'WaitTimeout',
    'free_port',
    'processes_of_session',
    'read_json_lines',
    'wait_for',
]
