#!/usr/bin/env python3
"""The latency benchmark's robot: times requests to DRVS next to plain calls, one round at a time.

Each round makes one plain persistent call to ``~plain`` (the anchor: a
DetectObjectBoundary service that answers at once, ``bench/nodes/echo.py``), then
one persistent call to ``~server`` (``/drvs/detect_object_boundary``) whose
callback service is this node's own ``~callback_coordinates``, and waits until
``~expect`` vision systems have called back, or ``~timeout`` seconds. Rounds
never overlap, and each call starts ``~gap`` seconds after the last one ended
(default 0.002), so that every call, plain or not, finds the processes idle (a
vision system still finishing its last callback would slow whichever call came
next): each one measures latency, not queueing. Times are ``time.perf_counter()``
in this process: a callback's is taken when rospy hands it to the handler (after
reading and deserialising it, as a robot would see it).

Parameters: ``~out`` (JSON-lines file, required), ``~plain`` (the anchor service,
required), ``~server`` (default ``/drvs/detect_object_boundary``), ``~rounds``
(default 100), ``~warmup`` (rounds made first and not written, default 10),
``~algorithm`` and ``~region`` (YAML ``[min_x, min_y, max_x, max_y]``) of the
requests, ``~expect`` (vision systems, default 1: first the client asks until the
acknowledgement says this many got the request, up to ``~settle`` seconds,
default 60; then it waits for that many callbacks per request), ``~gap``,
``~timeout`` (s per request, default 5), ``~cpu_pid`` (a process whose CPU time,
user + system from ``/proc``, is read when the measured rounds begin and end;
default 0: none), ``~fused`` (default false: the requests are fused, docs/interface.md
"Fused mode"; each is then answered by one callback from the server, ``first`` and ``last``
are its time, and a round whose callback says fewer than ``~expect`` vision systems
answered counts as short).

Output: ``{"ready": time.time()}`` once the vision systems answer, then one line
per measured round, ``{"round", "plain", "ack", "first", "last",
"vision_systems", "callbacks", "status"}`` (fused: and ``"answered"``, ``"objects"``), the
times in seconds after the call was sent (``first`` / ``last`` null when no callback came),
then ``{"done": true, "window": s, "cpu": s, "failed": n}`` (the measured rounds' wall time, the CPU
time ``~cpu_pid`` used meanwhile, and the rounds refused or short of callbacks).
Exit code 0, or 1 when a round was refused or short of callbacks.
"""

import json
import os
import threading
import time

import rospy
import yaml

from drvs.srv import (
    CallbackCoordinates,
    CallbackCoordinatesResponse,
    DetectObjectBoundary,
    DetectObjectBoundaryRequest,
)


class Callbacks:
    """Arrival times of the callbacks per request id, and a wait for a number of them."""

    def __init__(self):
        self._times: dict[str, list[float]] = {}
        self.answered: dict[str, tuple[int, int]] = {}  # request id -> (vision systems answered, objects)
        self._arrived = threading.Condition()

    def handle(self, request) -> CallbackCoordinatesResponse:
        now = time.perf_counter()
        with self._arrived:
            self._times.setdefault(request.request_id, []).append(now)
            if request.fused:
                self.answered[request.request_id] = (len(request.answered), len(request.objects))
            self._arrived.notify_all()
        return CallbackCoordinatesResponse()

    def wait(self, request_id: str, count: int, timeout: float) -> list[float]:
        """The arrival times for ``request_id`` once ``count`` came (fewer after ``timeout``)."""
        deadline = time.monotonic() + timeout
        with self._arrived:
            while len(self._times.get(request_id, ())) < count:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._arrived.wait(left)
            return list(self._times.pop(request_id, ()))


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` so far (all its threads), from ``/proc``."""
    with open(f'/proc/{pid}/stat') as handle:
        fields = handle.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def settle(server, request, expect: int, timeout: float) -> None:
    """Ask until ``expect`` vision systems get the request (they have registered)."""
    request.request_id = 'settle'
    deadline = time.monotonic() + timeout
    while True:
        ack = server(request)
        if ack.accepted and ack.vision_systems >= expect:
            return
        if time.monotonic() > deadline:
            raise SystemExit(
                f'only {ack.vision_systems} of {expect} vision systems after {timeout:g} s: {ack}'
            )
        time.sleep(0.05)


def main() -> int:
    rospy.init_node('latency_client')
    out = rospy.get_param('~out')
    plain_name = rospy.get_param('~plain')
    server_name = rospy.get_param('~server', '/drvs/detect_object_boundary')
    rounds = int(rospy.get_param('~rounds', 100))
    warmup = int(rospy.get_param('~warmup', 10))
    expect = int(rospy.get_param('~expect', 1))
    timeout = float(rospy.get_param('~timeout', 5.0))
    cpu_pid = int(rospy.get_param('~cpu_pid', 0))
    gap = float(rospy.get_param('~gap', 0.002))
    fused = bool(rospy.get_param('~fused', False))
    region = rospy.get_param('~region', [0.0, 0.0, 1.0, 1.0])
    if isinstance(region, str):
        region = yaml.safe_load(region)
    callbacks = Callbacks()
    callback = rospy.Service('~callback_coordinates', CallbackCoordinates, callbacks.handle)
    request = DetectObjectBoundaryRequest(
        algorithm=rospy.get_param('~algorithm', 'colour:0,0,150,80,80,255'),
        callback_service=callback.resolved_name,
        fused=fused,
    )
    box = request.region_of_interest
    box.min_x, box.min_y, box.max_x, box.max_y = map(float, region)
    for name in (plain_name, server_name):
        rospy.wait_for_service(name, timeout=30.0)
    plain = rospy.ServiceProxy(plain_name, DetectObjectBoundary, persistent=True)
    server = rospy.ServiceProxy(server_name, DetectObjectBoundary, persistent=True)
    settle(server, request, expect, float(rospy.get_param('~settle', 60.0)))
    failed = 0
    with open(out, 'w') as handle:
        handle.write(json.dumps({'ready': time.time()}) + '\n')
        handle.flush()
        for number in range(-warmup, rounds):
            if rospy.is_shutdown():
                break
            if number == 0:
                began, cpu = time.perf_counter(), cpu_seconds(cpu_pid) if cpu_pid else 0.0
            request.request_id = f'r{number}'
            time.sleep(gap)
            sent = time.perf_counter()
            plain(request)
            plain_time = time.perf_counter() - sent
            time.sleep(gap)
            sent = time.perf_counter()
            ack = server(request)
            ack_time = time.perf_counter() - sent
            wanted = (1 if fused else expect) if ack.accepted else 0
            times = callbacks.wait(request.request_id, wanted, timeout) if wanted else []
            answered, objects = callbacks.answered.pop(request.request_id, (0, 0))
            failed += not ack.accepted or len(times) < wanted or (fused and answered < expect)
            if number < 0:
                continue
            record = {
                'round': number,
                'plain': plain_time,
                'ack': ack_time,
                'first': min(times) - sent if times else None,
                'last': max(times) - sent if times else None,
                'vision_systems': ack.vision_systems,
                'callbacks': len(times),
                'status': ack.status,
            }
            if fused:
                record.update(answered=answered, objects=objects)
            handle.write(json.dumps(record) + '\n')
        window = time.perf_counter() - began
        cpu = cpu_seconds(cpu_pid) - cpu if cpu_pid else None
        handle.write(json.dumps({'done': True, 'window': window, 'cpu': cpu, 'failed': failed}) + '\n')
    plain.close()
    server.close()
    return 1 if failed else 0


if __name__ == '__main__':
    raise SystemExit(main())
