"""The blind robot node: the ROS glue of :mod:`drvs.robot` — it asks DRVS where it is, where its
station and the obstacles are, plans with D* Lite and drives there (paper, section 4).

Topics, services, parameters and exit codes: docs/nodes/blind_robot.md; its threads:
docs/architecture.md.
"""

from __future__ import annotations

import io
import math
import threading
import time

import rospy
from geometry_msgs.msg import PoseStamped, Twist, Vector3
from nav_msgs.msg import OccupancyGrid, Path

from drvs.common.failover import ServerList
from drvs.common.guard import RESTART, SHUTDOWN
from drvs.common.health import Health, robot_health
from drvs.common.status import name as status_name
from drvs.msg import RobotStatus
from drvs.robot.assembly import assemble
from drvs.robot.controller import FINAL_STATES, Controller
from drvs.robot.mission import (
    FAIL,
    SKIP,
    USE,
    Coverage,
    callback_stamp,
    fleet_robot,
    fused_outcome,
    fused_role,
    mission_end,
    post_round,
    schedule_for,
)
from drvs.robot.params import RobotParams
from drvs.robot.perception import LOCALISATION_ROLES, PerceptionError, whole_floor
from drvs.robot.poll_schedule import ACCEPT, RETRY, Request
from drvs.robot.watch_schedule import WatchCall
from drvs.ros.conversions import box_to_msg, polygon_to_points
from drvs.ros.messages import occupancy_to_msg, path_to_msg, pose_to_msg, robot_status_to_msg
from drvs.ros.node import NodeScaffold
from drvs.ros.service_client import ServiceCallError, ServiceClient
from drvs.sim.world_file import load_world
from drvs.srv import (
    CallbackCoordinates,
    CallbackCoordinatesResponse,
    DetectObjectBoundary,
    DetectObjectBoundaryRequest,
    WatchObjectBoundary,
    WatchObjectBoundaryRequest,
)

__all__ = ['BlindRobot']

IDLE_WAIT = 0.5
"""Seconds the idle requester sleeps at most before it checks for a stop (a new round wakes it at once)."""
STOP_GRACE = 2.0
"""Wall seconds the requester may spend cancelling the watches once the node stops."""
MIN_WAIT = 0.005
"""Seconds: the shortest wait of the control loop for its next tick (ROS time, waited in wall slices)."""
COUNTERS = ('callbacks', 'callback_bytes', 'refused_callbacks')
"""The node's own counters in its status (the schedule counts the requests)."""


class BlindRobot:
    """Wires DRVS requests and callbacks, the map, the planner and the controller (:mod:`drvs.robot`)."""

    def __init__(self, params: RobotParams):
        self.params = params
        world = load_world(params.world)
        me = fleet_robot(world, params.robot, rospy.get_name())
        parts = assemble(params, world, me, rospy.get_name())
        self.floor_size, self.speed, self.robot_radius = parts.floor_size, parts.speed, parts.robot_radius
        self.watching, self.fused = parts.watching, params.fused
        self.perception, self.asked, self.regions = parts.perception, parts.asked, parts.regions
        self.map, self.yielding, self.settings = parts.map, parts.yielding, parts.settings
        self.schedule = schedule_for(params, tuple(me.colour_models), clock=rospy.get_time)
        self.controller: Controller | None = None  # from start()
        self.coverage: Coverage | None = None  # from start()
        self._lock = threading.Lock()  # guards perception, asked and coverage; orders the map's observations
        self._requests = threading.Condition()  # guards schedule; wakes the requester for a new round
        self._tracking = False  # whether the robot's own region is around it (else the whole floor)
        self._done = threading.Event()
        self._last_path: list | None = None
        self._refused: tuple[str, str] | None = None  # (role, message): a fused answer every camera refused
        self.servers = ServerList(params.services, return_after=params.server_return)  # guarded by _requests
        self._clients: dict[str, ServiceClient] = {}  # by server; only the requester thread calls them
        self.node = NodeScaffold(self.health, COUNTERS, hardware_id=rospy.get_name().rsplit('/', 1)[-1])

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> None:
        self._service_class = WatchObjectBoundary if self.watching else DetectObjectBoundary
        self.cmd_vel = rospy.Publisher('~cmd_vel', Twist, queue_size=1)
        self.path_pub = rospy.Publisher('~path', Path, queue_size=1, latch=True)
        self.map_pub = rospy.Publisher('~map', OccupancyGrid, queue_size=1, latch=True)
        self.status_pub = rospy.Publisher('~status', RobotStatus, queue_size=1, latch=True)
        self.pose_pub = rospy.Publisher('~pose', PoseStamped, queue_size=1)
        self.callback_service = rospy.resolve_name('~callback_coordinates')
        self._service = rospy.Service('~callback_coordinates', CallbackCoordinates, self._on_callback)
        self._wait_for_clock()
        started_at = rospy.get_time()
        self.controller = Controller(self.map.grid, self.settings, now=started_at, yielding=self.yielding)
        self.coverage = Coverage(self.params.fix_timeout, started_at)
        rospy.on_shutdown(self.node.stopping.set)
        self.node.spawn(self._request_loop, 'requester', RESTART)
        self.node.spawn(self._loop, 'control', SHUTDOWN)
        self.node.start()
        rospy.on_shutdown(self.node.diagnostics.stop)
        rospy.loginfo(
            'blind robot: radius %.3f m, speed %.2f m/s, %s%s %s at %.1f Hz',
            self.robot_radius,
            self.speed,
            'watching with' if self.watching else 'polling',
            ' fused' if self.fused else '',
            ', then '.join(self.servers.servers),
            self.params.rate,
        )

    def _wait_for_clock(self) -> None:
        """Under ``/use_sim_time`` ROS time is 0 until ``/clock`` first ticks: deadlines count from then."""
        if rospy.get_time() == 0.0:
            rospy.loginfo('waiting for /clock (simulated time)')
        while rospy.get_time() == 0.0 and not rospy.is_shutdown():
            self.node.wait(0.05)

    def wait(self) -> int:
        """With ``~once``: block until done, otherwise until shutdown; the exit code
        (:func:`drvs.robot.mission.mission_end`)."""
        while not rospy.is_shutdown() and not (self.params.once and self._done.is_set()):
            self._done.wait(0.2)
        self.node.stop()
        with self._requests:
            self._requests.notify_all()
        self.node.join(self.params.request_timeout + STOP_GRACE + 5.0)  # the requester cancels first
        self._halt()
        for client in self._clients.values():
            client.close()
        controller = self.controller
        state, reason = (controller.state, controller.reason) if controller is not None else (None, '')
        end = mission_end(self.params.once, self.node.failure, state, reason)
        if end.failure:
            rospy.logerr('blind robot failed: %s', end.failure)
        if end.early:
            rospy.logwarn('blind robot stopped before it reached the station')
        return end.code

    def _halt(self) -> None:
        try:
            self.cmd_vel.publish(Twist())
        except rospy.ROSException as error:  # publishing after shutdown
            rospy.logdebug('could not publish the stop command: %s', error)

    # -- callbacks from vision systems -----------------------------------------------------
    def _on_callback(self, req) -> CallbackCoordinatesResponse:
        received = rospy.get_time()
        stamp = callback_stamp(req.stamp.to_sec(), received)
        outlines = [polygon_to_points(obj.boundary) for obj in req.objects]
        velocities = [(obj.velocity.x, obj.velocity.y) if obj.track_id else None for obj in req.objects]
        levels = [(obj.height, obj.clearance) for obj in req.objects]
        serialized = io.BytesIO()
        req.serialize(serialized)
        self.node.counters.add(callbacks=1, callback_bytes=serialized.tell())
        outcome = fused_outcome(req.status) if req.fused else USE
        with self._lock:
            try:
                if outcome != USE:
                    role, _ = self.perception.requests.parse(req.request_id)
                    if outcome == FAIL:
                        self._refused = (role, req.message)
                    answer = None
                else:
                    answer = self.perception.accept(
                        req.algorithm, req.request_id, req.vision_system, stamp, outlines, velocities, levels
                    )
            except PerceptionError as error:
                refused = error  # logged once the lock is released
            else:
                refused = None
                if answer is not None and answer.role in self.map.obstacle_roles:
                    region = self.asked.region(answer.role)
                    self.map.observe(
                        answer.role,
                        answer.vision_system,
                        answer.outlines,
                        received,
                        region,
                        answer.velocities,
                        stamp,
                        answer.levels,
                    )
                    self.asked.heard(answer.role, answer.vision_system, stamp)
        if outcome == SKIP:
            self.node.log_throttled(
                'fused skipped',
                rospy.logdebug,
                'a fused callback said nothing (%s): %s',
                status_name(req.status),
                req.message,
            )
        if refused is not None:
            self.node.counters.add(refused_callbacks=1)
            self.node.log_throttled(
                'callback', rospy.logwarn, 'ignored a callback from %s: %s', req.vision_system or '?', refused
            )
        return CallbackCoordinatesResponse()

    # -- requests: the requester thread ------------------------------------------------------
    def _request_loop(self) -> None:
        """Send what the schedule says, one call at a time, until the node stops; then cancel the
        watches that may stand (best effort, for ``STOP_GRACE`` seconds at most)."""
        give_up_at = math.inf
        while True:
            with self._requests:
                if self.node.stopped:
                    self.schedule.stop()
                    give_up_at = min(give_up_at, time.monotonic() + STOP_GRACE)
                    if self.schedule.done or time.monotonic() > give_up_at:
                        return
                request = self.schedule.next_request()
                if request is None:
                    wait = self.schedule.wait_time()
                    self._requests.wait(IDLE_WAIT if wait is None else min(wait, IDLE_WAIT))
                    continue
            try:
                if self.watching:
                    self._send_watch(request)
                else:
                    self._send_request(request)
            except BaseException:
                with self._requests:  # a bug, not the network: count it failed, ask again after restart
                    if self.schedule.in_flight(request.role):
                        self.schedule.on_failure(request.role)
                raise

    def _send_request(self, request: Request) -> None:
        role = request.role
        with self._lock:
            request_id = self.perception.requests.issue(role)
            algorithm = self.perception.algorithms[role]
        sent = rospy.get_time()
        message = DetectObjectBoundaryRequest(
            algorithm=algorithm,
            region_of_interest=box_to_msg(request.region_of_interest),
            callback_service=self.callback_service,
            request_id=request_id,
            fused=fused_role(self.params, role),
        )
        server = self._server()
        try:
            response = self._clients[server].call(message)
        except ServiceCallError as error:
            with self._requests:
                outcome = self.schedule.on_failure(role)
                self._heard(server, None, str(error))
            self.node.log_throttled(
                'call failed',
                rospy.logwarn,
                'DRVS request %s failed: %s; asking again in %.2f s',
                request_id,
                error,
                outcome.delay,
            )
            return
        with self._requests:
            outcome = self.schedule.on_response(role, response.status, response.retry_after, response.message)
            self._heard(server, response.status, response.message)
        self._answered(role, f'request {request_id}', outcome, response, request.region_of_interest, sent)

    def _send_watch(self, call: WatchCall) -> None:
        role = call.role
        with self._lock:
            request_id = self.perception.requests.watch_id(role)
            algorithm = self.perception.algorithms[role]
        sent = rospy.get_time()
        rospy.logdebug(
            'watch %s (%s) in %s for %g s', request_id, call.reason, call.region_of_interest, call.duration
        )
        message = WatchObjectBoundaryRequest(
            algorithm=algorithm,
            region_of_interest=box_to_msg(call.region_of_interest),
            callback_service=self.callback_service,
            request_id=request_id,
            period=call.period,
            duration=call.duration,
            changes_only=True,
            fused=fused_role(self.params, role),
        )
        server = self._server()
        try:
            response = self._clients[server].call(message)
        except ServiceCallError as error:
            with self._requests:
                outcome = self.schedule.on_failure(role)
                self._heard(server, None, str(error))
            if call.duration:
                self.node.log_throttled(
                    'call failed',
                    rospy.logwarn,
                    'DRVS watch %s (%s) failed: %s; asking again in %.2f s',
                    request_id,
                    call.reason,
                    error,
                    outcome.delay,
                )
            else:
                rospy.loginfo('could not cancel the watch %s: %s', request_id, error)
            return
        with self._requests:
            outcome = self.schedule.on_response(
                role, response.status, response.duration, response.retry_after, response.message
            )
            self._heard(server, response.status, response.message)
        if call.duration:
            self._answered(
                role, f'watch {request_id} ({call.reason})', outcome, response, call.region_of_interest, sent
            )

    def _server(self) -> str:
        """The server to ask now, with a client for it."""
        with self._requests:
            server = self.servers.to_ask()
        if server not in self._clients:
            self._clients[server] = ServiceClient(server, self._service_class, self.params.request_timeout)
        return server

    def _heard(self, server: str, status: int | None, why: str) -> None:
        """A call to ``server`` ended (no answer: ``status`` None; the caller holds ``_requests``): on
        ``UNAVAILABLE`` or no answer the next calls go to the next server, and the watches standing
        are renewed there at once."""
        heard = self.servers.heard(server, status, why)
        if heard.line:
            (rospy.logwarn if heard.warning else rospy.loginfo)('blind robot: %s', heard.line)
        if heard.moved and self.watching:
            self.schedule.reissue()

    def _answered(self, role: str, what: str, outcome, response, region, sent: float) -> None:
        """Act on the outcome of an answered call over ``region``, sent at ``sent`` (``what``
        names it in the log)."""
        if outcome.action == ACCEPT:
            now = rospy.get_time()
            with self._lock:
                self.coverage.accepted(role, response.vision_systems, now)
                # Fused, one callback answers for every vision system DRVS asked.
                fused = fused_role(self.params, role)
                asked = min(response.vision_systems, 1) if fused else response.vision_systems
                self.asked.accepted(role, region, sent, now, asked)
        elif outcome.action == RETRY:
            self.node.log_throttled(
                ('refused', response.status),
                rospy.logwarn,
                'DRVS refused %s (%s): %s; asking again in %.2f s',
                what,
                status_name(response.status),
                response.message,
                outcome.delay,
            )
        # GIVE_UP (INVALID, UNSUPPORTED): the control loop fails the mission with the server's message.

    def _post_round(self, now: float, fix, station, velocity, lost) -> None:
        """Tell the requester which region each role needs now (or, once done, to stop asking).

        Watches reach ahead where the robot goes (it moves them seldom); polling asks anew each
        tick, around where it is.
        """
        velocity = velocity if self.watching else (0.0, 0.0)
        controller = self.controller
        regions = self.regions.regions(
            now, fix, station, controller.position, velocity, lost, controller.corridor
        )
        tracking = regions['self'].box != whole_floor(self.floor_size)
        if tracking != self._tracking:
            self._tracking = tracking
            if tracking:
                rospy.loginfo('found itself: asking for it around its position only')
            else:
                rospy.loginfo('lost itself: asking for it over the whole floor again')
        with self._requests:
            post_round(self.schedule, regions, fix, station, self.controller.state)
            self._requests.notify()

    # -- the control loop ------------------------------------------------------------------
    def _loop(self) -> None:
        period = 1.0 / self.params.rate
        next_tick = rospy.get_time()
        while not self.node.stopped:
            self._tick(rospy.get_time())
            if self.controller.state in FINAL_STATES:
                self._done.set()
            next_tick = max(next_tick + period, rospy.get_time())  # fell behind: do not catch up
            self._sleep_until(next_tick, period)

    def _sleep_until(self, when: float, longest: float) -> None:
        """Wait until ROS time ``when`` or a stop. Simulated time (``/clock``) may run slower than
        the wall: wait in wall slices and look at the clock again."""
        while not self.node.stopped:
            left = when - rospy.get_time()
            if left <= 0:
                return
            self.node.wait(min(max(left, MIN_WAIT), longest))

    def _tick(self, now: float) -> None:
        """One control step; never waits for DRVS (the requester does)."""
        controller = self.controller
        with self._requests:
            invalid = self.schedule.invalid
        with self._lock:
            invalid = invalid or self._refused
        if invalid is not None:
            role, message = invalid
            controller.fail(f'DRVS refused the {role} request: {message}')
        with self._lock:
            fix, station = (self.perception.fix(role) for role in LOCALISATION_ROLES)
            lost = [role for role in LOCALISATION_ROLES if self.perception.lost(role)]
            uncovered = self.coverage.failure(now)
            known = self.asked.known(now)
        update = self.map.update(now, fix, station, controller.position)
        if update.changes:
            controller.on_map_changed(update.changes)
        if update.publish:
            grid = self.map.grid
            self.map_pub.publish(occupancy_to_msg(grid.occupancy(), grid.spec.resolution, now))
        if uncovered is not None:
            controller.fail(uncovered)
        vx, vy = controller.step(now, fix, station, known, self.map.movers, self.map.people)
        self.cmd_vel.publish(Twist(linear=Vector3(vx, vy, 0.0)))
        self._post_round(now, fix, station, (vx, vy), lost)
        self._publish(now)

    # -- publications ----------------------------------------------------------------------
    def health(self) -> Health:
        """The robot's health now, for ``/diagnostics``."""
        now = rospy.get_time()
        controller = self.controller
        with self._lock:
            fix = self.perception.fix('self')
            covered = self.coverage.covered
        return robot_health(
            state=controller.state,
            reason=controller.reason,
            fix_age=None if fix is None else max(now - fix.stamp, 0.0),
            fix_timeout=self.params.fix_timeout,
            coverage=covered,
            server=self.servers.current,
            server_moves=self.servers.moves,
        )

    def _publish(self, now: float) -> None:
        controller = self.controller
        status = controller.status()
        with self._requests:
            status.requests, status.failed_requests = self.schedule.sent, self.schedule.failed
            status.refused = dict(self.schedule.refused)
            if self.watching:
                status.watch_calls, status.watches = self.schedule.sent, self.schedule.standing
        for key, value in self.node.counters.snapshot().items():
            setattr(status, key, value)
        with self._lock:
            status.superseded = self.perception.superseded
            status.vision_systems = dict(self.coverage.vision_systems)
            fix = self.perception.fix('self')
        heading = fix.heading if fix is not None else None
        if heading is not None:  # asked with apriltag: seen, not predicted
            status.tag_pose, status.tag_stamp = (*fix.position, heading), fix.stamp
        status.obstacles, status.stamp = self.map.obstacles, now
        self.status_pub.publish(robot_status_to_msg(status))
        if controller.position is not None:
            self.pose_pub.publish(pose_to_msg(controller.position, heading, now))
        if controller.path is not self._last_path:
            self._last_path = controller.path
            self.path_pub.publish(path_to_msg(controller.path, now))
