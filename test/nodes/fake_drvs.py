#!/usr/bin/env python3
"""A scripted fake DRVS for the blind robot's tests: no rendering, no vision systems, no world_sim.

Serves ``~detect_object_boundary`` and ``~watch_object_boundary`` (run it as
``__name:=drvs``), moves the robot body kinematically from ``/robot/cmd_vel`` (velocity in ``map``, capped at
the world's robot speed, stopped at any object it would touch, counting
contacts) and answers each request like DRVS would: ``~latency`` seconds later,
one callback per fake camera that covers the region of interest *and* sees an
object of the requested colour there (the west camera sees x < 60 % of the
floor, the east one x > 40 %, so objects in the middle are seen twice, a few
millimetres apart), in random order, each sent twice when ``~duplicate``.
The outlines are the objects' true footprints at the time of the request.

A watch (keyed by callback service and request id; duration 0 cancels it) is
evaluated every period (at least ``STEP`` seconds) until it expires: each fake
camera that covers its region calls back like a one-shot answer — with
``changes_only``, only when what it sees changed, and once with no objects when
all it had reported is gone; a new watch or a renewal reports in full.

Objects named in ``~hidden`` (comma-separated) are absent until the robot comes
within ``~appear_distance`` metres of them: an obstacle that steps onto its path.
Humans walk their waypoint loops at their speed.

A troubled server: the first ``~refuse_first`` requests are refused with status
``~refuse_status`` (a :mod:`drvs.common.status` code, any number), ``~refuse_retry_after``
and ``~refuse_message``, and no callback; every acknowledgement is held back
``~ack_delay`` seconds (its callbacks are on their way meanwhile): a slow server.

Parameters: ``~world`` (required), ``~output`` (JSON lines, required),
``~latency`` (0.15), ``~duplicate`` (true), ``~hidden`` (''),
``~appear_distance`` (0.9), ``~cameras`` (2; 0 = no vision system covers anything),
``~refuse_first`` (0, one-shot requests and watch calls together), ``~refuse_status``
(2, BUSY), ``~refuse_retry_after`` (0.3), ``~refuse_message`` ('refused by the fake
DRVS'), ``~ack_delay`` (0).

Output lines (``kind``): ``request`` (time, role, request_id, roi, vision_systems,
status name, retry_after), ``watch`` (the same and period, duration), ``appear``
(name, robot), ``truth`` every 0.2 s (time,
robot position, contacts, cmd_vels received so far, the robot's latest
/robot/status as ``status``: :func:`drvs.ros.messages.robot_status_to_dict`). Times
are seconds since the fake started.
"""

import json
import math
import queue
import random
import threading
import time

import rospy
from geometry_msgs.msg import Twist
from shapely.geometry import Point as ShapelyPoint
from shapely.geometry import Polygon, box

from drvs.algorithms import AlgorithmError, parse_algorithm
from drvs.common.status import ACCEPTED, INVALID, name
from drvs.msg import RobotStatus
from drvs.ros.conversions import msg_to_box, points_to_detected_object
from drvs.ros.messages import robot_status_to_dict
from drvs.sim.world import box_footprint
from drvs.sim.world_file import load_world
from drvs.srv import (
    CallbackCoordinates,
    CallbackCoordinatesRequest,
    DetectObjectBoundary,
    DetectObjectBoundaryResponse,
    WatchObjectBoundary,
    WatchObjectBoundaryResponse,
)

CMD_TIMEOUT = 0.5
STEP = 0.02


def position_on_loop(waypoints, speed, t):
    """Where a walker is ``t`` seconds after starting its closed waypoint loop."""
    legs = list(zip(waypoints, waypoints[1:] + waypoints[:1], strict=True))
    lengths = [math.dist(a, b) for a, b in legs]
    s = (speed * t) % sum(lengths)
    for (a, b), length in zip(legs, lengths, strict=True):
        if s <= length:
            f = s / length if length else 0.0
            return (a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]))
        s -= length
    return waypoints[0]


class FakeDrvs:
    def __init__(self):
        self.world = load_world(rospy.get_param('~world'))
        self.output = rospy.get_param('~output')
        self.latency = float(rospy.get_param('~latency', 0.15))
        self.duplicate = bool(rospy.get_param('~duplicate', True))
        self.hidden = {n for n in str(rospy.get_param('~hidden', '')).split(',') if n}
        self.appear_distance = float(rospy.get_param('~appear_distance', 0.9))
        self.refuse_first = int(rospy.get_param('~refuse_first', 0))
        self.refuse_status = int(rospy.get_param('~refuse_status', 2))
        self.refuse_retry_after = float(rospy.get_param('~refuse_retry_after', 0.3))
        self.refuse_message = str(rospy.get_param('~refuse_message', 'refused by the fake DRVS'))
        self.ack_delay = float(rospy.get_param('~ack_delay', 0.0))
        self.requests = 0
        self.cmd_vels = 0
        fx, fy = self.world.floor_size
        cameras = int(rospy.get_param('~cameras', 2))
        self.cameras = {'/fake_west': box(0, 0, 0.6 * fx, fy), '/fake_east': box(0.4 * fx, 0, fx, fy)}
        self.cameras = dict(list(self.cameras.items())[:cameras])
        self.jitter = {'/fake_west': 0.004, '/fake_east': -0.004}
        self.lock = threading.Lock()
        self.robot = self.world.robot.position
        self.command = (0.0, 0.0, -math.inf)
        self.contacts = 0
        self.touching = False
        self.started = time.monotonic()
        self.status = None
        self.outbox = queue.Queue()
        self.watches = {}  # (callback service, request id) -> the watch (a dict)

    def record(self, entry):
        with open(self.output, 'a') as handle:
            handle.write(json.dumps(entry) + '\n')

    # -- ground truth ------------------------------------------------------------------------
    def footprints(self):
        """name -> (role colour, footprint polygon) of every present object, robot and station."""
        t = time.monotonic() - self.started
        bodies = {'robot': (self.world.robot, self.robot), 'station': (self.world.station, None)}
        for obj in self.world.objects:
            if obj.name in self.hidden:
                continue
            position = position_on_loop(list(obj.waypoints), obj.speed, t) if obj.moving else None
            bodies[obj.name] = (obj, position)
        return {
            name: (body.colour, Polygon(box_footprint(position or body.position, body.size[:2], body.yaw)))
            for name, (body, position) in bodies.items()
        }

    def step(self, _event):
        with self.lock:
            vx, vy, stamp = self.command
            if time.monotonic() - stamp > CMD_TIMEOUT:
                vx = vy = 0.0
            speed = math.hypot(vx, vy)
            cap = self.world.robot.speed
            if speed > cap:
                vx, vy = vx * cap / speed, vy * cap / speed
            moved = (self.robot[0] + vx * STEP, self.robot[1] + vy * STEP)
            body = Polygon(box_footprint(moved, self.world.robot.size[:2], 0.0))
            others = [fp for name, (_, fp) in self.footprints().items() if name not in ('robot', 'station')]
            touching = any(body.intersects(fp) for fp in others)
            if touching:
                self.contacts += 0 if self.touching else 1
            else:
                self.robot = moved
            self.touching = touching
            for name in sorted(self.hidden):
                obj = next(o for o in self.world.objects if o.name == name)
                if math.dist(obj.position, self.robot) <= self.appear_distance:
                    self.hidden.discard(name)
                    self.record({'kind': 'appear', 'name': name, 'robot': list(self.robot)})

    def report(self, _event):
        with self.lock:
            self.record(
                {
                    'kind': 'truth',
                    'time': time.monotonic() - self.started,
                    'robot': list(self.robot),
                    'contacts': self.contacts,
                    'cmd_vels': self.cmd_vels,
                    'status': self.status,
                }
            )

    # -- DRVS --------------------------------------------------------------------------------
    def detect(self, req):
        response = self.answer(req)
        time.sleep(self.ack_delay)
        return response

    def answer(self, req):
        try:
            model = parse_algorithm(req.algorithm).params
        except AlgorithmError as error:
            return DetectObjectBoundaryResponse(accepted=False, status=INVALID, message=str(error))
        roi = box(*msg_to_box(req.region_of_interest))
        role = req.request_id.rpartition('-')[0]
        captured = rospy.Time.now()
        if self.refused():
            self.record_request('request', req, role, 0, self.refuse_status, self.refuse_retry_after)
            return DetectObjectBoundaryResponse(**self.refusal())
        with self.lock:
            seen = self.seen(model, roi)
        reached = [camera for camera, coverage in self.cameras.items() if coverage.intersects(roi)]
        self.record_request('request', req, role, len(reached), ACCEPTED, 0.0)
        callbacks = []
        for camera in reached:
            visible = self.visible(camera, seen)
            if visible:  # selectivity: a vision system that found nothing does not call back
                callbacks.append(self.callback(req, camera, captured, visible))
        random.shuffle(callbacks)
        self.send(req.callback_service, callbacks)
        return DetectObjectBoundaryResponse(accepted=True, status=ACCEPTED, vision_systems=len(reached))

    def refused(self):
        """Whether this call is one of the first ``~refuse_first``."""
        with self.lock:
            self.requests += 1
            return self.requests <= self.refuse_first

    def refusal(self):
        return {
            'accepted': self.refuse_status == ACCEPTED,
            'status': self.refuse_status,
            'message': self.refuse_message,
            'retry_after': self.refuse_retry_after,
        }

    def seen(self, model, roi):
        """Footprints of the colour ``model`` intersecting ``roi`` (the lock held)."""
        return [
            fp
            for colour, fp in self.footprints().values()
            if all(lo <= c <= hi for lo, c, hi in zip(model.lower, colour, model.upper, strict=True))
            and fp.intersects(roi)
        ]

    def visible(self, camera, seen):
        return [fp for fp in seen if self.cameras[camera].contains(ShapelyPoint(fp.centroid))]

    def callback(self, req, camera, captured, visible):
        shift = self.jitter[camera]
        objects = [
            points_to_detected_object([(x + shift, y) for x, y in list(fp.exterior.coords)[:-1]])
            for fp in visible
        ]
        return CallbackCoordinatesRequest(
            algorithm=req.algorithm,
            request_id=req.request_id,
            vision_system=camera,
            stamp=captured,
            objects=objects,
        )

    def send(self, service, callbacks):
        """Queue ``callbacks`` for ``service``, ``~latency`` from now (each twice with ``~duplicate``)."""
        if self.duplicate:
            callbacks = callbacks + callbacks
        due = time.monotonic() + self.latency
        for callback in callbacks:
            self.outbox.put((due, service, callback))

    # -- watches -----------------------------------------------------------------------------
    def watch(self, req):
        response = self.answer_watch(req)
        time.sleep(self.ack_delay)
        return response

    def answer_watch(self, req):
        try:
            model = parse_algorithm(req.algorithm).params
        except AlgorithmError as error:
            return WatchObjectBoundaryResponse(accepted=False, status=INVALID, message=str(error))
        roi = box(*msg_to_box(req.region_of_interest))
        role = req.request_id.rpartition('/')[2]
        if self.refused():
            self.record_request('watch', req, role, 0, self.refuse_status, self.refuse_retry_after)
            return WatchObjectBoundaryResponse(**self.refusal())
        key = (req.callback_service, req.request_id)
        reached = [camera for camera, coverage in self.cameras.items() if coverage.intersects(roi)]
        period = max(req.period, STEP)
        with self.lock:
            if req.duration <= 0:
                self.watches.pop(key, None)
            else:
                watch = self.watches.setdefault(key, {'reported': {}})
                watch.update(
                    req=req,
                    model=model,
                    roi=roi,
                    period=period,
                    changes_only=req.changes_only,
                    expires=time.monotonic() + req.duration,
                    next=time.monotonic(),
                    full=True,
                )
        self.record_request('watch', req, role, len(reached), ACCEPTED, 0.0)
        return WatchObjectBoundaryResponse(
            accepted=True, status=ACCEPTED, vision_systems=len(reached), period=period, duration=req.duration
        )

    def evaluate(self, _event):
        """Every watch due: one callback per camera with news (see the module docstring)."""
        now = time.monotonic()
        captured = rospy.Time.now()
        with self.lock:
            for key, watch in list(self.watches.items()):
                if now > watch['expires']:
                    del self.watches[key]
                    continue
                if now < watch['next']:
                    continue
                watch['next'] = now + watch['period']
                seen = self.seen(watch['model'], watch['roi'])
                callbacks = []
                for camera, coverage in self.cameras.items():
                    if not coverage.intersects(watch['roi']):
                        watch['reported'].pop(camera, None)  # withdrawn from this camera
                        continue
                    visible = self.visible(camera, seen)
                    shapes = sorted(
                        tuple(round(c, 4) for xy in fp.exterior.coords for c in xy) for fp in visible
                    )
                    before = watch['reported'].get(camera)
                    news = shapes != before or watch['full'] or not watch['changes_only']
                    if (visible and news) or (not visible and before):
                        callbacks.append(self.callback(watch['req'], camera, captured, visible))
                    watch['reported'][camera] = shapes if visible else None
                watch['full'] = False
                self.send(key[0], callbacks)

    def record_request(self, kind, req, role, vision_systems, status, retry_after):
        entry = {
            'kind': kind,
            'time': time.monotonic() - self.started,
            'role': role,
            'request_id': req.request_id,
            'roi': list(msg_to_box(req.region_of_interest)),
            'vision_systems': vision_systems,
            'status': name(status),
            'retry_after': retry_after,
        }
        if kind == 'watch':
            entry.update(period=req.period, duration=req.duration)
        self.record(entry)

    def deliver(self):
        """Send callbacks when they are due (one worker: answers leave in the order they were made)."""
        proxies = {}
        while not rospy.is_shutdown():
            try:
                due, service, callback = self.outbox.get(timeout=0.2)
            except queue.Empty:
                continue
            time.sleep(max(0.0, due - time.monotonic()))
            try:
                proxy = proxies.setdefault(service, rospy.ServiceProxy(service, CallbackCoordinates))
                proxy(callback)
            except (rospy.ServiceException, rospy.ROSException) as error:
                proxies.pop(service, None)
                rospy.logwarn('callback to %s failed: %s', service, error)

    def on_cmd_vel(self, msg):
        with self.lock:
            self.command = (msg.linear.x, msg.linear.y, time.monotonic())
            self.cmd_vels += 1

    def on_status(self, msg):
        with self.lock:
            self.status = robot_status_to_dict(msg)


def main():
    rospy.init_node('drvs')
    fake = FakeDrvs()
    rospy.Subscriber('/robot/cmd_vel', Twist, fake.on_cmd_vel, queue_size=1)
    rospy.Subscriber('/robot/status', RobotStatus, fake.on_status, queue_size=1)
    rospy.Timer(rospy.Duration(STEP), fake.step)
    rospy.Timer(rospy.Duration(0.2), fake.report)
    rospy.Timer(rospy.Duration(STEP), fake.evaluate)
    threading.Thread(target=fake.deliver, daemon=True).start()
    rospy.Service('~detect_object_boundary', DetectObjectBoundary, fake.detect)
    rospy.Service('~watch_object_boundary', WatchObjectBoundary, fake.watch)
    rospy.spin()


if __name__ == '__main__':
    main()
