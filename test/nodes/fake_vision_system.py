#!/usr/bin/env python3
"""A fake vision system for tests: registers a field of view, records every forward it receives.

Serves ``~detect_object_boundary`` (drvs/DetectObjectBoundary), with ``~watch``
also ``~watch_object_boundary`` (drvs/WatchObjectBoundary), and appends one JSON
line per event to ``~output``:

- ``{"kind": "forward", "algorithm", "region_of_interest": [min_x, min_y, max_x, max_y],
  "callback_service", "request_id", "caller"}`` for every request received;
- ``{"kind": "watch", the same fields, "period", "duration", "changes_only"}`` for
  every watch forward received (answered ACCEPTED with the period and duration asked);
- ``{"kind": "register", "field_of_view", "algorithms", "service_name", "accepted",
  "status", "message", "lease", "retry_after"}`` for every registration answer.

Parameters:

- ``~output`` (required): the JSON-lines file.
- ``~field_of_view`` (YAML list of [x, y], default ``[]``): what to register.
  Changing the parameter while the node runs re-registers (a moved camera).
- ``~algorithms`` (YAML list of names, default ``[]`` = the built-ins): the
  algorithm names to register; changing it re-registers too.
- ``~register`` (bool, default true): register with ``~server``.
- ``~server`` (default ``/drvs/register_vision_service``).
- ``~service_name`` (default this node's ``detect_object_boundary``): the name
  sent in the registration (a test can make it claim another node's service).
- ``~renew`` (seconds, default 0 = once): re-register this often (lease renewal);
  the parameter is also checked this often (0.2 s when 0).
- ``~hang`` (seconds, default 0): hold every request this long before answering.
- ``~watch`` (bool, default false): serve ``~watch_object_boundary`` too, before registering.
- ``~objects`` (YAML list of outlines, each a list of [x, y], default ``[]``): with ``~answer``,
  what it "sees"; each moves at ``~velocity`` ([vx, vy] m/s, default [0, 0]) from ``~epoch`` (ROS
  seconds, default the node's start: give fakes that see the same objects the same epoch).
- ``~answer`` (bool, default false): call the request's callback service back with the objects
  whose centre lies in the region (a request once; a watch every period until it ends).
- ``~stamp_offset`` (seconds, default 0): stamp callbacks this far off the clock (a camera
  host's clock skew).
- ``~refuse`` (status code, default 0): refuse every request and watch with this status and
  ``~refuse_message``.
"""

import json
import threading
import time

import rospy
import yaml

from drvs.ros.conversions import points_to_detected_object, points_to_polygon
from drvs.srv import (
    CallbackCoordinates,
    DetectObjectBoundary,
    DetectObjectBoundaryResponse,
    RegisterVisionService,
    WatchObjectBoundary,
    WatchObjectBoundaryResponse,
)


def list_param(name):
    """A list parameter, given as a list or as YAML text (``_param:=...`` on the command line)."""
    value = rospy.get_param(name, [])
    if isinstance(value, str):
        value = yaml.safe_load(value)
    return value or []


def main():
    rospy.init_node('fake_vision_system')
    output = rospy.get_param('~output')
    hang = float(rospy.get_param('~hang', 0.0))
    renew = float(rospy.get_param('~renew', 0.0))
    lock = threading.Lock()

    def record(entry):
        with lock, open(output, 'a') as handle:
            handle.write(json.dumps(entry) + '\n')

    def fields(kind, request):
        box = request.region_of_interest
        return {
            'kind': kind,
            'algorithm': request.algorithm,
            'region_of_interest': [box.min_x, box.min_y, box.max_x, box.max_y],
            'callback_service': request.callback_service,
            'request_id': request.request_id,
            'caller': request._connection_header.get('callerid', ''),
        }

    own = rospy.resolve_name('~detect_object_boundary')
    answering = rospy.get_param('~answer', False)
    outlines = list_param('~objects')
    velocity = list_param('~velocity') or [0.0, 0.0]
    offset = float(rospy.get_param('~stamp_offset', 0.0))
    refuse = int(rospy.get_param('~refuse', 0))
    refuse_message = rospy.get_param('~refuse_message', 'refused by the fake')
    started = float(rospy.get_param('~epoch', rospy.get_time()))  # when the objects were at ~objects
    watches = {}  # (caller, request_id) -> end time

    def seen(request):
        """The objects at this moment whose centre lies in the request's region, and the stamp."""
        now = rospy.get_time()
        box, dt = request.region_of_interest, now - started
        found = []
        for outline in outlines:
            moved = [[x + velocity[0] * dt, y + velocity[1] * dt] for x, y in outline]
            cx = sum(p[0] for p in moved) / len(moved)
            cy = sum(p[1] for p in moved) / len(moved)
            if box.min_x <= cx <= box.max_x and box.min_y <= cy <= box.max_y:
                found.append(points_to_detected_object(moved))
        return found, rospy.Time.from_sec(now + offset)

    def call_back(request):
        found, stamp = seen(request)
        try:
            rospy.ServiceProxy(request.callback_service, CallbackCoordinates)(
                algorithm=request.algorithm,
                request_id=request.request_id,
                vision_system=own,
                stamp=stamp,
                objects=found,
            )
        except (rospy.ServiceException, rospy.ROSException) as error:
            rospy.logwarn('callback failed: %s', error)

    def serve_watch(request, key):
        while not rospy.is_shutdown() and time.monotonic() < watches.get(key, 0.0):
            call_back(request)
            time.sleep(max(request.period, 0.05))

    def handle(request):
        record(fields('forward', request))
        if hang > 0:
            time.sleep(hang)
        if refuse:
            return DetectObjectBoundaryResponse(accepted=False, status=refuse, message=refuse_message)
        if answering:
            threading.Thread(target=call_back, args=(request,), daemon=True).start()
        return DetectObjectBoundaryResponse(accepted=True, message='fake', vision_systems=1)

    def handle_watch(request):
        terms = {'period': request.period, 'duration': request.duration, 'changes_only': request.changes_only}
        record({**fields('watch', request), **terms})
        if refuse:
            return WatchObjectBoundaryResponse(accepted=False, status=refuse, message=refuse_message)
        key = (request._connection_header.get('callerid', ''), request.request_id)
        serving = watches.get(key, 0.0) > time.monotonic()
        watches[key] = time.monotonic() + request.duration
        if answering and request.duration > 0 and not serving:
            threading.Thread(target=serve_watch, args=(request, key), daemon=True).start()
        return WatchObjectBoundaryResponse(
            accepted=True, message='fake', vision_systems=1, period=request.period, duration=request.duration
        )

    rospy.Service(own, DetectObjectBoundary, handle)
    if rospy.get_param('~watch', False):
        rospy.Service(rospy.resolve_name('~watch_object_boundary'), WatchObjectBoundary, handle_watch)
    if not rospy.get_param('~register', True):
        rospy.spin()
        return
    service_name = rospy.get_param('~service_name', own)
    server = rospy.get_param('~server', '/drvs/register_vision_service')
    rospy.wait_for_service(server, timeout=30.0)
    register = rospy.ServiceProxy(server, RegisterVisionService)
    last, last_time = None, 0.0
    while not rospy.is_shutdown():
        fov = list_param('~field_of_view')
        algorithms = list_param('~algorithms')
        now = time.monotonic()
        if (fov, algorithms) != last or (renew > 0 and now - last_time >= renew):
            try:
                answer = register(service_name, points_to_polygon(fov), algorithms)
            except (rospy.ServiceException, rospy.ROSException) as error:
                rospy.logwarn('registration failed: %s', error)
                register = rospy.ServiceProxy(server, RegisterVisionService)
            else:
                record(
                    {
                        'kind': 'register',
                        'field_of_view': fov,
                        'algorithms': algorithms,
                        'service_name': service_name,
                        'accepted': answer.accepted,
                        'status': answer.status,
                        'message': answer.message,
                        'lease': answer.lease,
                        'retry_after': answer.retry_after,
                    }
                )
                last, last_time = (fov, algorithms), now
        time.sleep(min(renew, 0.2) if renew > 0 else 0.2)


if __name__ == '__main__':
    try:
        main()
    except rospy.ROSInterruptException:
        pass
