#!/usr/bin/env python3
"""A subscriber for tests: appends every message of a topic, of any type, to ``~output`` as one JSON line.

Parameters: ``~topic`` (required; e.g. ``/drvs/registry``), ``~output`` (file, required).
Each line: ``time`` (``time.monotonic()`` when it arrived: the same clock as the
test process's on Linux), ``type`` (e.g. ``drvs/Registry``) and ``data`` (the message
as ``rostopic echo`` prints it, parsed: :func:`drvs.testing.harness.parse_echo`).
"""

import json
import threading
import time

import genpy.message
import roslib.message
import rospy

from drvs.testing.harness import parse_echo


def main():
    rospy.init_node('topic_recorder')
    output = rospy.get_param('~output')
    lock = threading.Lock()

    def on_message(message):
        arrived = time.monotonic()
        kind = message._connection_header['type']
        decoded = roslib.message.get_message_class(kind)().deserialize(message._buff)
        data = parse_echo(genpy.message.strify_message(decoded))
        with lock, open(output, 'a') as handle:
            handle.write(json.dumps({'time': arrived, 'type': kind, 'data': data}) + '\n')

    rospy.Subscriber(rospy.get_param('~topic'), rospy.AnyMsg, on_message, queue_size=100)
    rospy.spin()


if __name__ == '__main__':
    main()
