"""Test support: a private rosmaster per test, nodes as subprocesses, waits with deadlines."""

from drvs.testing.clock import ManualClock
from drvs.testing.harness import (
    NodeProcess,
    RosHarness,
    RosMaster,
    WaitTimeout,
    echo,
    free_port,
    freeze,
    points,
    processes_of_session,
    read_json_lines,
    seconds,
    wait_for,
)

__all__ = [
    'ManualClock',
    'NodeProcess',
    'RosHarness',
    'RosMaster',
    'WaitTimeout',
    'echo',
    'free_port',
    'freeze',
    'points',
    'processes_of_session',
    'read_json_lines',
    'seconds',
    'wait_for',
]
