#!/usr/bin/env python3
"""drvs_robot: a bench robot that asks DRVS one round at a time and logs every callback with its CPU time.

What a robot does with DRVS for one round of vision: one DetectObjectBoundary request
to the server (or one WatchObjectBoundary that then stands), then it receives the
vision systems' callbacks on its own CallbackCoordinates service — or, asked with
``fused`` true, the server's one callback with every object once (docs/interface.md,
"Fused mode"). It neither decodes nor segments anything. CPU time is the process's
(time.process_time: every thread).

CLI (private parameters)::

    .venv/bin/python bench/nodes/drvs_robot.py __name:=robot1 _out:=/tmp/robot1.jsonl \\
        _algorithm:=colour:150,0,0,255,80,80 _regions:="{a: [1.0, 1.0, 2.0, 2.0]}"

- ``~out``: JSON lines file (required).
- ``~algorithm``: the algorithm string (default ``colour:150,0,0,255,80,80``).
- ``~regions``: named regions, each [min_x, min_y, max_x, max_y] in ``map`` (required). For each
  name ``n`` it serves (roscpp/Empty, each returns once the server acknowledged):
  ``~ask_n``: one DetectObjectBoundary (request_id ``n<N>``, N counting this robot's asks);
  ``~fuse_n``: the same with ``fused`` true (request_id ``fused_n<N>``), answered by one callback;
  ``~watch_n``: one WatchObjectBoundary (request_id ``watch_n``) of ``~period`` seconds for
  ``~duration`` seconds, whose callbacks then come every period; ``~unwatch_n`` cancels it
  (duration 0).
- ``~period`` (default 1.0 s), ``~duration`` (default 300 s): the watches'.
- ``~server``: the server's namespace (default ``/drvs``).
- ``~profile``: a path: every service connection's thread (rospy's ``ServiceImpl.handle``: the
  callbacks and the asks) runs under cProfile timed by the thread's CPU time, and on SIGUSR2 each
  thread's statistics so far are written (marshal, as ``pstats`` reads them) to ``<profile>.<n>``,
  then ``<profile>.done``.

Lines (``event`` says which): ``ask`` / ``watch`` / ``unwatch`` (request_id, status, message,
vision_systems, ``sent``: time.time() before sending, ``cpu0``: process CPU when the handler
started, ``cpu`` after the acknowledgement); ``callback`` (request_id, vision_system, objects,
vertices, ``received``: time.time() on arrival, ``stamp``: the frame's, ``cpu`` after handling,
``handler``: thread CPU in the handler, this file's code but the final write; a fused callback
adds ``fused``, ``status`` and how many vision systems ``answered``, ``refused`` and were ``missing``);
``mark`` (``cpu``), written when the process gets SIGUSR1, so a bench can read the CPU between
rounds without a ROS call.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
import time

import rospy
from roscpp.srv import Empty, EmptyResponse

from drvs.msg import BoundingBox
from drvs.ros.service_client import ServiceClient
from drvs.srv import (
    CallbackCoordinates,
    CallbackCoordinatesResponse,
    DetectObjectBoundary,
    DetectObjectBoundaryRequest,
    WatchObjectBoundary,
    WatchObjectBoundaryRequest,
)


class BenchRobot:
    def __init__(self):
        self.out = open(rospy.get_param('~out'), 'a', buffering=1)  # noqa: SIM115 - closed at shutdown
        self.algorithm = str(rospy.get_param('~algorithm', 'colour:150,0,0,255,80,80'))
        self.regions = {
            str(name): BoundingBox(*(float(v) for v in box))
            for name, box in rospy.get_param('~regions').items()
        }
        self.period = float(rospy.get_param('~period', 1.0))
        self.duration = float(rospy.get_param('~duration', 300.0))
        server = str(rospy.get_param('~server', '/drvs')).rstrip('/')
        self.callback = rospy.resolve_name('~callback_coordinates')
        self.lock = threading.Lock()
        self.asks = 0
        self.detect = ServiceClient(f'{server}/detect_object_boundary', DetectObjectBoundary, 10.0)
        self.watch = ServiceClient(f'{server}/watch_object_boundary', WatchObjectBoundary, 10.0)

    def write(self, record: dict) -> None:
        with self.lock:
            if not self.out.closed:
                self.out.write(json.dumps(record) + '\n')

    def start(self) -> None:
        rospy.Service('~callback_coordinates', CallbackCoordinates, self.on_callback)
        for name in self.regions:
            rospy.Service(f'~ask_{name}', Empty, lambda _, name=name: self.ask(name))
            rospy.Service(f'~fuse_{name}', Empty, lambda _, name=name: self.ask(name, fused=True))
            rospy.Service(f'~watch_{name}', Empty, lambda _, name=name: self.ask_watch(name, self.duration))
            rospy.Service(f'~unwatch_{name}', Empty, lambda _, name=name: self.ask_watch(name, 0.0))
        signal.signal(signal.SIGUSR1, lambda *_: self.write({'event': 'mark', 'cpu': time.process_time()}))
        rospy.on_shutdown(self.close)

    def close(self) -> None:
        with self.lock:
            self.out.close()
        self.detect.close()
        self.watch.close()

    def ask(self, name: str, fused: bool = False) -> EmptyResponse:
        cpu0 = time.process_time()
        self.asks += 1
        request = DetectObjectBoundaryRequest(
            algorithm=self.algorithm,
            region_of_interest=self.regions[name],
            callback_service=self.callback,
            request_id=f'fused_{name}{self.asks}' if fused else f'{name}{self.asks}',
            fused=fused,
        )
        self.send('ask', self.detect, request, cpu0)
        return EmptyResponse()

    def ask_watch(self, name: str, duration: float) -> EmptyResponse:
        cpu0 = time.process_time()
        request = WatchObjectBoundaryRequest(
            algorithm=self.algorithm,
            region_of_interest=self.regions[name],
            callback_service=self.callback,
            request_id=f'watch_{name}',
            period=self.period,
            duration=duration,
        )
        self.send('watch' if duration > 0 else 'unwatch', self.watch, request, cpu0)
        return EmptyResponse()

    def send(self, event: str, client: ServiceClient, request, cpu0: float) -> None:
        sent = time.time()
        response = client.call(request)
        self.write(
            {
                'event': event,
                'request_id': request.request_id,
                'status': response.status,
                'message': response.message,
                'vision_systems': response.vision_systems,
                'sent': sent,
                'cpu0': cpu0,
                'cpu': time.process_time(),
            }
        )

    def on_callback(self, request) -> CallbackCoordinatesResponse:
        received, started = time.time(), time.thread_time()
        record = {
            'event': 'callback',
            'request_id': request.request_id,
            'vision_system': request.vision_system,
            'objects': len(request.objects),
            'vertices': sum(len(o.boundary.points) for o in request.objects),
            'received': received,
            'stamp': request.stamp.to_sec(),
        }
        if request.fused:
            record.update(
                fused=True,
                status=request.status,
                answered=len(request.answered),
                refused=len(request.refused),
                missing=len(request.missing),
            )
        record['cpu'] = time.process_time()
        line = json.dumps(record)
        line = f'{line[:-1]}, "handler": {time.thread_time() - started}}}'  # the write below not in it
        with self.lock:
            if not self.out.closed:
                self.out.write(line + '\n')
        return CallbackCoordinatesResponse()


def profile_service_threads(path: str) -> None:
    """Run every rospy service connection thread under its own cProfile; SIGUSR2 writes them."""
    import cProfile
    import marshal

    from rospy.impl.tcpros_service import ServiceImpl

    profiles: list[cProfile.Profile] = []
    handle = ServiceImpl.handle

    def profiled(self, transport, header):
        profile = cProfile.Profile(time.thread_time)  # CPU time: a thread waiting in recv costs nothing
        profiles.append(profile)
        return profile.runcall(handle, self, transport, header)

    def write(*_) -> None:
        for number, profile in enumerate(list(profiles)):
            profile.snapshot_stats()  # not create_stats: that would stop another thread's profiler
            with open(f'{path}.{number}', 'wb') as handle_:
                marshal.dump(profile.stats, handle_)
        with open(f'{path}.done', 'w') as handle_:
            handle_.write(f'{len(profiles)}\n')

    ServiceImpl.handle = profiled
    signal.signal(signal.SIGUSR2, write)


def main() -> int:
    rospy.init_node('drvs_robot')
    if rospy.get_param('~profile', ''):
        profile_service_threads(str(rospy.get_param('~profile')))
    robot = BenchRobot()
    robot.start()
    rospy.spin()
    return 0


if __name__ == '__main__':
    sys.exit(main())
