"""Message <-> core-type conversions (plain tuples, numpy arrays and shapely geometry)."""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from geometry_msgs.msg import Point32, Polygon

from drvs.common.status import Refusal
from drvs.msg import BoundingBox, DetectedObject
from drvs.srv import DetectObjectBoundaryResponse

Point = tuple[float, float]
Box = tuple[float, float, float, float]  # min_x, min_y, max_x, max_y


def polygon_to_points(polygon: Polygon) -> list[Point]:
    """geometry_msgs/Polygon -> [(x, y), ...] (z dropped)."""
    return [(p.x, p.y) for p in polygon.points]


def points_to_polygon(points: Iterable[Sequence[float]]) -> Polygon:
    """[(x, y), ...] -> geometry_msgs/Polygon on the floor (z = 0)."""
    return Polygon(points=[Point32(float(x), float(y), 0.0) for x, y, *_ in points])


def box_to_msg(box: Box) -> BoundingBox:
    return BoundingBox(*map(float, box))


def msg_to_box(msg: BoundingBox) -> Box:
    return (msg.min_x, msg.min_y, msg.max_x, msg.max_y)


def bounds_of(points: Iterable[Sequence[float]]) -> Box:
    xs, ys = zip(*((p[0], p[1]) for p in points), strict=True)
    return (min(xs), min(ys), max(xs), max(ys))


def points_to_detected_object(
    points: Sequence[Sequence[float]],
    label: str = '',
    confidence: float = 0.0,
    height: float = 0.0,
    clearance: float = 0.0,
) -> DetectedObject:
    """An outline (counter-clockwise on the floor), its label, the algorithm's confidence (0-1;
    0: unknown), the height of its top and of its underside (metres; 0: unknown) ->
    drvs/DetectedObject with its bounding box (the fusion stage's fields at their defaults)."""
    return DetectedObject(
        boundary=points_to_polygon(points),
        bounding_box=box_to_msg(bounds_of(points)),
        label=label,
        height=height,
        clearance=clearance,
        confidence=confidence,
    )


def refusal_to_detect_response(refusal: Refusal) -> DetectObjectBoundaryResponse:
    """A DetectObjectBoundary response that refuses: status, message and retry_after of ``refusal``."""
    return DetectObjectBoundaryResponse(
        accepted=False,
        status=refusal.status,
        message=refusal.message,
        vision_systems=0,
        retry_after=refusal.retry_after,
    )
