"""``drvs_ask``: ask DRVS one question from a terminal and print the answers.

It serves a temporary drvs/CallbackCoordinates service, sends one
DetectObjectBoundary request to the server with that service as the callback,
prints the server's acknowledgement and then every vision system's callback
(outlines in ``map``) until ``--wait`` seconds have passed.
"""

from __future__ import annotations

import argparse
import os
import queue
import sys

import rospy

from drvs.algorithms import AlgorithmError, parse_algorithm
from drvs.msg import BoundingBox
from drvs.ros.conversions import polygon_to_points
from drvs.ros.service_client import ServiceCallError, ServiceClient
from drvs.srv import (
    CallbackCoordinates,
    CallbackCoordinatesResponse,
    DetectObjectBoundary,
    DetectObjectBoundaryRequest,
)


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
    parser.add_argument('--server', default='/drvs/detect_object_boundary', help='the DRVS server service')
    args = parser.parse_args(argv)
    try:
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
        lines.append(f'  [{i}] bounds x {box.min_x:.3f}..{box.max_x:.3f}, y {box.min_y:.3f}..{box.max_y:.3f}')
        lines.append(f'      outline {points}')
    return '\n'.join(lines)


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
    client = ServiceClient(args.server, DetectObjectBoundary, timeout=5.0)
    try:
        reply = client.call(
            DetectObjectBoundaryRequest(
                algorithm=args.algorithm,
                region_of_interest=BoundingBox(*args.roi),
                callback_service=callback,
                request_id=request_id,
            )
        )
    except ServiceCallError as error:
        print(
            f'drvs_ask: {error} (is DRVS running? source scripts/env.sh for ROS_MASTER_URI)', file=sys.stderr
        )
        return 2
    finally:
        client.close()
    print(f'accepted: {reply.accepted}, vision_systems: {reply.vision_systems}, message: {reply.message!r}')
    if not reply.accepted:
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
