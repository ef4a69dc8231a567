#!/usr/bin/env python3
"""A camera driver played by the test: a drawn image of a known floor, its CameraInfo and a static tf.

The camera stands at ``~eye`` looking at ``~target`` (image up along ``~up``) with
intrinsics ``~fx``, ``~fy``, ``~cx``, ``~cy`` (OpenCV convention: pixel centres at
integers) and plumb_bob ``~distortion``, ``~width`` x ``~height``. The floor is
``~floor_colour``; one box with floor corners ``~box`` ([[x, y], ...], any convex
polygon), height ``~box_height`` (0: a flat patch) and colour ``~box_colour``
is drawn where this camera would see its top face: its edges sampled densely and
projected with cv2.projectPoints, so straight edges bend with the lens. No DRVS
code draws the picture; only OpenCV and numpy.

Published at ``~rate`` Hz, stamped with the time of publication:

- ``~image_raw`` (sensor_msgs/Image, ``~encoding``: rgb8, bgr8, mono8 or bayer_rggb8);
- ``~image_raw/compressed`` (sensor_msgs/CompressedImage, PNG) when ``~compressed``;
- ``~camera_info`` (sensor_msgs/CameraInfo, plumb_bob);
- ``~depth`` (sensor_msgs/Image, ``~depth_encoding`` 32FC1 metres or 16UC1 mm, along
  the optical axis; floor and box top, no distortion, aligned pixel for pixel with the
  colour image; ``~depth_size`` [width, height] resizes it, as a camera whose depth is not
  registered to its colour) when ``~publish_depth``;
- tf_static ``map`` -> ``~frame_id``, unless ``~publish_tf`` is false (the camera's pose is
  then somebody else's business, e.g. a calibrated static_transform_publisher).

``~pause`` (std_msgs/Bool, subscribed): true stops publishing frames (a dead feed),
false resumes. ``~stamps`` (file, optional): every published stamp, one per line.
"""

import threading

import cv2
import numpy as np
import rospy
import tf2_ros
from cv_bridge import CvBridge
from geometry_msgs.msg import TransformStamped
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Bool

from drvs.common.transforms import quaternion_from_matrix


def optical_rotation(eye, target, up):
    """map <- optical: columns x right, y down, z forward."""
    forward = np.subtract(target, eye).astype(float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    return np.column_stack([right, np.cross(forward, right), forward])


def densify(corners, per_edge=64):
    corners = np.asarray(corners, float)
    points = []
    for a, b in zip(corners, np.roll(corners, -1, axis=0), strict=True):
        for t in np.linspace(0.0, 1.0, per_edge, endpoint=False):
            points.append(a + t * (b - a))
    return np.asarray(points)


class SyntheticCamera:
    def __init__(self):
        get = rospy.get_param
        self.eye = np.asarray(get('~eye'), float)
        self.rotation = optical_rotation(self.eye, get('~target'), get('~up', [0.0, 1.0, 0.0]))
        self.width, self.height = int(get('~width', 640)), int(get('~height', 480))
        fx, fy = float(get('~fx')), float(get('~fy'))
        cx, cy = float(get('~cx', (self.width - 1) / 2.0)), float(get('~cy', (self.height - 1) / 2.0))
        self.K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        self.D = np.asarray(get('~distortion', [0.0] * 5), float)
        self.frame_id = get('~frame_id', 'synthetic_optical_frame')
        self.encoding = get('~encoding', 'rgb8')
        self.compressed = bool(get('~compressed', False))
        self.publish_depth = bool(get('~publish_depth', False))
        self.depth_encoding = get('~depth_encoding', '32FC1')
        self.stamps = get('~stamps', '')
        box = np.asarray(get('~box'), float)
        box_height = float(get('~box_height', 0.0))
        self.box_colour = get('~box_colour', [0, 0, 220])
        self.rgb = self.draw(box, box_height, get('~floor_colour', [230, 230, 230]), self.box_colour)
        self.depth = self.draw_depth(box, box_height) if self.publish_depth else None
        if self.depth is not None and get('~depth_size', None):  # a depth image not registered to the colour
            self.depth = cv2.resize(self.depth, tuple(get('~depth_size')), interpolation=cv2.INTER_NEAREST)
        self.bridge = CvBridge()
        self.paused = threading.Event()

    # -- drawing ---------------------------------------------------------------------------------
    def project(self, points):
        camera_from_map = self.rotation.T
        rvec, _ = cv2.Rodrigues(camera_from_map)
        tvec = -camera_from_map @ self.eye
        pixels, _ = cv2.projectPoints(np.asarray(points, float).reshape(-1, 1, 3), rvec, tvec, self.K, self.D)
        return pixels.reshape(-1, 2)

    def draw(self, box, box_height, floor_colour, box_colour):
        image = np.empty((self.height, self.width, 3), np.uint8)
        image[:] = floor_colour
        top = densify(box)
        pixels = self.project(np.c_[top, np.full(len(top), box_height)])
        # Pixel (r, c) is filled when its centre (c, r) lies inside: fillPoly with sub-pixel precision.
        shift = 8
        points = np.round(pixels * (1 << shift)).astype(np.int32)
        cv2.fillPoly(image, [points], box_colour, lineType=cv2.LINE_8, shift=shift)
        return image

    def draw_depth(self, box, box_height):
        rows, cols = np.mgrid[0 : self.height, 0 : self.width]
        rays = np.stack(
            [(cols - self.K[0, 2]) / self.K[0, 0], (rows - self.K[1, 2]) / self.K[1, 1], np.ones(rows.shape)],
            axis=-1,
        )
        down = (rays @ self.rotation.T)[..., 2]  # map z of each ray with optical z = 1
        with np.errstate(divide='ignore', invalid='ignore'):
            depth = np.where(down < 0, -self.eye[2] / down, np.nan)
            top = np.where(down < 0, (box_height - self.eye[2]) / down, np.nan)
        mask = np.all(self.rgb == self.box_colour, axis=-1)  # aligned: the box's own pixels
        depth[mask] = top[mask]
        return depth.astype(np.float32)

    # -- messages --------------------------------------------------------------------------------
    def image_message(self, stamp):
        if self.encoding == 'rgb8':
            message = self.bridge.cv2_to_imgmsg(self.rgb, 'rgb8')
        elif self.encoding == 'bgr8':
            message = self.bridge.cv2_to_imgmsg(np.ascontiguousarray(self.rgb[..., ::-1]), 'bgr8')
        elif self.encoding == 'mono8':
            message = self.bridge.cv2_to_imgmsg(cv2.cvtColor(self.rgb, cv2.COLOR_RGB2GRAY), 'mono8')
        elif self.encoding == 'bayer_rggb8':
            mosaic = np.empty((self.height, self.width), np.uint8)
            mosaic[0::2, 0::2] = self.rgb[0::2, 0::2, 0]
            mosaic[0::2, 1::2] = self.rgb[0::2, 1::2, 1]
            mosaic[1::2, 0::2] = self.rgb[1::2, 0::2, 1]
            mosaic[1::2, 1::2] = self.rgb[1::2, 1::2, 2]
            message = self.bridge.cv2_to_imgmsg(mosaic, 'bayer_rggb8')
        else:
            raise ValueError(f'~encoding: {self.encoding!r} is not one this test camera draws')
        message.header.stamp = stamp
        message.header.frame_id = self.frame_id
        return message

    def info_message(self, stamp):
        info = CameraInfo(width=self.width, height=self.height, distortion_model='plumb_bob')
        info.header.stamp, info.header.frame_id = stamp, self.frame_id
        info.D = list(self.D)
        info.K = list(self.K.ravel())
        info.R = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]
        info.P = list(np.c_[self.K, np.zeros(3)].ravel())
        return info

    def depth_message(self, stamp):
        if self.depth_encoding == '16UC1':
            millimetres = np.nan_to_num(self.depth * 1000.0, nan=0.0).round().astype(np.uint16)
            message = self.bridge.cv2_to_imgmsg(millimetres, '16UC1')
        else:
            message = self.bridge.cv2_to_imgmsg(self.depth, '32FC1')
        message.header.stamp, message.header.frame_id = stamp, self.frame_id
        return message

    def run(self):
        transform = TransformStamped()
        transform.header.stamp = rospy.Time.now()
        transform.header.frame_id = 'map'
        transform.child_frame_id = self.frame_id
        t = transform.transform
        t.translation.x, t.translation.y, t.translation.z = map(float, self.eye)
        t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w = map(
            float, quaternion_from_matrix(self.rotation)
        )
        if rospy.get_param('~publish_tf', True):
            broadcaster = tf2_ros.StaticTransformBroadcaster()
            broadcaster.sendTransform(transform)
        image_pub = rospy.Publisher('~image_raw', Image, queue_size=1)
        compressed_pub = rospy.Publisher('~image_raw/compressed', CompressedImage, queue_size=1)
        info_pub = rospy.Publisher('~camera_info', CameraInfo, queue_size=1)
        depth_pub = rospy.Publisher('~depth', Image, queue_size=1)
        rospy.Subscriber('~pause', Bool, lambda m: self.paused.set() if m.data else self.paused.clear())
        rate = rospy.Rate(float(rospy.get_param('~rate', 10.0)))
        while not rospy.is_shutdown():
            if not self.paused.is_set():
                stamp = rospy.Time.now()
                info_pub.publish(self.info_message(stamp))
                if self.depth is not None:
                    depth_pub.publish(self.depth_message(stamp))
                if self.compressed:
                    message = self.bridge.cv2_to_compressed_imgmsg(self.rgb[..., ::-1], dst_format='png')
                    message.header.stamp, message.header.frame_id = stamp, self.frame_id
                    message.format = 'rgb8; png compressed bgr8'
                    compressed_pub.publish(message)
                image_pub.publish(self.image_message(stamp))
                if self.stamps:
                    with open(self.stamps, 'a') as handle:
                        handle.write(f'{stamp.to_sec():.9f}\n')
            try:
                rate.sleep()
            except rospy.ROSInterruptException:
                break


def main():
    rospy.init_node('synthetic_camera')
    SyntheticCamera().run()


if __name__ == '__main__':
    main()
