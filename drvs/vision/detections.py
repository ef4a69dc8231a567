"""A vision system's one-shot requests (:class:`Job`) and the objects found on its newest frame,
kept so that requests sharing a frame and an algorithm detect once (:class:`FrameDetections`).

No ROS here; the node that queues jobs is :mod:`drvs.ros.vision_system` (docs/nodes/vision_system.md).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

from drvs.algorithms import Parsed
from drvs.vision.frame import Frame
from drvs.vision.pipeline import FloorObject, on_floor

__all__ = ['MAX_DETECTIONS_KEPT', 'FrameDetections', 'Job']

MAX_DETECTIONS_KEPT = 16
"""Algorithm strings whose objects are kept for the newest frame; callers choose them, so capped."""


@dataclass(frozen=True)
class Job:
    """A one-shot request, queued for a worker. Like a watch's :class:`drvs.vision.watch_runner.Terms`,
    it names the algorithm (parsed), the callback service and the request id a callback carries.

    :param region: the region of interest (min_x, min_y, max_x, max_y) in metres.
    :param arrival: when the request came (ROS seconds): a frame at most ``~max_frame_age``
        older serves it.
    """

    algorithm: Parsed
    region: tuple[float, float, float, float]
    callback_service: str
    request_id: str
    arrival: float
    fused: bool = False  # for the server's fusion stage: call back even when nothing is found
    callback_uri: str = ''  # the callback service's address (a caller at another site); '': ask the master


class FrameDetections:
    """The objects found on the newest frame, per algorithm string (:func:`drvs.vision.pipeline.on_floor`).

    Requests that share a frame (``~max_frame_age``, :class:`drvs.vision.pipeline.FrameCache`) and
    ask with the same algorithm detect once, as the watches due at one time do; each
    request then only clips them to its region (:func:`drvs.vision.pipeline.in_region`). Not for
    algorithms with memory (``streaming``): what they find depends on what they have seen.
    Thread-safe: ``FrameDetections._lock`` guards the frame and its objects; detection
    runs outside it (two workers may detect at once; the newer frame's objects are kept).

    :param limit: algorithm strings kept for one frame (callers choose them).
    """

    def __init__(self, limit: int = MAX_DETECTIONS_KEPT):
        self.limit = limit
        self._lock = threading.Lock()
        self._frame: Frame | None = None
        self._objects: dict[str, list[FloorObject]] = {}  # algorithm text -> on_floor(self._frame, algorithm)

    def on_floor(self, frame: Frame, algorithm: Parsed) -> list[FloorObject]:
        """:func:`drvs.vision.pipeline.on_floor` of ``frame`` and ``algorithm`` (a parsed algorithm)."""
        if algorithm.algorithm.streaming:
            return on_floor(frame, algorithm)
        with self._lock:
            objects = self._objects.get(algorithm.text) if frame is self._frame else None
        if objects is not None:
            return objects
        objects = on_floor(frame, algorithm)
        with self._lock:
            if self._frame is None or (frame is not self._frame and frame.stamp >= self._frame.stamp):
                self._frame, self._objects = frame, {}
            if frame is self._frame and len(self._objects) < self.limit:
                self._objects[algorithm.text] = objects
        return objects
