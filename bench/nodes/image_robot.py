#!/usr/bin/env python3
"""image_robot: a robot of the image-sharing baseline; receives JPEG frames, decodes and segments them.

What a robot must do with image sharing to learn what DRVS would tell it: take every
camera's frame, decode it and run the same colour segmentation the DRVS vision
systems run (drvs.algorithms.colour, the vision system's defaults min_area 20 px,
epsilon 1 px). CPU time is the process's (time.process_time: every thread,
rospy's receive threads included).

CLI (private parameters)::

    .venv/bin/python bench/nodes/image_robot.py __name:=robot1 \\
        _topics:=/cams/cam1/image/compressed,/cams/cam2/image/compressed _out:=/tmp/robot1.jsonl

- ``~topics``: comma list of sensor_msgs/CompressedImage topics to subscribe to (required).
- ``~out``: JSON lines file, one line per frame (required).
- ``~algorithm``: the colour algorithm string (default ``colour:150,0,0,255,80,80``).
- ``~segment``: false to only receive (no decode, no segmentation; default true).
- ``~threads``: OpenCV's threads (cv2.setNumThreads, default 1).

One line per frame: ``camera`` (the topic), ``seq``, ``received`` (time.time() on arrival),
``latency`` (received - header.stamp, s), ``bytes`` (JPEG size), ``objects`` (found),
``vertices`` (their total), ``work`` (thread CPU s of decode + segment), ``decode`` (of which
decoding), ``cpu``
(time.process_time() after the frame: the bench subtracts two of them for a round);
``event`` is ``frame``. On SIGUSR1 it writes ``{"event": "mark", "cpu": ...}``: the process CPU
between rounds, read without a ROS call.
Callbacks of different topics run on rospy's threads, one per topic: a lock serialises
the work so ``work`` is one frame's.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
import time

import cv2
import numpy as np
import rospy
from sensor_msgs.msg import CompressedImage

from drvs.algorithms import ColourModel


def main() -> int:
    rospy.init_node('image_robot')
    topics = [t.strip() for t in str(rospy.get_param('~topics')).split(',') if t.strip()]
    out = open(rospy.get_param('~out'), 'a', buffering=1)  # noqa: SIM115 - closed at shutdown
    algorithm = str(rospy.get_param('~algorithm', 'colour:150,0,0,255,80,80'))
    segment = bool(rospy.get_param('~segment', True))
    # OpenCV's worker threads spin while they wait: with them a robot's process CPU for one frame
    # varied threefold between runs. One thread: the CPU is the decoding and segmenting itself.
    cv2.setNumThreads(int(rospy.get_param('~threads', 1)))
    model = ColourModel.parse(algorithm.split(':', 1)[1])
    lock = threading.Lock()

    def on_frame(message: CompressedImage, topic: str) -> None:
        received = time.time()
        with lock:
            started = time.thread_time()
            objects = []
            decoded = started
            if segment:
                bgr = cv2.imdecode(np.frombuffer(message.data, np.uint8), cv2.IMREAD_COLOR)
                decoded = time.thread_time()
                objects = model.detect(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
            work = time.thread_time() - started
            record = {
                'event': 'frame',
                'camera': topic,
                'seq': message.header.seq,
                'received': received,
                'latency': received - message.header.stamp.to_sec(),
                'bytes': len(message.data),
                'objects': len(objects),
                'vertices': sum(len(o.outline) for o in objects),
                'work': work,
                'decode': decoded - started,
                'cpu': time.process_time(),
            }
            if not out.closed:
                out.write(json.dumps(record) + '\n')

    def close() -> None:
        with lock:
            out.close()

    for topic in topics:
        rospy.Subscriber(
            topic, CompressedImage, on_frame, callback_args=topic, queue_size=2, buff_size=1 << 22
        )

    def mark(*_) -> None:
        with lock:
            if not out.closed:
                out.write(json.dumps({'event': 'mark', 'cpu': time.process_time()}) + '\n')

    signal.signal(signal.SIGUSR1, mark)
    rospy.on_shutdown(close)
    rospy.loginfo('image_robot: subscribed to %d topic(s)', len(topics))
    rospy.spin()
    return 0


if __name__ == '__main__':
    sys.exit(main())
