#!/usr/bin/env python3
"""A consumer of camera topics for tests: records messages and looks each image's frame up on tf.

Parameters: ``~output`` (JSON lines file), ``~counts`` (JSON ``{topic: messages to record}``).
"""

import base64
import json
import threading

import rospy
import tf2_ros
from sensor_msgs.msg import Image


def main() -> None:
    """Record to ``~output`` the first ``~counts[topic]`` messages of each topic, then unsubscribe.

    Each line: ``topic``, ``type``, ``data`` (the serialized message, base64) and, for
    images, ``lookup``: map -> the image's frame at its stamp (translation, rotation
    x y z w, stamp) or ``lookup_error``.
    """
    rospy.init_node('grabber')
    output, counts = rospy.get_param('~output'), rospy.get_param('~counts')
    tf_buffer = tf2_ros.Buffer(debug=False)
    tf2_ros.TransformListener(tf_buffer)
    lock = threading.Lock()  # guards received, subscribers and the file
    received: dict[str, int] = {}
    subscribers = {}

    def on_message(message, topic):
        with lock:
            if received[topic] >= counts[topic]:
                return
            received[topic] += 1
            if received[topic] == counts[topic]:
                subscribers[topic].unregister()
        kind = message._connection_header['type']
        entry = {'topic': topic, 'type': kind, 'data': base64.b64encode(message._buff).decode()}
        if kind == 'sensor_msgs/Image':
            header = Image().deserialize(message._buff).header
            try:
                found = tf_buffer.lookup_transform('map', header.frame_id, header.stamp, rospy.Duration(2.0))
            except tf2_ros.TransformException as error:
                entry['lookup_error'] = f'{type(error).__name__}: {error}'
            else:
                t, q = found.transform.translation, found.transform.rotation
                entry['lookup'] = {
                    'translation': [t.x, t.y, t.z],
                    'rotation': [q.x, q.y, q.z, q.w],
                    'stamp': found.header.stamp.to_sec(),
                }
        with lock, open(output, 'a') as handle:
            handle.write(json.dumps(entry) + '\n')

    for topic, count in counts.items():
        received[topic] = 0
        with lock:
            subscribers[topic] = rospy.Subscriber(
                topic, rospy.AnyMsg, on_message, callback_args=topic, queue_size=count
            )
    rospy.spin()


if __name__ == '__main__':
    main()
