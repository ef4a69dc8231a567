"""drvs.ros.node: the scaffold every node is built on (no master: nothing here talks to one)."""

import threading

from drvs.common.health import OK, Health
from drvs.common.status import BUSY, UNAVAILABLE, Refusal
from drvs.ros.node import NodeScaffold, internal_error, refusal_response
from drvs.srv import RegisterVisionServiceResponse, WatchObjectBoundaryResponse


def scaffold(**kwargs) -> NodeScaffold:
    return NodeScaffold(lambda: Health(OK, 'fine'), **kwargs)


def test_every_runs_until_the_node_stops_and_join_waits_for_it():
    node = scaffold()
    ran = threading.Event()
    thread = node.every(0.001, ran.set, 'ticker')
    assert ran.wait(10.0)
    node.stop(join=10.0)
    assert not thread.is_alive() and node.stopped and node.failure is None


def test_a_loop_that_keeps_failing_takes_the_node_down(monkeypatch):
    reasons = []
    monkeypatch.setattr('rospy.signal_shutdown', reasons.append)
    node = scaffold()
    node.guard.restart_delay = 0.0

    def broken():
        raise RuntimeError('broken loop')

    node.spawn(broken, 'broken')
    assert node.stopping.wait(10.0)
    node.join(10.0)
    assert node.failure is not None and 'broken loop' in node.failure
    assert reasons == [node.failure]


def test_log_throttled_logs_once_per_period_and_counts_the_rest():
    node = scaffold(log_period=3600.0)
    lines = []
    log = lambda text, *args: lines.append(text % args)  # noqa: E731
    for _ in range(3):
        node.log_throttled('BUSY', log, 'refused %s', 'x')
    node._log_throttle._next['BUSY'] = 0.0  # the period has passed
    node.log_throttled('BUSY', log, 'refused %s', 'y')
    assert lines == ['refused x', 'refused y (2 more like it not logged in the last 3600 s)']


def test_counters_and_refusals_are_counted_by_name():
    node = scaffold(counters=('requests', 'refused'))
    node.counters.add(requests=2)
    node.refused(Refusal(BUSY, 'busy', 0.5))
    assert node.counters.snapshot() == {'requests': 2, 'refused': 0}
    assert node.refusals.totals() == {'BUSY': 1}


def test_a_refusal_becomes_any_response_with_its_status():
    refusal = Refusal(BUSY, 'busy: try again', 0.5)
    for response_class in (RegisterVisionServiceResponse, WatchObjectBoundaryResponse):
        response = refusal_response(response_class, refusal)
        assert (response.accepted, response.status, response.message, response.retry_after) == (
            False,
            BUSY,
            'busy: try again',
            0.5,
        )


def test_an_internal_error_is_unavailable_and_names_the_error(monkeypatch):
    logged = []
    monkeypatch.setattr('rospy.logerr', lambda *args: logged.append(args))
    try:
        raise KeyError('x')
    except KeyError as error:
        refusal = internal_error('the DRVS server', 'request', error, 1.0)
    assert refusal.status == UNAVAILABLE and refusal.retry_after == 1.0
    assert refusal.message == (
        "internal error in the DRVS server (KeyError: 'x'); it is logged there; retry later"
    )
    assert logged and 'Traceback' in logged[0][2]


def test_a_node_without_health_publishes_no_diagnostics():
    node = NodeScaffold(None)
    assert node.diagnostics is None
    node.start()
    node.stop()
    assert node.stopped
