#!/usr/bin/env python3
"""image_camera: K cameras in one process publishing JPEG sensor_msgs/CompressedImage: image sharing.

The alternative DRVS is measured against (paper Table 1, "compressed image"): every
camera publishes its frames and every robot subscribes to every camera. One process
stands for K cameras so that 50 of them cost one interpreter, not 50.

CLI (private parameters)::

    .venv/bin/python bench/nodes/image_camera.py __name:=cams _cameras:=cam1,cam2 \\
        _image:=/tmp/photo.png _rate:=0

- ``~cameras``: comma list of camera names (default ``cam1``); camera ``c`` publishes on
  ``~c/image/compressed`` (``/cams/cam1/image/compressed`` above).
- ``~image``: an image file (anything cv2.imread reads) every camera publishes; or
- ``~world``: a world file (drvs/sim/world.py): camera ``c`` publishes the view of the world's
  ``vision_systems`` entry named ``c`` (or, when no entry has that name, the entry at the
  camera's index in ``~cameras``), rendered once at start with drvs.sim.scene (the world is
  static here).
- ``~width``, ``~height``: render at / resize to this size (default 0: the world entry's
  resolution, or the file's size).
- ``~quality``: JPEG quality for cv2.imencode (default 80).
- ``~rate``: frames per second per camera (streaming); 0 (default): publish one frame per
  camera each time the roscpp/Empty service ``~publish`` is called (it returns once every
  frame is queued to every subscriber).
- ``~frame_id``: the headers' frame_id (default ``camera``).

Each camera's frame is encoded once at start (the same bytes each time: the camera's
own CPU is not what is measured); ``header.stamp`` is the send time (rospy.Time.now()),
``header.seq`` counts frames. It logs one line with each camera's JPEG size.
"""

from __future__ import annotations

import sys
import threading

import cv2
import numpy as np
import rospy
from roscpp.srv import Empty, EmptyResponse
from sensor_msgs.msg import CompressedImage


def names_of(text) -> list[str]:
    if isinstance(text, list | tuple):
        return [str(name).strip() for name in text if str(name).strip()]
    return [name.strip() for name in str(text).split(',') if name.strip()]


def rendered_views(world_path: str, cameras: list[str], size: tuple[int, int]) -> dict[str, np.ndarray]:
    """RGB views of the world's vision systems, one per camera name."""
    from drvs.sim.scene import Scene
    from drvs.sim.world_file import load_world
    from drvs.vision.camera import PinholeCamera

    world = load_world(world_path)
    entries = {camera.name: camera for camera in world.vision_systems}
    views = {}
    with Scene(world) as scene:
        for index, name in enumerate(cameras):
            entry = entries.get(name) or world.vision_systems[index % len(world.vision_systems)]
            model = PinholeCamera.from_config(entry, size if size[0] and size[1] else None)
            views[name] = scene.render(model).rgb
    return views


def encoded(rgb: np.ndarray, quality: int) -> bytes:
    ok, data = cv2.imencode('.jpg', cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError('cv2.imencode failed')
    return data.tobytes()


def main() -> int:
    rospy.init_node('image_camera')
    cameras = names_of(rospy.get_param('~cameras', 'cam1'))
    size = (int(rospy.get_param('~width', 0)), int(rospy.get_param('~height', 0)))
    quality = int(rospy.get_param('~quality', 80))
    rate = float(rospy.get_param('~rate', 0.0))
    frame_id = str(rospy.get_param('~frame_id', 'camera'))
    image, world = rospy.get_param('~image', ''), rospy.get_param('~world', '')
    if bool(image) == bool(world):
        rospy.logfatal('image_camera: give exactly one of ~image and ~world')
        return 2
    if image:
        bgr = cv2.imread(image, cv2.IMREAD_COLOR)
        if bgr is None:
            rospy.logfatal('image_camera: cannot read image %s', image)
            return 2
        if size[0] and size[1] and (bgr.shape[1], bgr.shape[0]) != size:
            bgr = cv2.resize(bgr, size, interpolation=cv2.INTER_AREA)
        views = dict.fromkeys(cameras, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    else:
        views = rendered_views(world, cameras, size)
    frames = {name: encoded(rgb, quality) for name, rgb in views.items()}
    publishers = {
        name: rospy.Publisher(f'~{name}/image/compressed', CompressedImage, queue_size=2) for name in cameras
    }
    lock = threading.Lock()

    def publish_all() -> None:
        with lock:
            for name in cameras:
                message = CompressedImage(format='jpeg', data=frames[name])
                message.header.stamp, message.header.frame_id = rospy.Time.now(), frame_id
                publishers[name].publish(message)

    rospy.loginfo(
        'image_camera: %d camera(s), JPEG q%d, bytes %s',
        len(cameras),
        quality,
        ','.join(str(len(frames[name])) for name in cameras),
    )
    if rate > 0:
        period = rospy.Rate(rate)
        while not rospy.is_shutdown():
            publish_all()
            try:
                period.sleep()
            except rospy.ROSInterruptException:
                break
    else:
        rospy.Service('~publish', Empty, lambda _request: (publish_all(), EmptyResponse())[1])
        rospy.spin()
    return 0


if __name__ == '__main__':
    sys.exit(main())
