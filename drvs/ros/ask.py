"""``drvs_ask``: ask DRVS one question from a terminal and print the answers.

It serves a temporary drvs/CallbackCoordinates service, sends one
DetectObjectBoundary request to the server with that service as the callback,
prints the server's acknowledgement and then every vision system's callback
(outlines in ``map``) until ``--wait`` seconds have passed.

A temporary refusal (``BUSY``, ``RATE_LIMITED``, ``UNAVAILABLE``) or an unreachable
server is retried after the server's ``retry_after`` (with jitter,
:func:`drvs.retry.retry_delay`) until ``--timeout`` seconds have passed; ``INVALID``
is final. Exit codes: 0 when at least one vision system called back, 1 when none
did, 2 when the request was refused or could not be sent.
"""

from __future__ import annotations

import argparse
import itertools
import os
import queue
import sys
import time

import rospy

from drvs.algorithms import AlgorithmError, default_algorithms, parse_algorithm, split_algorithm
from drvs.msg import BoundingBox
from drvs.retry import retry_delay
from drvs.ros.conversions import polygon_to_points
from drvs.ros.service_client import ServiceCallError, ServiceClient
from drvs.srv import (
    CallbackCoordinates,
    CallbackCoordinatesResponse,
    DetectObjectBoundary,
    DetectObjectBoundaryRequest,
)
from drvs.status import ACCEPTED, is_temporary
from drvs.status import name as status_name


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog='drvs_ask',
        description='Ask DRVS where the objects of one algorithm are, and print the outlines.',
    )
    parser.add_argument('algorithm', help='NAME:PARAMS, e.g. colour:0,0,150,80,80,255')
    parser.add_argument(
        '--roi',
        nargs=4,
        type=float,
        metavar=('MIN_X', 'MIN_Y', 'MAX_X', 'MAX_Y'),
        default=[0.0, 0.0, 1e3, 1e3],
        help='region of interest in map, metres (default: everything from (0, 0))',
    )
    parser.add_argument('--wait', type=float, default=2.0, help='seconds to wait for callbacks (default 2)')
    parser.add_argument(
        '--timeout',
        type=float,
        default=10.0,
        help='seconds to keep retrying while DRVS is busy, rate-limits or is unreachable (default 10)',
    )
    parser.add_argument('--server', default='/drvs/detect_object_boundary', help='the DRVS server service')
    args = parser.parse_args(argv)
    try:  # as the server does: in full what this installation has, else the syntax only (a plugin)
        name, _ = split_algorithm(args.algorithm)
        if name in default_algorithms():
            parse_algorithm(args.algorithm)
    except AlgorithmError as error:
        parser.error(str(error))
    return args


def format_callback(request) -> str:
    lines = [
        f'{request.vision_system} (frame at {request.stamp.to_sec():.3f}): {len(request.objects)} object(s)'
    ]
    for i, detected in enumerate(request.objects):
        box = detected.bounding_box
        points = ' '.join(f'({x:.3f}, {y:.3f})' for x, y in polygon_to_points(detected.boundary))
        label = f' {detected.label}' if detected.label else ''
        lines.append(
            f'  [{i}]{label} bounds x {box.min_x:.3f}..{box.max_x:.3f}, y {box.min_y:.3f}..{box.max_y:.3f}'
        )
        lines.append(f'      outline {points}')
    return '\n'.join(lines)


def send_with_retries(server: str, request, timeout: float):
    """Send ``request`` to ``server``, retrying temporary refusals and failed calls for ``timeout`` seconds.

    Returns the first final response (ACCEPTED or INVALID), or the last temporary
    refusal once time is up.

    :raises ServiceCallError: the last call failed and time is up.
    """
    deadline = time.monotonic() + timeout
    client = ServiceClient(server, DetectObjectBoundary, timeout=min(5.0, timeout))
    try:
        for attempt in itertools.count():
            try:
                reply = client.call(request)
            except ServiceCallError:
                if time.monotonic() >= deadline:
                    raise
                wait = 0.0
            else:
                if not is_temporary(reply.status) or time.monotonic() >= deadline:
                    return reply
                wait = reply.retry_after
                print(f'drvs_ask: {status_name(reply.status)}, retrying: {reply.message}', file=sys.stderr)
            time.sleep(max(0.0, min(retry_delay(wait, attempt), deadline - time.monotonic())))
    finally:
        client.close()
    raise AssertionError('unreachable: the loop returns or raises')


def ask(args: argparse.Namespace) -> int:
    """Send the request and print what comes back; 0 when at least one vision system answered."""
    answers: queue.Queue = queue.Queue()
    callback = f'{rospy.get_name()}/callback_coordinates'
    request_id = f'drvs_ask-{os.getpid()}'

    def on_callback(request):
        if request.request_id == request_id:
            answers.put(request)
        return CallbackCoordinatesResponse()

    rospy.Service(callback, CallbackCoordinates, on_callback)
    request = DetectObjectBoundaryRequest(
        algorithm=args.algorithm,
        region_of_interest=BoundingBox(*args.roi),
        callback_service=callback,
        request_id=request_id,
    )
    try:
        reply = send_with_retries(args.server, request, args.timeout)
    except ServiceCallError as error:
        print(
            f'drvs_ask: {error} (is DRVS running? source scripts/env.sh for ROS_MASTER_URI)', file=sys.stderr
        )
        return 2
    print(f'accepted: {reply.accepted}, vision_systems: {reply.vision_systems}, message: {reply.message!r}')
    if reply.status != ACCEPTED:
        print(f'drvs_ask: refused ({status_name(reply.status)}): {reply.message}', file=sys.stderr)
        return 2
    answered = 0
    deadline = rospy.get_time() + args.wait
    while (left := deadline - rospy.get_time()) > 0:
        try:
            print(format_callback(answers.get(timeout=left)))
            answered += 1
        except queue.Empty:
            break
    print(f'{answered} of {reply.vision_systems} vision system(s) called back within {args.wait:.1f} s')
    return 0 if answered else 1
