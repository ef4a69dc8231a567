#!/usr/bin/env python3
"""A subscriber for tests under ``/use_sim_time``: what a node's clock says when messages come.

Parameters: ``~topics`` (a list of topic names), ``~output`` (JSON lines file). Each line:
``topic``, ``rostime`` (``rospy.get_time()`` when the message arrived: the simulated time,
0 before the first ``/clock``) and ``data`` (the message as ``rostopic echo`` prints it, parsed).
"""

import json
import threading

import genpy.message
import roslib.message
import rospy

from drvs.testing.harness import parse_echo


def main():
    rospy.init_node('clock_probe')
    output = rospy.get_param('~output')
    lock = threading.Lock()

    def on_message(message, topic):
        now = rospy.get_time()
        if isinstance(message, rospy.AnyMsg):
            kind = message._connection_header['type']
            message = roslib.message.get_message_class(kind)().deserialize(message._buff)
        # else /clock, which rospy under /use_sim_time has subscribed to, typed, already
        data = parse_echo(genpy.message.strify_message(message))
        with lock, open(output, 'a') as handle:
            handle.write(json.dumps({'topic': topic, 'rostime': now, 'data': data}) + '\n')

    for topic in rospy.get_param('~topics'):
        rospy.Subscriber(topic, rospy.AnyMsg, on_message, callback_args=topic, queue_size=100)
    rospy.spin()


if __name__ == '__main__':
    main()
