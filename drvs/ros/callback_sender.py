"""A vision system's calls back to the robots: what it found, on their CallbackCoordinates services.

:class:`CallbackSender` keeps one connection per callback service (the least recently used and
idle ones closed), counts what it sends for ``~stats`` and the health report, and puts the
outlines on ``/drvs/markers`` for RViz. Described in docs/nodes/vision_system.md.
"""

from __future__ import annotations

import io
from collections.abc import Callable

import rospy
from visualization_msgs.msg import MarkerArray

from drvs.common.client_cache import ClosingCache
from drvs.common.counters import PeriodCounts
from drvs.ros.conversions import points_to_detected_object
from drvs.ros.markers import detection_markers
from drvs.ros.service_client import ServiceCallError, ServiceClient
from drvs.srv import CallbackCoordinates, CallbackCoordinatesRequest

__all__ = ['CallbackSender']


class CallbackSender:
    """Sends CallbackCoordinates to the caller of a request or a watch: at its ``callback_uri`` when
    the request gave one (a caller at another site), else looked up on the master.

    :param count: the node's counter (``callbacks``, ``callback_failures``, ``callback_bytes``,
        ``objects``).
    :param timeout: limit on one callback, seconds (``~callback_timeout``).
    :param max_clients: connections kept (``~max_callback_clients``).
    :param idle: seconds after which an unused connection is closed (``~callback_idle``).
    """

    def __init__(self, count: Callable[..., None], timeout: float, max_clients: int, idle: float):
        self._count = count
        self._clients = ClosingCache(
            lambda key: ServiceClient(key[0], CallbackCoordinates, timeout, uri=key[1] or None),
            maxsize=max_clients,
            ttl=idle,
        )
        self.period = PeriodCounts()  # 'attempted' and 'failed' callbacks, for the health report
        self.markers_pub: rospy.Publisher | None = None

    def start(self, markers_topic: str) -> None:
        """Advertise the markers topic (the server's, next to its registration service)."""
        self.markers_pub = rospy.Publisher(markers_topic, MarkerArray, queue_size=10)

    def send(self, asked, vision_system: str, stamp: float, found) -> bool:
        """Send ``found`` (:class:`drvs.vision.pipeline.Located`: outline, label, confidence,
        height, clearance; [] for a watch's "all gone") seen in a frame of ``stamp`` to the caller
        of ``asked`` (a :class:`drvs.vision.detections.Job` or a watch's
        :class:`drvs.vision.watch_runner.Terms`); whether the call arrived."""
        request = CallbackCoordinatesRequest(
            algorithm=asked.algorithm.text,
            request_id=asked.request_id,
            vision_system=vision_system,
            stamp=rospy.Time.from_sec(stamp),
            objects=[points_to_detected_object(*located) for located in found],
        )
        buffer = io.BytesIO()
        request.serialize(buffer)  # once: counted, then sent as it is
        client = self._clients.get((asked.callback_service, asked.callback_uri))
        self.period.add('attempted')
        try:
            client.call(request, serialized=buffer.getvalue())
        except ServiceCallError as error:
            self._count(callback_failures=1)
            self.period.add('failed')
            rospy.logwarn(
                '%s: callback for request %r dropped: %s', rospy.get_name(), asked.request_id, error
            )
            arrived = False
        else:
            self._count(callbacks=1, callback_bytes=len(buffer.getvalue()), objects=len(found))
            arrived = True
        if self.markers_pub.get_num_connections() > 0:  # after the callback: the robot waits, RViz can
            outlines = [outline for outline, *_ in found]
            self.markers_pub.publish(
                detection_markers(vision_system, asked.algorithm.text, outlines, request.stamp)
            )
        return arrived

    def expire(self) -> None:
        """Close the connections idle for longer than ``idle``."""
        self._clients.expire()

    def close(self) -> None:
        self._clients.clear()
