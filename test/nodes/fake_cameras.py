#!/usr/bin/env python3
"""Fake vision systems for load tests: several in one process, each calling back once per forward.

Every camera named in ``~cameras`` serves ``~<name>/detect_object_boundary``
(run as ``__name:=cams0``: ``/cams0/c03/detect_object_boundary``), registers
its field of view with the DRVS server and renews it at half the lease the
server grants. For every forward it accepts it calls the request's callback
service back exactly once, from the camera's own worker in arrival order, with
one object: the part of the region of interest inside its field of view. No
rendering, so twenty of them fit on two cores where twenty real vision systems
do not; a test that uses them says so.

Parameters:

- ``~cameras`` (required): YAML mapping of camera name to field of view ``[[x, y], ...]``,
  or to ``{fov: [[x, y], ...], algorithms: [name, ...]}`` to register algorithm names
  (default ``[]``: the built-ins).
- ``~output`` (required): JSON lines, one per event, each with ``kind`` and ``camera``:
  ``forward`` (request_id, callback_service, caller), ``callback`` (request_id,
  callback_service, ok, error), ``register`` (status, message, lease, retry_after).
- ``~server`` (default ``/drvs/register_vision_service``).
- ``~callback_timeout`` (s, default 2), ``~queue_size`` (default 1000: beyond it a
  forward is refused with ``BUSY``).
"""

import json
import queue
import threading
import time

import rospy
import yaml
from shapely.geometry import Polygon, box
from shapely.geometry.polygon import orient

from drvs.common.client_cache import ClosingCache
from drvs.common.status import ACCEPTED, BUSY
from drvs.ros.conversions import msg_to_box, points_to_detected_object, points_to_polygon
from drvs.ros.service_client import ServiceCallError, ServiceClient
from drvs.srv import (
    CallbackCoordinates,
    CallbackCoordinatesRequest,
    DetectObjectBoundary,
    DetectObjectBoundaryResponse,
    RegisterVisionService,
    RegisterVisionServiceRequest,
)

REGISTER_TIMEOUT = 2.0
RETRY = 0.2  # seconds between registration attempts after a failure, beyond retry_after


class Recorder:
    def __init__(self, path):
        self.path = path
        self.lock = threading.Lock()

    def __call__(self, **entry):
        with self.lock, open(self.path, 'a') as handle:
            handle.write(json.dumps(entry) + '\n')


class Camera:
    def __init__(self, name, field_of_view, record, callback_timeout, queue_size, algorithms=()):
        self.name = name
        self.field_of_view = [(float(x), float(y)) for x, y in field_of_view]
        self.algorithms = list(algorithms)
        self.polygon = Polygon(self.field_of_view)
        self.record = record
        self.jobs = queue.Queue(maxsize=queue_size)
        self.callbacks = ClosingCache(
            lambda service: ServiceClient(service, CallbackCoordinates, callback_timeout),
            maxsize=64,
            ttl=30.0,
        )
        self.service_name = rospy.resolve_name(f'~{name}/detect_object_boundary')
        self.lease = 0.0
        self.next_registration = 0.0

    def start(self):
        rospy.Service(self.service_name, DetectObjectBoundary, self.handle)
        threading.Thread(target=self.work, name=f'{self.name}-callbacks', daemon=True).start()

    def handle(self, request):
        self.record(
            kind='forward',
            camera=self.service_name,
            request_id=request.request_id,
            callback_service=request.callback_service,
            caller=request._connection_header.get('callerid', ''),
        )
        try:
            self.jobs.put_nowait(request)
        except queue.Full:
            return DetectObjectBoundaryResponse(
                accepted=False, status=BUSY, message='busy', vision_systems=0, retry_after=0.1
            )
        return DetectObjectBoundaryResponse(accepted=True, status=ACCEPTED, message='', vision_systems=1)

    def outline(self, request):
        region = box(*msg_to_box(request.region_of_interest))
        seen = region.intersection(self.polygon)
        shape = seen if isinstance(seen, Polygon) and seen.area > 0 else region
        return list(orient(shape).exterior.coords)[:-1]

    def work(self):
        while not rospy.is_shutdown():
            try:
                request = self.jobs.get(timeout=0.5)
            except queue.Empty:
                continue
            callback = CallbackCoordinatesRequest(
                algorithm=request.algorithm,
                request_id=request.request_id,
                vision_system=self.service_name,
                stamp=rospy.Time.now(),
                objects=[points_to_detected_object(self.outline(request))],
            )
            error = ''
            try:
                self.callbacks.get(request.callback_service).call(callback)
            except ServiceCallError as failure:
                error = str(failure)
            self.record(
                kind='callback',
                camera=self.service_name,
                request_id=request.request_id,
                callback_service=request.callback_service,
                ok=not error,
                error=error,
            )


def register_loop(cameras, server, record):
    """Register every camera, renew at half the granted lease, retry after refusals."""
    client = ServiceClient(server, RegisterVisionService, REGISTER_TIMEOUT)
    while not rospy.is_shutdown():
        now = time.monotonic()
        for camera in cameras:
            if now < camera.next_registration:
                continue
            request = RegisterVisionServiceRequest(
                service_name=camera.service_name,
                field_of_view=points_to_polygon(camera.field_of_view),
                algorithms=camera.algorithms,
            )
            try:
                answer = client.call(request)
            except ServiceCallError as error:
                rospy.logwarn_throttle(5.0, 'registration of %s failed: %s', camera.name, error)
                camera.next_registration = now + RETRY
                continue
            record(
                kind='register',
                camera=camera.service_name,
                status=answer.status,
                message=answer.message,
                lease=answer.lease,
                retry_after=answer.retry_after,
            )
            if answer.status == ACCEPTED:
                camera.lease = answer.lease
                camera.next_registration = now + max(answer.lease / 2.0, 0.1)
            else:
                camera.next_registration = now + max(answer.retry_after, 0.0) + RETRY
        time.sleep(0.05)
    client.close()


def main():
    rospy.init_node('fake_cameras')
    record = Recorder(rospy.get_param('~output'))
    layout = rospy.get_param('~cameras')
    if isinstance(layout, str):
        layout = yaml.safe_load(layout)
    cameras = [
        Camera(
            name,
            spec['fov'] if isinstance(spec, dict) else spec,
            record,
            float(rospy.get_param('~callback_timeout', 2.0)),
            int(rospy.get_param('~queue_size', 1000)),
            spec.get('algorithms', []) if isinstance(spec, dict) else [],
        )
        for name, spec in sorted(layout.items())
    ]
    for camera in cameras:
        camera.start()
    register_loop(cameras, rospy.get_param('~server', '/drvs/register_vision_service'), record)


if __name__ == '__main__':
    try:
        main()
    except rospy.ROSInterruptException:
        pass
