#!/usr/bin/env python3
"""A minimal drvs/DetectObjectBoundary server for tests: accepts everything, echoes the request.

The reply's message is the request's algorithm and request_id, and
vision_systems is the number of characters of callback_service, so a test can
check that every field arrived.
"""

import rospy

from drvs.srv import DetectObjectBoundary, DetectObjectBoundaryResponse


def handle(request):
    box = request.region_of_interest
    message = f'{request.algorithm}|{request.request_id}|{box.min_x},{box.min_y},{box.max_x},{box.max_y}'
    return DetectObjectBoundaryResponse(
        accepted=True, message=message, vision_systems=len(request.callback_service)
    )


if __name__ == '__main__':
    rospy.init_node('echo_detect_boundary')
    rospy.Service('~detect_object_boundary', DetectObjectBoundary, handle)
    rospy.spin()
