#!/usr/bin/env python3
"""The throughput benchmark's robot: DetectObjectBoundary calls back to back, by a schedule.

It keeps one persistent connection to each of ``~services`` (YAML mapping: a
label to a service name, e.g. ``{plain: /echo/detect_object_boundary, drvs:
/drvs/detect_object_boundary}``) and, in each phase of a schedule, calls one of
them as fast as it is answered: each call as soon as the last one was answered; a
refusal with a ``retry_after`` (``BUSY``) is waited out, as a robot would. The
callback service named in the requests is this node's own
``~callback_coordinates`` (it answers and does nothing).

Start-up: the node connects, asks each ``(label, region, count)`` of ``~expect``
(YAML list) until the answer says ``count`` vision systems got it, writes
``{"ready": time.time()}`` to ``~out``, then waits for the file ``~go``: JSON
``{"phases": [{"service": label, "regions": [[min_x, min_y, max_x, max_y], ...],
"start": t, "end": t}, ...]}`` in ``time.time()`` (the clock every process of the
benchmark shares), written by the benchmark once every client is ready. In each
phase it calls from ``start`` until ``end``, taking the regions in turn. Then it
writes ``{"bins": {"<bin>": [replies, accepted, refused]}, "bin": BIN}``, counted
per ``BIN`` seconds, and exits.
"""

import json
import os
import time
from collections import defaultdict

import rospy
import yaml

from drvs.srv import (
    CallbackCoordinates,
    CallbackCoordinatesResponse,
    DetectObjectBoundary,
    DetectObjectBoundaryRequest,
)

BIN = 0.01
GO_TIMEOUT = 120.0


def yaml_param(name: str, default):
    value = rospy.get_param(name, default)
    return yaml.safe_load(value) if isinstance(value, str) else value


def wait_for_go(path: str) -> list[dict]:
    """The schedule's phases from the ``~go`` file, once the benchmark writes it."""
    deadline = time.monotonic() + GO_TIMEOUT
    while not os.path.exists(path):
        if time.monotonic() > deadline or rospy.is_shutdown():
            raise SystemExit(f'no {path} after {GO_TIMEOUT:g} s')
        time.sleep(0.005)
    with open(path) as handle:
        return json.load(handle)['phases']


def main() -> None:
    rospy.init_node('load_client')
    out = rospy.get_param('~out')
    callback = rospy.Service(
        '~callback_coordinates', CallbackCoordinates, lambda _: CallbackCoordinatesResponse()
    )
    proxies = {}
    for label, service in yaml_param('~services', {}).items():
        rospy.wait_for_service(service, timeout=30.0)
        proxies[label] = rospy.ServiceProxy(service, DetectObjectBoundary, persistent=True)

    def request(number: int, region) -> DetectObjectBoundaryRequest:
        message = DetectObjectBoundaryRequest(
            algorithm='colour:0,0,150,80,80,255',
            callback_service=callback.resolved_name,
            request_id=f'{rospy.get_name()}-{number}',
        )
        box = message.region_of_interest
        box.min_x, box.min_y, box.max_x, box.max_y = map(float, region)
        return message

    deadline = time.monotonic() + 60.0
    for label, region, count in yaml_param('~expect', []):
        while proxies[label](request(0, region)).vision_systems < count:
            if time.monotonic() > deadline:
                raise SystemExit(f'fewer than {count} vision systems got {region} after 60 s')
            time.sleep(0.05)
    with open(out, 'w') as handle:
        handle.write(json.dumps({'ready': time.time()}) + '\n')
    bins = defaultdict(lambda: [0, 0, 0])
    for phase in wait_for_go(rospy.get_param('~go')):
        call = proxies[phase['service']]
        requests = [request(number, region) for number, region in enumerate(phase['regions'])]
        time.sleep(max(0.0, phase['start'] - time.time()))
        number, end = 0, phase['end']
        now = time.time()
        while now < end and not rospy.is_shutdown():
            answer = call(requests[number % len(requests)])
            number += 1
            now = time.time()
            counts = bins[int(now / BIN)]
            counts[0] += 1
            if answer.accepted:
                counts[1] += 1
            else:
                counts[2] += 1
                if answer.retry_after > 0:
                    time.sleep(answer.retry_after)
                    now = time.time()
    for proxy in proxies.values():
        proxy.close()
    with open(out, 'a') as handle:
        handle.write(json.dumps({'bins': {str(slot): c for slot, c in bins.items()}, 'bin': BIN}) + '\n')


if __name__ == '__main__':
    main()
