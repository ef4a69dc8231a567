#!/usr/bin/env python3
"""A tf client for tests: looks transforms up and prints each as one JSON line, then exits.

Usage: ``tf_lookup.py [--timeout S] PARENT CHILD [PARENT CHILD ...]``. Each pair is
looked up at the latest time tf has (``rospy.Time(0)``), waiting up to ``--timeout``
seconds (default 20) for it. Each line: ``parent``, ``child``, ``stamp`` (seconds),
``translation`` [x, y, z], ``rotation`` [x, y, z, w]. Exit code 0 when every pair
resolved, 1 with tf's error on stderr otherwise.
"""

import argparse
import json
import sys

import rospy
import tf2_ros


def main() -> int:
    rospy.init_node('tf_lookup', anonymous=True)
    parser = argparse.ArgumentParser()
    parser.add_argument('--timeout', type=float, default=20.0)
    parser.add_argument('frames', nargs='+', help='PARENT CHILD pairs')
    args = parser.parse_args(rospy.myargv()[1:])
    if len(args.frames) % 2:
        parser.error('frames: expected PARENT CHILD pairs')
    buffer = tf2_ros.Buffer()
    tf2_ros.TransformListener(buffer)
    for parent, child in zip(args.frames[::2], args.frames[1::2], strict=True):
        try:
            found = buffer.lookup_transform(parent, child, rospy.Time(0), rospy.Duration(args.timeout))
        except tf2_ros.TransformException as error:
            print(f'{parent} -> {child}: {error}', file=sys.stderr)
            return 1
        t, q = found.transform.translation, found.transform.rotation
        line = {
            'parent': parent,
            'child': child,
            'stamp': found.header.stamp.to_sec(),
            'translation': [t.x, t.y, t.z],
            'rotation': [q.x, q.y, q.z, q.w],
        }
        print(json.dumps(line), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
