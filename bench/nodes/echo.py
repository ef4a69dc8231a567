#!/usr/bin/env python3
"""The benchmarks' anchor: a drvs/DetectObjectBoundary service that accepts at once and does nothing.

A plain persistent rospy call to it is the floor a DRVS acknowledgement cannot
beat: the same message type both ways, the same rospy machinery on both ends,
and no work in the handler. The reply carries a message as long as the DRVS
server's ("forwarded to 1 vision system"), so both replies are the same size.

Run as ``__name:=echo``: serves ``/echo/detect_object_boundary``.
"""

import rospy

from drvs.common.status import ACCEPTED
from drvs.srv import DetectObjectBoundary, DetectObjectBoundaryResponse

REPLY = DetectObjectBoundaryResponse(
    accepted=True, status=ACCEPTED, message='forwarded to 1 vision system', vision_systems=1
)


def handle(request):
    return REPLY


if __name__ == '__main__':
    rospy.init_node('echo')
    rospy.Service('~detect_object_boundary', DetectObjectBoundary, handle)
    rospy.spin()
