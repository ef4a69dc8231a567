#!/usr/bin/env python3
"""A camera driver for tests: one still image and its CameraInfo, latched on ``~image_raw``, ``~camera_info``.

Parameters: ``~image`` (an image file, required), ``~camera_info`` (a
camera_calibration_parsers YAML file, required), ``~frame_id`` (the headers'
frame, default ``camera_optical_frame``), ``~encoding`` (``rgb8`` or ``bgr8``,
default rgb8). Run as ``__name:=cam1``: ``/cam1/image_raw``, ``/cam1/camera_info``.
The YAML is read here with PyYAML, not with the code under test.
"""

import cv2
import rospy
import yaml
from cv_bridge import CvBridge
from sensor_msgs.msg import CameraInfo, Image


def main():
    rospy.init_node('still_camera')
    frame_id = rospy.get_param('~frame_id', 'camera_optical_frame')
    encoding = rospy.get_param('~encoding', 'rgb8')
    image = cv2.imread(rospy.get_param('~image'), cv2.IMREAD_COLOR)
    if encoding == 'rgb8':
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    with open(rospy.get_param('~camera_info')) as handle:
        calibration = yaml.safe_load(handle)

    stamp = rospy.Time.now()
    message = CvBridge().cv2_to_imgmsg(image, encoding)
    message.header.stamp, message.header.frame_id = stamp, frame_id
    info = CameraInfo()
    info.header.stamp, info.header.frame_id = stamp, frame_id
    info.width, info.height = calibration['image_width'], calibration['image_height']
    info.distortion_model = calibration['distortion_model']
    info.K = calibration['camera_matrix']['data']
    info.D = calibration['distortion_coefficients']['data']
    info.R = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    k = info.K
    info.P = [k[0], k[1], k[2], 0.0, k[3], k[4], k[5], 0.0, k[6], k[7], k[8], 0.0]

    rospy.Publisher('~image_raw', Image, queue_size=1, latch=True).publish(message)
    rospy.Publisher('~camera_info', CameraInfo, queue_size=1, latch=True).publish(info)
    rospy.loginfo('still_camera: latched %dx%d %s on %s', image.shape[1], image.shape[0], encoding, frame_id)
    rospy.spin()


if __name__ == '__main__':
    main()
