"""``drvs_calibrate``: a camera's pose in ``map`` from one image and floor points, for tf and world files.

The image from a file (``--image``) or one sensor_msgs/Image of a running graph
(``--topic``); the intrinsics and the tf frame as the options say; the floor points and the
solving are :mod:`drvs.vision.calibration`'s. Its options, the order in which intrinsics
and the frame are taken, and its exit codes: docs/tutorials/your-camera.md.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
import xmlrpc.client
from pathlib import Path

import cv2
import numpy as np
import rosgraph
import rospy

from drvs.ros.service_client import TimeoutTransport
from drvs.vision.calibration import (
    CalibrationError,
    Intrinsics,
    detect_tags,
    parse_distortion,
    parse_point,
    parse_tag,
    read_camera_info_yaml,
    solve,
    tag_points,
)


def default_frame(name: str) -> str:
    """The optical frame of camera ``--name NAME`` when neither the image nor the camera info names one."""
    return f'{name}_optical_frame'


class _Parser(argparse.ArgumentParser):
    """Errors as one line, ``drvs_calibrate: error: ...``, exit code 2."""

    def error(self, message: str):
        self.exit(2, f'{self.prog}: error: {message} (see --help)\n')


def _argument(parse):
    """An argparse type from a parser raising CalibrationError."""

    def convert(text: str):
        try:
            return parse(text)
        except CalibrationError as error:
            raise argparse.ArgumentTypeError(str(error)) from None

    convert.__name__ = parse.__name__.removeprefix('parse_')
    return convert


NUMBER_LISTS = ('--distortion', '--point', '--tag')
"""Options whose value may start with a minus sign, which argparse would take for an option."""


def _attach_values(argv: list[str]) -> list[str]:
    """``--distortion -0.2,0.1,...`` -> ``--distortion=-0.2,0.1,...``, so argparse takes it as the value."""
    joined, i = [], 0
    while i < len(argv):
        if argv[i] in NUMBER_LISTS and i + 1 < len(argv) and re.match(r'-[0-9.]', argv[i + 1]):
            joined.append(f'{argv[i]}={argv[i + 1]}')
            i += 2
        else:
            joined.append(argv[i])
            i += 1
    return joined


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = _Parser(
        prog='drvs_calibrate',
        description=(
            "Compute a camera's pose in map from one image and 4 or more floor points at known map "
            'positions (cv2.solvePnP), and print it as static_transform_publisher arguments and as '
            'a world file vision_systems entry.'
        ),
        epilog=(
            'Intrinsics, first match wins: --fx/--fy/--cx/--cy; --camera-info; the camera_info topic '
            'next to --topic. Example: drvs_calibrate --topic /cam1/image_raw --tag 0:1,1 --tag 1:3,1 '
            '--tag 2:3,2.5 --tag 3:1,2.5 --name cam1'
        ),
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument('--image', metavar='FILE', help='an image file (any format cv2.imread reads)')
    source.add_argument('--topic', metavar='TOPIC', help='take one sensor_msgs/Image from this topic')
    parser.add_argument(
        '--camera-info',
        metavar='FILE|TOPIC',
        help='intrinsics: a camera_calibration_parsers YAML file, or a sensor_msgs/CameraInfo topic',
    )
    for name in ('fx', 'fy'):
        parser.add_argument(f'--{name}', type=float, help=f'intrinsics: focal length {name}, pixels')
    for name in ('cx', 'cy'):
        parser.add_argument(
            f'--{name}', type=float, help=f'intrinsics: principal point {name}, OpenCV pixel coordinates'
        )
    parser.add_argument(
        '--distortion',
        type=_argument(parse_distortion),
        metavar='K1,K2,P1,P2,K3',
        help='plumb_bob distortion, with --fx --fy --cx --cy',
    )
    parser.add_argument(
        '--tag',
        action='append',
        default=[],
        type=_argument(parse_tag),
        metavar='ID:X,Y',
        help='a tag36h11 AprilTag lying flat on the floor with its centre at map (X, Y); repeat',
    )
    parser.add_argument(
        '--point',
        action='append',
        default=[],
        metavar='U,V:X,Y',
        help='pixel (U, V) shows map (X, Y, 0); OpenCV pixel coordinates: the centre of the '
        'top-left pixel is 0,0, column first; repeat',
    )
    parser.add_argument('--name', default='cam1', help="the world file entry's name (default cam1)")
    parser.add_argument(
        '--frame',
        help="the camera's optical frame for tf (default: the frame_id of the image, else of the camera "
        'info, else NAME_optical_frame)',
    )
    parser.add_argument('--json', metavar='FILE', help='also write everything printed to FILE as JSON')
    parser.add_argument(
        '--reference',
        metavar='FILE',
        help="write the image to FILE as the camera's reference of its empty floor for the foreground "
        "algorithm (the vision system's ~reference); without --tag and --point, do only that",
    )
    parser.add_argument(
        '--timeout', type=float, default=10.0, help='seconds for everything taken from topics (default 10)'
    )
    args = parser.parse_args(_attach_values(argv))
    try:
        args.point = [parse_point(text, i) for i, text in enumerate(args.point, 1)]
    except CalibrationError as error:
        parser.error(f'argument --point: {error}')
    given = [name for name in ('fx', 'fy', 'cx', 'cy') if getattr(args, name) is not None]
    if given and len(given) < 4:
        missing = ', '.join(f'--{n}' for n in ('fx', 'fy', 'cx', 'cy') if n not in given)
        parser.error(f'intrinsics: {missing} missing: give all of --fx --fy --cx --cy, or --camera-info')
    if args.distortion is not None and not given:
        parser.error('--distortion goes with --fx --fy --cx --cy (a camera info carries its own)')
    args.reference_only = bool(args.reference) and not args.tag and not args.point
    if not given and not args.camera_info and not args.topic and not args.reference_only:
        parser.error('no intrinsics: give --camera-info FILE|TOPIC, or --fx --fy --cx --cy')
    if not args.name.replace('_', 'a').isalnum() or not args.name[0].isalpha():
        parser.error(f'--name {args.name!r}: a ROS name: letters, digits and _, starting with a letter')
    if not args.timeout > 0:
        parser.error(f'--timeout {args.timeout}: must be positive')
    return args


# -- the graph ---------------------------------------------------------------------------------
class Deadline:
    """One ``--timeout`` for every step that waits on the graph."""

    def __init__(self, timeout: float):
        self.timeout = timeout
        self._end = time.monotonic() + timeout

    def left(self) -> float:
        return max(0.0, self._end - time.monotonic())


def join_graph(deadline: Deadline) -> None:
    """Start this process's node, once the master answers: rospy.init_node would wait for it forever."""
    uri = rosgraph.get_master_uri()
    try:
        transport = TimeoutTransport(max(0.1, min(2.0, deadline.left())))
        with xmlrpc.client.ServerProxy(uri, transport=transport) as master:
            master.getPid('/drvs_calibrate')
    except (OSError, xmlrpc.client.Error) as error:
        raise CalibrationError(
            f'no ROS master at {uri} ({error}): start roscore and the camera driver, '
            'set ROS_MASTER_URI (source scripts/env.sh), or use --image FILE'
        ) from None
    rospy.init_node('drvs_calibrate', anonymous=True, disable_signals=True)


def take_message(topic: str, message_type, deadline: Deadline):
    """One message from ``topic``, or CalibrationError naming the topic and what is published."""
    kind = message_type._type
    published = dict(rospy.get_published_topics())
    name = rospy.resolve_name(topic)
    if published.get(name, kind) != kind:
        raise CalibrationError(f'{name} carries {published[name]}, not {kind}: give a {kind} topic')
    try:
        return rospy.wait_for_message(name, message_type, timeout=max(0.001, deadline.left()))
    except rospy.ROSException:
        others = sorted(t for t, k in rospy.get_published_topics() if k == kind)
        publishers = 'a publisher' if name in dict(rospy.get_published_topics()) else 'no publisher'
        raise CalibrationError(
            f'no {kind} on {name} within {deadline.timeout:g} s ({publishers}; '
            f'{kind} topics: {", ".join(others) or "none"}): is the camera running? (rostopic hz {name})'
        ) from None


def image_from_topic(topic: str, deadline: Deadline) -> tuple[np.ndarray, str]:
    """(BGR image, header frame_id) of one sensor_msgs/Image."""
    from cv_bridge import CvBridge, CvBridgeError
    from sensor_msgs.msg import Image

    message = take_message(topic, Image, deadline)
    try:
        image = CvBridge().imgmsg_to_cv2(message, 'bgr8')
    except CvBridgeError as error:
        raise CalibrationError(
            f'{topic}: cannot convert a {message.encoding} image to bgr8 ({error}): give a colour '
            'or mono image topic'
        ) from None
    return image, message.header.frame_id


def intrinsics_from_topic(topic: str, deadline: Deadline) -> Intrinsics:
    from image_geometry import PinholeCameraModel
    from sensor_msgs.msg import CameraInfo

    message = take_message(topic, CameraInfo, deadline)
    model = PinholeCameraModel()
    model.fromCameraInfo(message)
    return Intrinsics.from_matrix(
        f'camera info {topic}',
        np.asarray(model.intrinsicMatrix()),
        np.asarray(model.distortionCoeffs()).ravel(),
        message.distortion_model,
        message.width,
        message.height,
        message.header.frame_id,
    )


# -- the command -------------------------------------------------------------------------------
def read_image(path: str) -> np.ndarray:
    if not Path(path).is_file():
        raise CalibrationError(f'--image {path}: no such file')
    image = cv2.imread(path, cv2.IMREAD_COLOR)
    if image is None:
        raise CalibrationError(f'--image {path}: cannot read it as an image (not a format OpenCV reads?)')
    return image


def _camera_info_is_file(value: str) -> bool:
    return Path(value).is_file() or value.endswith(('.yaml', '.yml'))


def sibling_camera_info(image_topic: str) -> str:
    """``/cam1/image_raw`` -> ``/cam1/camera_info``."""
    namespace, slash, _ = image_topic.rstrip('/').rpartition('/')
    return f'{namespace}{slash}camera_info'


def calibrate(args: argparse.Namespace) -> int:
    """Run the command; 0 with a pose printed, 2 with one line on stderr."""
    try:
        return _calibrate(args)
    except CalibrationError as error:
        print(f'drvs_calibrate: error: {error}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print('drvs_calibrate: interrupted', file=sys.stderr)
        return 130
    finally:
        if rospy.core.is_initialized():
            rospy.signal_shutdown('drvs_calibrate done')


def write_reference(path: str, image: np.ndarray) -> None:
    """Write ``image`` (BGR) to ``path`` as the empty floor's reference (``foreground``)."""
    try:
        written = cv2.imwrite(path, image)
    except cv2.error as error:
        raise CalibrationError(f'--reference {path}: cannot write it: {error.err}') from None
    if not written:
        raise CalibrationError(
            f'--reference {path}: cannot write it (a folder that exists, an image suffix?)'
        )
    height, width = image.shape[:2]
    print(
        f'drvs_calibrate: wrote the reference of the empty floor, {width}x{height}, to {path}',
        file=sys.stderr,
    )


def _calibrate(args: argparse.Namespace) -> int:
    deadline = Deadline(args.timeout)
    if args.reference_only:
        if args.topic:
            join_graph(deadline)
        image = image_from_topic(args.topic, deadline)[0] if args.topic else read_image(args.image)
        write_reference(args.reference, image)
        return 0
    intrinsics, info_topic = None, None
    if args.fx is not None:
        intrinsics = Intrinsics.from_values(args.fx, args.fy, args.cx, args.cy, args.distortion or ())
    elif args.camera_info and _camera_info_is_file(args.camera_info):
        intrinsics = read_camera_info_yaml(args.camera_info)
    else:
        info_topic = args.camera_info or sibling_camera_info(args.topic)
    if args.topic or info_topic:
        join_graph(deadline)
    frame_id = ''
    if args.topic:
        image, frame_id = image_from_topic(args.topic, deadline)
    else:
        image = read_image(args.image)
    if info_topic:
        intrinsics = intrinsics_from_topic(info_topic, deadline)
    height, width = image.shape[:2]
    if intrinsics.width and (intrinsics.width, intrinsics.height) != (width, height):
        raise CalibrationError(
            f'the camera info is for {intrinsics.width}x{intrinsics.height} images, this one is '
            f'{width}x{height}: give the camera info of this resolution'
        )
    points = list(args.point)
    if args.tag:
        points = tag_points(args.tag, detect_tags(image, intrinsics)) + points
    calibration = solve(points, intrinsics, width, height)
    if args.reference:
        write_reference(args.reference, image)
    frame = args.frame or frame_id or intrinsics.frame_id or default_frame(args.name)
    print(calibration.report(args.name, frame))
    for note in calibration.notes:
        print(f'drvs_calibrate: note: {note}', file=sys.stderr)
    if args.json:
        try:
            Path(args.json).write_text(json.dumps(calibration.to_json(args.name, frame), indent=2) + '\n')
        except OSError as error:
            raise CalibrationError(f'--json {args.json}: cannot write it: {error.strerror}') from None
    return 0
