"""FrameDetections: one detection per frame and algorithm string; none kept for a streaming one."""

from types import SimpleNamespace

import drvs.vision.detections as detections_module
from drvs.vision.detections import FrameDetections


def parsed(text, streaming=False):
    return SimpleNamespace(text=text, algorithm=SimpleNamespace(streaming=streaming))


def test_requests_on_one_frame_with_one_algorithm_detect_once(monkeypatch):
    detected = []
    monkeypatch.setattr(
        detections_module, 'on_floor', lambda frame, algorithm: detected.append(frame) or [frame]
    )
    detections = FrameDetections(limit=2)
    old, new = SimpleNamespace(stamp=1.0), SimpleNamespace(stamp=2.0)
    assert detections.on_floor(old, parsed('colour:a')) == [old]
    assert detections.on_floor(old, parsed('colour:a')) == [old]  # reused
    assert detected == [old]
    detections.on_floor(new, parsed('colour:a'))  # a newer frame replaces the objects kept
    detections.on_floor(new, parsed('colour:a'))
    detections.on_floor(old, parsed('colour:a'))  # an older frame is detected, not kept
    detections.on_floor(new, parsed('colour:a'))
    assert detected == [old, new, old]
    for text in ('colour:b', 'colour:c', 'colour:c'):  # at most `limit` algorithm strings kept
        detections.on_floor(new, parsed(text))
    assert detected == [old, new, old, new, new, new]
    detections.on_floor(new, parsed('motion', streaming=True))
    detections.on_floor(new, parsed('motion', streaming=True))
    assert detected[-2:] == [new, new]
