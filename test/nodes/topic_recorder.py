#!/usr/bin/env python3
"""A std_msgs/String subscriber for tests: appends every message to ``~output`` as one JSON line.

Parameters: ``~topic`` (required; e.g. ``/drvs/registry``), ``~output`` (file, required).
Each line: ``time`` (``time.monotonic()`` when it arrived: the same clock as the
test process's on Linux) and ``data`` (the text, decoded if it is JSON).
"""

import json
import threading
import time

import rospy
from std_msgs.msg import String


def main():
    rospy.init_node('topic_recorder')
    output = rospy.get_param('~output')
    lock = threading.Lock()

    def on_message(message):
        arrived = time.monotonic()
        try:
            data = json.loads(message.data)
        except ValueError:
            data = message.data
        with lock, open(output, 'a') as handle:
            handle.write(json.dumps({'time': arrived, 'data': data}) + '\n')

    rospy.Subscriber(rospy.get_param('~topic'), String, on_message, queue_size=100)
    rospy.spin()


if __name__ == '__main__':
    main()
