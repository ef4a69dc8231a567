"""``drvs_ask``: ask DRVS one question from a terminal and print the answers.

It serves a temporary drvs/CallbackCoordinates service, sends one DetectObjectBoundary
request with it as the callback, prints the acknowledgement and every callback until
``--wait`` seconds have passed, retrying temporary refusals until ``--timeout``. Its
options and exit codes (:data:`EXIT_CODES`): docs/tutorials/by-hand.md.
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import queue
import sys
import time
from dataclasses import dataclass

import rospy

from drvs.algorithms import AlgorithmError, default_algorithms, parse_algorithm, split_algorithm
from drvs.common.failover import ServerList, moves_on
from drvs.common.retry import retry_delay
from drvs.common.settings import Settings
from drvs.common.status import ACCEPTED, INVALID, UNSUPPORTED, is_temporary
from drvs.common.status import name as status_name
from drvs.common.validation import ValidationError, region_of_interest
from drvs.msg import BoundingBox
from drvs.ros.conversions import polygon_to_points
from drvs.ros.service_client import MasterUnreachable, ServiceCallError, ServiceClient
from drvs.srv import (
    CallbackCoordinates,
    CallbackCoordinatesResponse,
    DetectObjectBoundary,
    DetectObjectBoundaryRequest,
)

FOUND, NOTHING_FOUND, USAGE, NOT_COVERED, REFUSED, NO_SERVER, NO_MASTER = range(7)
INTERRUPTED = 130
EXIT_CODES = {
    FOUND: 'objects found: at least one vision system called back with outlines',
    NOTHING_FOUND: 'vision systems were asked, but none found anything within --wait',
    USAGE: 'bad options',
    NOT_COVERED: 'no vision system covers the region (none was asked)',
    REFUSED: "the request was refused (its status and the server's message are printed); with --fused, "
    'also when every vision system asked refused it',
    NO_SERVER: 'no DRVS server answered within --timeout',
    NO_MASTER: 'no ROS master answered within --master-timeout',
    INTERRUPTED: 'interrupted (Ctrl-C)',
}
"""Exit code -> what it means, as ``--help`` lists it."""
FUSED_WAIT = 5.0
"""Seconds ``--fused`` waits at least: the server's ``~fused_deadline`` (2 s) and the delivery."""


@dataclass(frozen=True)
class AskSettings(Settings):
    """drvs_ask has options, no ``~parameters``: any ``_name:=`` given is warned about."""


def _number(minimum: float, strict: bool):
    """An argparse type: a finite number above (``strict``) or at least ``minimum``."""

    def number(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
        if not math.isfinite(value) or value < minimum or (strict and value == minimum):
            rule = f'greater than {minimum:g}' if strict else f'at least {minimum:g}'
            raise argparse.ArgumentTypeError(f'{text}: must be a finite number {rule}')
        return value

    return number


def _roi_number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog='drvs_ask',
        description='Ask DRVS where the objects of one algorithm are, and print the outlines.',
        epilog='exit codes:\n' + '\n'.join(f'  {code:<3}  {meaning}' for code, meaning in EXIT_CODES.items()),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument('algorithm', help='NAME:PARAMS, e.g. colour:0,0,150,80,80,255')
    parser.add_argument(
        '--roi',
        nargs=4,
        type=_roi_number,
        metavar=('MIN_X', 'MIN_Y', 'MAX_X', 'MAX_Y'),
        default=[0.0, 0.0, 1e3, 1e3],
        help='region of interest in map, metres (default: everything from (0, 0))',
    )
    parser.add_argument(
        '--wait', type=_number(0, strict=False), default=2.0, help='seconds to wait for callbacks (default 2)'
    )
    parser.add_argument(
        '--timeout',
        type=_number(0, strict=True),
        default=10.0,
        help='seconds to keep retrying while DRVS is busy, rate-limits or is unreachable (default 10)',
    )
    parser.add_argument(
        '--master-timeout',
        type=_number(0, strict=True),
        default=5.0,
        help='seconds to wait for the ROS master before giving up (default 5)',
    )
    parser.add_argument(
        '--fused',
        action='store_true',
        help='one callback from the fusion stage: every object once, with track ids and velocities '
        '(waits for it: --wait is then at least 5 s)',
    )
    parser.add_argument(
        '--server',
        nargs='+',
        default=['/drvs/detect_object_boundary'],
        metavar='SERVICE',
        help='the DRVS server service; several (replicas on one registry database, docs/registry.md): '
        'asked in order, the next on UNAVAILABLE or no answer',
    )
    args = parser.parse_args(argv)
    try:  # the server's own rules: a refusal it would send costs nothing here
        region_of_interest(args.roi)
    except ValidationError as error:
        parser.error(f'argument --roi: {error}')
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
        height = f', {detected.height:.3f} m high' if detected.height else ''
        lines.append(
            f'  [{i}]{label} bounds x {box.min_x:.3f}..{box.max_x:.3f}, y {box.min_y:.3f}..{box.max_y:.3f}'
            f'{height}'
        )
        if detected.track_id:
            velocity = detected.velocity
            lines.append(
                f'      track #{detected.track_id}, velocity ({velocity.x:.2f}, {velocity.y:.2f}) m/s'
                f'{", stationary" if detected.stationary else ""}, confidence {detected.confidence:.2f}, '
                f'seen by {", ".join(detected.seen_by) or "none this time (coasting)"}'
            )
        lines.append(f'      outline {points}')
    if request.fused:
        outcome = 'OK' if request.status == request.OK else status_name(request.status)
        lines.insert(1, f'  fused: {outcome}: {request.message}')
    return '\n'.join(lines)


def send_with_retries(servers: str | list[str], request, timeout: float):
    """Send ``request`` to the first of ``servers``, retrying temporary refusals and failed calls for
    ``timeout`` seconds; on ``UNAVAILABLE`` or a failed call the next server is asked
    (:class:`~drvs.common.failover.ServerList`).

    Returns the first final response (ACCEPTED or INVALID), or the last temporary
    refusal once time is up.

    :raises ServiceCallError: the last call failed and time is up.
    """
    deadline = time.monotonic() + timeout
    order = ServerList([servers] if isinstance(servers, str) else servers)
    clients: dict[str, ServiceClient] = {}
    try:
        for attempt in itertools.count():
            server = order.current
            if server not in clients:
                clients[server] = ServiceClient(server, DetectObjectBoundary, timeout=min(5.0, timeout))
            try:
                reply = clients[server].call(request)
            except ServiceCallError:
                if time.monotonic() >= deadline:
                    raise
                wait, status = 0.0, None
            else:
                if not is_temporary(reply.status) or time.monotonic() >= deadline:
                    return reply
                wait, status = reply.retry_after, reply.status
                print(f'drvs_ask: {status_name(reply.status)}, retrying: {reply.message}', file=sys.stderr)
            if moves_on(status) and len(order.servers) > 1:
                print(
                    f'drvs_ask: {server} did not serve the request; asking {order.failed()}', file=sys.stderr
                )
                if attempt < len(order.servers) - 1:
                    continue  # another server at once; a full round of failures waits as one would
            time.sleep(max(0.0, min(retry_delay(wait, attempt), deadline - time.monotonic())))
    finally:
        for client in clients.values():
            client.close()
    raise AssertionError('unreachable: the loop returns or raises')


def ask(args: argparse.Namespace) -> int:
    """Send the request and print what comes back; the exit code as in :data:`EXIT_CODES`."""
    try:
        return _ask(args)
    except KeyboardInterrupt:
        print('drvs_ask: interrupted', file=sys.stderr)
        return INTERRUPTED


def _ask(args: argparse.Namespace) -> int:
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
        fused=args.fused,
    )
    try:
        reply = send_with_retries(args.server, request, args.timeout)
    except MasterUnreachable as error:
        print(f'drvs_ask: {error} (the ROS master went away: is roscore still running?)', file=sys.stderr)
        return NO_MASTER
    except ServiceCallError as error:
        print(
            f'drvs_ask: {error} (is DRVS running? source scripts/env.sh for ROS_MASTER_URI)', file=sys.stderr
        )
        return NO_SERVER
    print(f'accepted: {reply.accepted}, vision_systems: {reply.vision_systems}, message: {reply.message!r}')
    if reply.status != ACCEPTED:
        print(f'drvs_ask: refused ({status_name(reply.status)}): {reply.message}', file=sys.stderr)
        return REFUSED
    if reply.vision_systems == 0:
        print(
            f'drvs_ask: not asked: {reply.message} (`rostopic echo /drvs/registry` lists the fields of view)',
            file=sys.stderr,
        )
        return NOT_COVERED
    answered = found = 0
    wait = max(args.wait, FUSED_WAIT) if args.fused else args.wait
    deadline = rospy.get_time() + wait
    while (left := deadline - rospy.get_time()) > 0:
        try:
            answer = answers.get(timeout=left)
        except queue.Empty:
            break
        print(format_callback(answer))
        if answer.fused:  # the one answer of a fused request
            if answer.status in (INVALID, UNSUPPORTED):
                print(f'drvs_ask: refused by the vision systems: {answer.message}', file=sys.stderr)
                return REFUSED
            found += len(answer.objects)
            answered = len(answer.answered)
            break
        answered += 1
        found += len(answer.objects)
    print(f'{answered} of {reply.vision_systems} vision system(s) called back within {wait:.1f} s')
    if found:
        return FOUND
    print(
        f'drvs_ask: nothing found: {reply.vision_systems} vision system(s) asked, none found anything '
        f'within {args.wait:g} s',
        file=sys.stderr,
    )
    return NOTHING_FOUND
