#!/usr/bin/env python3
"""fused_watcher: an observer that keeps fused watches on the whole floor, so the fusion stage tracks.

The ``tracking`` bench section runs it beside a scenario: robots that ask per camera (or watch
only around themselves) leave the fusion stage nothing, or part of the floor, to track; this
watcher asks for every object of each algorithm on the whole floor, fused, every ``~period``,
and renews its watches at half their granted duration. It counts its callbacks and ignores
their contents: the tracks reach the scenario recorder on ``/drvs/objects``.

CLI (private parameters)::

    .venv/bin/python bench/nodes/fused_watcher.py __name:=fused_watcher \\
        _algorithms:="[colour:150,0,0,255,80,80, apriltag:tag36h11:1,2]" _region:="[0, 0, 6, 4.5]"

- ``~algorithms``: the algorithm strings to watch (required; a list, or one string).
- ``~region``: [min_x, min_y, max_x, max_y] in ``map`` (required): the floor.
- ``~period`` (default 0.2 s), ``~duration`` (default 30 s): the watches'.
- ``~server``: the server's namespace (default ``/drvs``).

A refused watch is logged and asked again after its ``retry_after`` (at least 1 s).
"""

from __future__ import annotations

import threading

import rospy

from drvs.msg import BoundingBox
from drvs.ros.service_client import ServiceCallError, ServiceClient
from drvs.srv import (
    CallbackCoordinates,
    CallbackCoordinatesResponse,
    WatchObjectBoundary,
    WatchObjectBoundaryRequest,
)


def main() -> None:
    rospy.init_node('fused_watcher')
    algorithms = rospy.get_param('~algorithms')
    algorithms = [algorithms] if isinstance(algorithms, str) else [str(a) for a in algorithms]
    region = BoundingBox(*(float(v) for v in rospy.get_param('~region')))
    period = float(rospy.get_param('~period', 0.2))
    duration = float(rospy.get_param('~duration', 30.0))
    server = str(rospy.get_param('~server', '/drvs')).rstrip('/')
    callbacks = {'count': 0}
    lock = threading.Lock()  # guards callbacks

    def on_callback(request) -> CallbackCoordinatesResponse:
        with lock:
            callbacks['count'] += 1
        return CallbackCoordinatesResponse()

    callback = rospy.resolve_name('~callback_coordinates')
    rospy.Service('~callback_coordinates', CallbackCoordinates, on_callback)
    client = ServiceClient(f'{server}/watch_object_boundary', WatchObjectBoundary, 10.0)
    due = dict.fromkeys(algorithms, 0.0)  # algorithm -> wall time of its next (re)watch
    stop = threading.Event()
    rospy.on_shutdown(stop.set)
    while not stop.is_set():
        now = rospy.get_time()
        for index, algorithm in enumerate(algorithms):
            if now < due[algorithm]:
                continue
            request = WatchObjectBoundaryRequest(
                algorithm=algorithm,
                region_of_interest=region,
                callback_service=callback,
                request_id=f'fused{index}',
                period=period,
                duration=duration,
                changes_only=False,
                fused=True,
            )
            try:
                answer = client.call(request)
            except ServiceCallError as error:
                rospy.logwarn('fused_watcher: %s: %s', algorithm, error)
                due[algorithm] = now + 1.0
                continue
            if answer.accepted:
                due[algorithm] = now + max(answer.duration / 2.0, 1.0)
            else:
                rospy.logwarn('fused_watcher: %s refused: %s', algorithm, answer.message)
                due[algorithm] = now + max(answer.retry_after, 1.0)
        with lock:
            count = callbacks['count']
        rospy.loginfo_throttle(10.0, 'fused_watcher: %d callbacks so far', count)
        stop.wait(0.2)
    client.close()


if __name__ == '__main__':
    main()
