"""Who may change what in DRVS, per-caller rate limits, and where the nodes listen.

Already covered in ``test/live/test_server.py``, not repeated here:
``test_invalid_inputs_are_refused_and_the_server_keeps_serving[register]`` — a node
(``/unnamed``) may not register or move (a new field of view) another node's service,
may not unregister it, and a camera node (``/thief``) may not claim it; the original
field of view stays routed and published. ``[detect]`` — a callback service of another
type (a vision system's DetectObjectBoundary) is refused ``INVALID``, and a caller of
the wrong service type is refused by the transport while the server keeps serving.

Added here: a move or an unregistration attempted by another *registered vision
system*; callback services of other types provided by the server itself (its own
services, rospy's ``get_loggers``) and a topic name; the rate limit per caller id
(``RATE_LIMITED`` with ``retry_after`` for one caller while another is served, and
served again once ``retry_after`` has passed); the addresses every DRVS process listens
on with ``ROS_HOSTNAME=127.0.0.1``; and what ``scripts/env.sh`` sets.

Limits of ROS 1, which these tests do not pretend to close: caller ids are not
authenticated. Any process can send ``callerid=/vs1`` in its TCPROS handshake and
then move or unregister vs1's service (``test_hostile_input``'s fuzz does exactly that
to reach the accepting paths). ``test_the_server_refuses_to_register_its_own_service``
shows the worst case of it: a forwarding loop.
"""

from __future__ import annotations

import os
import re
import subprocess
import time

import psutil
import pytest
from geometry_msgs.msg import Polygon
from test_server import CALLBACK, COLOUR, square

from drvs.common import status
from drvs.msg import BoundingBox
from drvs.ros.conversions import points_to_polygon
from drvs.ros.service_client import ServiceClient
from drvs.srv import DetectObjectBoundary, RegisterVisionService
from drvs.testing import wait_for
from drvs.testing.harness import REPO

pytestmark = pytest.mark.shared_master  # see test/conftest.py

DETECT = '/drvs/detect_object_boundary'
REGISTER = '/drvs/register_vision_service'
VS1 = '/vs1/detect_object_boundary'
VS2 = '/vs2/detect_object_boundary'


def registration(service_name, field_of_view):
    return RegisterVisionService._request_class(service_name=service_name, field_of_view=field_of_view)


def detect_request(box=(0.5, 0.5, 1.0, 1.0), request_id='r', callback=CALLBACK):
    return DetectObjectBoundary._request_class(
        algorithm=COLOUR,
        region_of_interest=BoundingBox(*box),
        callback_service=callback,
        request_id=request_id,
    )


def forwarded_ids(graph, name):
    return [r['request_id'] for r in graph.forwards(name)]


def test_a_vision_system_may_not_move_or_unregister_another(ros, make_graph):
    g = make_graph(lease=3600)
    g.camera('vs1', square(0, 0, 2, 2))
    g.camera('vs2', square(5, 5, 6, 6))
    # vs2, itself a registered provider, speaks for itself (its own caller id) about vs1's service.
    as_vs2 = ServiceClient(REGISTER, RegisterVisionService, 10.0, caller_id='/vs2')
    try:
        moved = as_vs2.call(registration(VS1, points_to_polygon(square(5, 5, 6, 6))))
        dropped = as_vs2.call(registration(VS1, Polygon()))
        renewed = as_vs2.call(registration(VS2, points_to_polygon(square(5, 5, 6, 6))))
    finally:
        as_vs2.close()
    assert (moved.status, moved.accepted, moved.message) == (
        status.INVALID,
        False,
        f'service_name: {VS1} is provided by /vs1, not by the caller /vs2; '
        'a node may register only its own service',
    )
    assert (dropped.status, dropped.accepted, dropped.message) == (
        status.INVALID,
        False,
        f'service_name: {VS1} was registered by /vs1; /vs2 may not unregister it',
    )
    assert (renewed.status, renewed.message) == (status.ACCEPTED, f'renewed {VS2}; lease 3600 s')
    # Routing is unchanged: vs1's square still goes to vs1 alone, vs2's to vs2 alone.
    assert g.detect((0.5, 0.5, 1.0, 1.0), request_id='in vs1').vision_systems == 1
    assert g.detect((5.2, 5.2, 5.5, 5.5), request_id='in vs2').vision_systems == 1
    wait_for(lambda: forwarded_ids(g, 'vs1') == ['in vs1'], 10, 'the forward to vs1')
    wait_for(lambda: forwarded_ids(g, 'vs2') == ['in vs2'], 10, 'the forward to vs2')
    assert [
        (v['service_name'], v['provider'], v['field_of_view']) for v in g.registry_topic()['vision_systems']
    ] == [
        (VS1, '/vs1', square(0, 0, 2, 2)),
        (VS2, '/vs2', square(5, 5, 6, 6)),
    ]


def test_a_callback_service_of_another_kind_is_invalid(ros, make_graph):
    g = make_graph()
    g.camera('vs1', square(0, 0, 2, 2))
    expected = 'expected drvs/CallbackCoordinates'
    cases = [
        (DETECT, f'callback_service: {DETECT} is of type drvs/DetectObjectBoundary, {expected}'),
        (REGISTER, f'callback_service: {REGISTER} is of type drvs/RegisterVisionService, {expected}'),
        (
            '/drvs/get_loggers',
            f'callback_service: /drvs/get_loggers is of type roscpp/GetLoggers, {expected}',
        ),
        ('/rosout', 'callback_service: /rosout is not known to the ROS master'),  # a topic, not a service
        ('/drvs/registry', 'callback_service: /drvs/registry is not known to the ROS master'),
    ]
    for callback, message in cases:
        answer = g.detect((0.5, 0.5, 1.0, 1.0), request_id=f'to {callback}', callback=callback)
        assert (answer.status, answer.accepted, answer.vision_systems, answer.message) == (
            status.INVALID,
            False,
            0,
            message,
        )
    assert g.detect((0.5, 0.5, 1.0, 1.0), request_id='good callback').vision_systems == 1
    wait_for(lambda: forwarded_ids(g, 'vs1') == ['good callback'], 10, 'the good forward alone')


def test_the_server_refuses_to_register_its_own_service(ros, make_graph):
    g = make_graph(lease=3600)
    g.camera('cam', square(0, 0, 2, 2))
    spoofed = ServiceClient(REGISTER, RegisterVisionService, 10.0, caller_id='/drvs')
    try:
        answer = spoofed.call(registration(DETECT, points_to_polygon(square(0, 0, 2, 2))))
    finally:
        spoofed.close()
    assert g.detect((0.5, 0.5, 1.0, 1.0), request_id='once').vision_systems == 1
    # One request, one forward; with the loop, cam gets ~100 (the burst of /drvs's bucket).
    wait_for(lambda: forwarded_ids(g, 'cam'), 10, 'the forward to cam')
    assert forwarded_ids(g, 'cam') == ['once']
    assert (answer.status, answer.message) == (
        status.INVALID,
        'service_name: the caller /drvs is the DRVS server itself; forwarding to it would loop',
    )


RATE, BURST = 5, 5
LIMITED = re.compile(
    r'rate limited: /a sends more than 5 requests/s \(bursts of 5\); retry after (\d+\.\d{3}) s'
)


def test_a_fast_caller_is_rate_limited_while_another_is_served(ros, make_graph):
    g = make_graph(max_requests_per_s=RATE, burst=BURST)
    a = ServiceClient(DETECT, DetectObjectBoundary, 10.0, caller_id='/a')
    a_register = ServiceClient(REGISTER, RegisterVisionService, 10.0, caller_id='/a')
    b = ServiceClient(DETECT, DetectObjectBoundary, 10.0, caller_id='/b')
    try:
        # /a sends as fast as it can: its burst is served, then it is refused. Each refused
        # detect is followed at once by a registration from /a: both services share its bucket,
        # so (unless a token refilled in between, then it goes on) that is refused too.
        unregister = registration('/a/nothing', Polygon())
        started, answers = time.monotonic(), []
        while len(answers) < 100:
            answers.append(a.call(detect_request(request_id=f'a{len(answers)}')))
            if answers[-1].status == status.RATE_LIMITED:
                refused, refused_at = answers[-1], time.monotonic()
                answers.append(a_register.call(unregister))
                if answers[-1].status == status.RATE_LIMITED:
                    break
        assert answers[-1].status == status.RATE_LIMITED and not answers[-1].accepted, answers
        assert refused.status == status.RATE_LIMITED and not refused.accepted, refused
        statuses = [answer.status for answer in answers]
        first_refusal = statuses.index(status.RATE_LIMITED)
        # At least the burst, no more than what refilled while sending (plus one for rounding).
        assert BURST <= first_refusal <= BURST + RATE * (refused_at - started) + 1, (
            statuses,
            refused_at - started,
        )
        assert set(statuses) == {status.ACCEPTED, status.RATE_LIMITED}, statuses
        for answer in answers[-2:]:
            assert 0 < answer.retry_after <= 1 / RATE + 1e-6, answer
        assert float(LIMITED.fullmatch(refused.message).group(1)) == pytest.approx(
            refused.retry_after, abs=1e-3
        )

        # At the same moment another caller is served.
        other = b.call(detect_request(request_id='b0'))
        assert (other.status, other.accepted, other.retry_after) == (status.ACCEPTED, True, 0.0), other

        # /a polls (a refusal takes no token): refused until retry_after has passed, then served.
        polls = []

        def served_again():
            polls.append((time.monotonic(), a.call(detect_request(request_id=f'poll{len(polls)}'))))
            return polls[-1][1].status == status.ACCEPTED

        wait_for(served_again, refused.retry_after + 5.0, '/a to be served again', interval=0.01)
        assert all(answer.status == status.RATE_LIMITED for _, answer in polls[:-1]), polls
        # Not before retry_after (less the time the refusal took to reach us).
        assert polls[-1][0] - refused_at >= refused.retry_after - 0.05, (polls[-1][0] - refused_at, refused)
    finally:
        for client in (a, a_register, b):
            client.close()
    assert g.server.running()


# -- where DRVS listens --------------------------------------------------------------------------


def listening(pid: int) -> list[tuple[str, int]]:
    """(address, port) of every listening TCP socket of ``pid`` and its children."""
    process = psutil.Process(pid)
    found = []
    for each in [process, *process.children(recursive=True)]:
        found += [
            (c.laddr.ip, c.laddr.port) for c in each.connections(kind='tcp') if c.status == psutil.CONN_LISTEN
        ]
    return sorted(found)


def test_every_drvs_process_listens_on_loopback_only(ros):
    assert ros.env['ROS_HOSTNAME'] == '127.0.0.1'
    server = ros.start_node('nodes/drvs_server', name='drvs')
    ros.wait_for_service(DETECT, node=server)
    vision = ros.start_node('nodes/vision_system', name='vs1', params={'world': 'test/worlds/small.yaml'})
    ros.wait_for_service(VS1, node=vision)
    processes = {'rosmaster': ros.master.node.pid, 'drvs_server': server.pid, 'vision_system': vision.pid}
    found = {name: listening(pid) for name, pid in processes.items()}
    print('listening sockets:', found)
    # The master's XML-RPC port; each node's XML-RPC and TCPROS ports.
    assert [port for _, port in found['rosmaster']] == [ros.master.port]
    assert len(found['drvs_server']) == 2 and len(found['vision_system']) == 2, found
    assert {address for sockets in found.values() for address, _ in sockets} == {'127.0.0.1'}, found


@pytest.mark.parametrize(
    'given, expected',
    [
        ({}, '127.0.0.1'),
        ({'ROS_HOSTNAME': 'robot.local'}, 'robot.local'),
        ({'ROS_IP': '192.168.1.7'}, ''),  # ROS_IP is the user's choice; rospy uses it
    ],
    ids=['unset', 'ROS_HOSTNAME set', 'ROS_IP set'],
)
def test_env_sh_sets_a_loopback_hostname_unless_the_user_chose(given, expected):
    env = {k: v for k, v in os.environ.items() if k not in ('ROS_HOSTNAME', 'ROS_IP')}
    result = subprocess.run(
        ['bash', '-c', 'source scripts/env.sh >/dev/null 2>&1; printf %s "${ROS_HOSTNAME:-}"'],
        env={**env, **given},
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert (result.returncode, result.stdout) == (0, expected), result.stderr


def test_run_scenario_sources_env_sh_before_it_starts_anything():
    script = (REPO / 'scripts' / 'run_scenario.sh').read_text().splitlines()
    sourced = [
        i for i, line in enumerate(script) if re.fullmatch(r'\s*source "\$root/scripts/env\.sh"', line)
    ]
    started = [i for i, line in enumerate(script) if re.match(r'\s*start \w+ ', line)]
    assert sourced and started and sourced[0] < started[0], (sourced, started)
    # Nothing between clears ROS_HOSTNAME or ROS_IP.
    assert not [line for line in script if re.search(r'unset[^#]*\bROS_(HOSTNAME|IP)\b', line)]
