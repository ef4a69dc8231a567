#!/usr/bin/env python3
"""Light fake vision systems for the throughput benchmark: they acknowledge every forward at once.

``~count`` vision systems in one process (run as ``__name:=fakes``:
``/fakes/vs0/detect_object_boundary``, ...), vision system *i* seeing the unit
square [i, i + 1] × [0, 1] of the floor, so a region inside one square reaches one
of them and a region across all reaches every one. Each registers with the DRVS
server and renews at half the lease granted. A forward is answered ``ACCEPTED``
at once and counted, nothing else: no frame, no callback, so that what
saturates is the server's forwarding, not the vision.

Forwards are counted per ``BIN`` seconds of ``time.time()`` (the clock every
process of the benchmark shares); at shutdown (SIGINT) the node writes
``{"bins": {"<bin>": forwards}, "bin": BIN}`` to ``~out``.
"""

import json
import threading
import time
from collections import Counter

import rospy

from drvs.common.status import ACCEPTED
from drvs.ros.conversions import points_to_polygon
from drvs.ros.service_client import ServiceCallError, ServiceClient
from drvs.srv import (
    DetectObjectBoundary,
    DetectObjectBoundaryResponse,
    RegisterVisionService,
    RegisterVisionServiceRequest,
)

BIN = 0.01
REGISTER_TIMEOUT = 2.0
REPLY = DetectObjectBoundaryResponse(accepted=True, status=ACCEPTED, message='', vision_systems=1)


class Forwards:
    """Forwards received, counted per time bin (one lock; a count is a dict increment)."""

    def __init__(self):
        self.bins: Counter = Counter()
        self.lock = threading.Lock()

    def handle(self, request) -> DetectObjectBoundaryResponse:
        slot = int(time.time() / BIN)
        with self.lock:
            self.bins[slot] += 1
        return REPLY


def register_loop(requests: list, server: str) -> None:
    """Register every vision system, renew each at half the lease granted, retry after refusals."""
    client = ServiceClient(server, RegisterVisionService, REGISTER_TIMEOUT)
    due = [0.0] * len(requests)
    while not rospy.is_shutdown():
        now = time.monotonic()
        for index, request in enumerate(requests):
            if now < due[index]:
                continue
            try:
                answer = client.call(request)
            except ServiceCallError as error:
                rospy.logwarn_throttle(5.0, 'registration of %s failed: %s', request.service_name, error)
                due[index] = now + 0.2
                continue
            if answer.status == ACCEPTED:
                due[index] = now + max(answer.lease / 2.0, 0.1)
            else:
                due[index] = now + max(answer.retry_after, 0.0) + 0.2
        time.sleep(0.05)
    client.close()


def main() -> None:
    rospy.init_node('ack_vision_systems')
    out = rospy.get_param('~out')
    forwards = Forwards()
    requests = []
    for index in range(int(rospy.get_param('~count', 5))):
        service = rospy.Service(f'~vs{index}/detect_object_boundary', DetectObjectBoundary, forwards.handle)
        square = [(index, 0.0), (index + 1.0, 0.0), (index + 1.0, 1.0), (index, 1.0)]
        requests.append(
            RegisterVisionServiceRequest(
                service_name=service.resolved_name, field_of_view=points_to_polygon(square)
            )
        )

    def write() -> None:
        with forwards.lock, open(out, 'w') as handle:
            json.dump(
                {'bins': {str(slot): count for slot, count in forwards.bins.items()}, 'bin': BIN}, handle
            )

    rospy.on_shutdown(write)
    register_loop(requests, rospy.get_param('~server', '/drvs/register_vision_service'))


if __name__ == '__main__':
    main()
