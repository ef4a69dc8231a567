"""One DetectObjectBoundary call from a test process, on a fresh connection closed afterwards."""

from __future__ import annotations

from drvs.ros.service_client import ServiceClient
from drvs.srv import DetectObjectBoundary, DetectObjectBoundaryRequest

CALLBACK = '/robot/callback_coordinates'


def detect(service: str, algorithm: str, region, request_id: str, callback: str = CALLBACK, timeout=10.0):
    """Ask ``service`` for ``algorithm`` in ``region`` (min_x, min_y, max_x, max_y); the response."""
    message = DetectObjectBoundaryRequest(
        algorithm=algorithm, callback_service=callback, request_id=request_id
    )
    r = message.region_of_interest
    r.min_x, r.min_y, r.max_x, r.max_y = region
    client = ServiceClient(service, DetectObjectBoundary, timeout)
    try:
        return client.call(message)
    finally:
        client.close()
