#!/usr/bin/env python3
"""A node with a publication, a subscription and a service, kept registered by a MasterWatch.

Parameters: ``~output`` (file, required) gets one JSON line per message received
and per service call; ``~publish`` (topic, default ``~out``) gets a std_msgs/String
``<node name> <count>`` every ``~publish_period`` seconds (default 0.1);
``~subscribe`` (topic, default ``~in``); ``~service`` (default ``~callback``), a
drvs/CallbackCoordinates that records the call's request_id; ``~watch_period``
(default 1.0), the MasterWatch's period.
"""

import json
import threading

import rospy
from std_msgs.msg import String

from drvs.ros.master_watch import MasterWatch
from drvs.srv import CallbackCoordinates, CallbackCoordinatesResponse


def main():
    rospy.init_node('master_watch_node')
    watch = MasterWatch(period=float(rospy.get_param('~watch_period', 1.0)))
    watch.start()
    rospy.on_shutdown(watch.stop)
    output = rospy.get_param('~output')
    lock = threading.Lock()

    def record(entry):
        with lock, open(output, 'a') as handle:
            handle.write(json.dumps(entry) + '\n')

    def on_message(message):
        record({'kind': 'message', 'data': message.data})

    def on_call(request):
        record({'kind': 'call', 'request_id': request.request_id})
        return CallbackCoordinatesResponse()

    publisher = rospy.Publisher(rospy.get_param('~publish', '~out'), String, queue_size=10)
    rospy.Subscriber(rospy.get_param('~subscribe', '~in'), String, on_message)
    rospy.Service(rospy.get_param('~service', '~callback'), CallbackCoordinates, on_call)
    rate = rospy.Rate(1.0 / float(rospy.get_param('~publish_period', 0.1)))
    count = 0
    while not rospy.is_shutdown():
        publisher.publish(String(f'{rospy.get_name()} {count}'))
        count += 1
        try:
            rate.sleep()
        except rospy.ROSInterruptException:
            break


if __name__ == '__main__':
    main()
