#!/usr/bin/env python3
"""A drvs/CallbackCoordinates server for tests: appends every call as one JSON line to ``~output``.

Parameters: ``~output`` (file, required), ``~service`` (default
``/robot/callback_coordinates``), ``~services`` (a list, YAML or comma-separated:
serve all of these instead of ``~service``, as many robots' callbacks in one
process), ``~delay`` (seconds to hold each call before answering, default 0:
simulates a slow or hung robot).
Each line: service (the one called), received (``time.monotonic()`` on arrival:
the test process's clock on Linux), algorithm, request_id, vision_system, stamp
(float seconds), caller, objects (a list of outlines, each a list of [x, y]),
bounding_boxes, and the fused mode's fields: fused, status, message, answered, refused,
missing, gone, and per object track_ids, velocities, seen_by, labels, heights.
"""

import json
import threading
import time

import rospy

from drvs.srv import CallbackCoordinates, CallbackCoordinatesResponse


def service_names():
    names = rospy.get_param('~services', None)
    if names is None:
        return [rospy.get_param('~service', '/robot/callback_coordinates')]
    if isinstance(names, str):
        names = names.split(',')
    return [str(name).strip() for name in names if str(name).strip()]


def main():
    rospy.init_node('callback_recorder')
    output = rospy.get_param('~output')
    delay = float(rospy.get_param('~delay', 0.0))
    lock = threading.Lock()

    def handler(service):
        def handle(request):
            record = {
                'service': service,
                'received': time.monotonic(),
                'algorithm': request.algorithm,
                'request_id': request.request_id,
                'vision_system': request.vision_system,
                'stamp': request.stamp.to_sec(),
                'caller': request._connection_header.get('callerid', ''),
                'objects': [[[p.x, p.y] for p in o.boundary.points] for o in request.objects],
                'bounding_boxes': [
                    [o.bounding_box.min_x, o.bounding_box.min_y, o.bounding_box.max_x, o.bounding_box.max_y]
                    for o in request.objects
                ],
                'fused': request.fused,
                'status': request.status,
                'message': request.message,
                'answered': list(request.answered),
                'refused': list(request.refused),
                'missing': list(request.missing),
                'gone': list(request.gone),
                'track_ids': [o.track_id for o in request.objects],
                'velocities': [[o.velocity.x, o.velocity.y] for o in request.objects],
                'seen_by': [list(o.seen_by) for o in request.objects],
                'labels': [o.label for o in request.objects],
                'heights': [o.height for o in request.objects],
            }
            with lock, open(output, 'a') as handle_:
                handle_.write(json.dumps(record) + '\n')
            if delay > 0:
                time.sleep(delay)
            return CallbackCoordinatesResponse()

        return handle

    for service in service_names():
        rospy.Service(service, CallbackCoordinates, handler(rospy.resolve_name(service)))
    rospy.spin()


if __name__ == '__main__':
    main()
