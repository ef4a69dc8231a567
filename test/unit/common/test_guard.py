"""drvs.common.guard: LoopGuard restarts a failed background loop or takes the node down (no sleeps)."""

import logging
import threading

import pytest

from drvs.common.guard import RESTART, SHUTDOWN, LoopGuard
from drvs.testing import ManualClock

WAIT = 5.0  # seconds any thread event may take before the test fails


class Fatal:
    """An on_fatal that records its calls and signals the first."""

    def __init__(self):
        self.reasons = []
        self.called = threading.Event()

    def __call__(self, reason):
        self.reasons.append(reason)
        self.called.set()


def joined(thread):
    thread.join(WAIT)
    return not thread.is_alive()


def test_loop_that_raises_once_is_restarted_then_finishes(caplog):
    fatal = Fatal()
    guard = LoopGuard(fatal, restart_delay=0)
    runs = []

    def loop():
        runs.append(len(runs))
        if len(runs) == 1:
            raise RuntimeError('first run fails')

    with caplog.at_level(logging.ERROR, logger='rosout.drvs.guard'):
        thread = guard.spawn(loop, 'renewal', RESTART)
        assert joined(thread)
    assert runs == [0, 1]
    assert guard.restarts == {'renewal': 1}
    assert guard.failure is None
    assert fatal.reasons == []
    assert guard.threads == [thread]
    assert thread.daemon and thread.name == 'renewal'


def test_shutdown_loop_failure_is_fatal_once():
    fatal = Fatal()
    stop = threading.Event()
    guard = LoopGuard(fatal, stop=stop)

    def loop():
        return 1 / 0

    first = guard.spawn(loop, 'registration', SHUTDOWN)
    assert fatal.called.wait(WAIT)
    assert joined(first)
    second = guard.spawn(lambda: [][1], 'other', SHUTDOWN)
    assert joined(second)
    reason = 'background loop registration failed: ZeroDivisionError: division by zero'
    assert fatal.reasons == [reason]
    assert guard.failure == reason
    assert stop.is_set()
    assert guard.restarts == {'registration': 0, 'other': 0}


def test_restart_escalates_after_max_restarts_within_window():
    fatal = Fatal()
    clock = ManualClock()
    guard = LoopGuard(fatal, restart_delay=0, max_restarts=2, window=60, clock=clock)
    runs = []

    def loop():
        runs.append(clock.now)
        clock.now += 10
        raise ValueError('bad frame')

    thread = guard.spawn(loop, 'worker', RESTART)
    assert joined(thread)
    assert len(runs) == 3
    assert guard.restarts == {'worker': 2}
    assert fatal.reasons == ['background loop worker failed: ValueError: bad frame (3 failures within 60 s)']
    assert guard.failure == fatal.reasons[0]


def test_failures_spread_beyond_the_window_do_not_escalate():
    fatal = Fatal()
    clock = ManualClock()
    guard = LoopGuard(fatal, restart_delay=0, max_restarts=1, window=60, clock=clock)
    runs = []

    def loop():
        runs.append(clock.now)
        clock.now += 60
        if len(runs) <= 5:
            raise ValueError('now and then')

    thread = guard.spawn(loop, 'worker', RESTART)
    assert joined(thread)
    assert len(runs) == 6
    assert guard.restarts == {'worker': 5}
    assert guard.failure is None
    assert fatal.reasons == []


def test_stop_during_restart_delay_ends_the_thread():
    fatal = Fatal()
    stop = threading.Event()
    guard = LoopGuard(fatal, stop=stop, restart_delay=3600)
    failed = threading.Event()

    def loop():
        failed.set()
        raise OSError('connection refused')

    thread = guard.spawn(loop, 'renewal', RESTART)
    assert failed.wait(WAIT)
    stop.set()
    assert joined(thread)
    assert guard.restarts == {'renewal': 0}
    assert guard.failure is None
    assert fatal.reasons == []


def test_failure_while_stopping_is_not_fatal():
    fatal = Fatal()
    stop = threading.Event()
    guard = LoopGuard(fatal, stop=stop)

    def loop():
        stop.set()
        raise ConnectionError('master went away')

    assert joined(guard.spawn(loop, 'expiry', SHUTDOWN))
    assert guard.failure is None
    assert fatal.reasons == []


def test_traceback_is_logged(caplog):
    guard = LoopGuard(Fatal())

    def failing_loop_body():
        raise KeyError('camera_3')

    with caplog.at_level(logging.ERROR, logger='rosout.drvs.guard'):
        assert joined(guard.spawn(failing_loop_body, 'watch', SHUTDOWN))
    errors = [record for record in caplog.records if record.levelno == logging.ERROR]
    assert len(errors) == 1
    message = errors[0].getMessage()
    assert message.startswith('background loop watch failed:\nTraceback (most recent call last):\n')
    assert 'in failing_loop_body' in message
    assert message.endswith("KeyError: 'camera_3'\n")
    critical = [record.getMessage() for record in caplog.records if record.levelno == logging.CRITICAL]
    assert critical == ["background loop watch failed: KeyError: 'camera_3'; stopping the node"]


def test_system_exit_in_a_loop_is_fatal():
    fatal = Fatal()
    guard = LoopGuard(fatal)
    hooked = []
    previous_hook = threading.excepthook
    threading.excepthook = lambda args: hooked.append(args.exc_type)
    try:

        def loop():
            raise SystemExit(3)

        assert joined(guard.spawn(loop, 'stray_exit', RESTART))
    finally:
        threading.excepthook = previous_hook
    assert hooked == [SystemExit]  # re-raised after failing the node
    assert fatal.reasons == ['background loop stray_exit failed: SystemExit: 3']


def test_on_fatal_that_raises_is_logged(caplog):
    def on_fatal(reason):
        raise RuntimeError('no master')

    guard = LoopGuard(on_fatal)
    with caplog.at_level(logging.ERROR, logger='rosout.drvs.guard'):
        assert joined(guard.spawn(lambda: 1 / 0, 'loop', SHUTDOWN))
    assert guard.failure == 'background loop loop failed: ZeroDivisionError: division by zero'
    assert 'on_fatal failed for: background loop loop failed' in caplog.text
    assert 'RuntimeError: no master' in caplog.text


@pytest.mark.parametrize(
    'arguments, message',
    [
        ({'restart_delay': -1}, 'restart_delay: must not be negative, got -1'),
        ({'max_restarts': -1}, 'max_restarts: must not be negative, got -1'),
        ({'window': 0}, 'window: must be positive, got 0'),
    ],
)
def test_guard_bad_arguments(arguments, message):
    with pytest.raises(ValueError) as caught:
        LoopGuard(Fatal(), **arguments)
    assert str(caught.value) == message


def test_guard_bad_policy():
    with pytest.raises(ValueError) as caught:
        LoopGuard(Fatal()).spawn(lambda: None, 'loop', 'ignore')
    assert str(caught.value) == "policy: must be 'restart' or 'shutdown', got 'ignore'"
