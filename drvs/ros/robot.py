"""The blind robot node: perception through DRVS only, D* Lite planning, re-planning (paper, section 4).

The robot has no sensor of its own. It asks DRVS where it is, where its charging
station is and where the obstacles are, with the colour models of its entry in
the world file (roles ``self``, ``station``, ``obstacle``, ``human``, and
``robot`` — the other robots — when the world has that model), and DRVS's
vision systems call it back on ``~callback_coordinates`` with outlines in
``map``. It never subscribes to anything: no images, no world_sim topic, no
ground truth. From the world file it reads only its own entry
(``World.fleet_robot``: ``~robot``, by default the node's name, or the world's
only robot): the colour models, its size and speed, and the floor size — never
where anything is.

How it asks (``~requests``):

- ``watch`` (the default): one standing request per role, drvs/WatchObjectBoundary
  on ``~watch_service``, with ``changes_only``: the vision systems call back when
  what they see of the role changed, and once with no object when it is gone.
  The robot asks for itself and for moving obstacles every control period
  (``1 / ~rate``), for static obstacles every ``~obstacle_period``, for its station
  every ``~station_period``. Each watch stands ``~watch_duration`` and is renewed
  at half the granted duration — a renewal makes the vision systems report in
  full — or sent again at once when its region must move; the robot's own also
  when it heard nothing of itself for a quarter of ``~fix_timeout`` (standing
  still, :func:`watch_schedule`); when
  the mission ends (arrived, failed, shutdown) every watch is cancelled, best
  effort (:mod:`drvs.robot.watch_schedule`). A vision system's outlines stand until it
  replaces them, or for the watch's duration at most.
- ``poll``: the paper's one-shot requests, drvs/DetectObjectBoundary on
  ``~drvs_service``, a round of every role each control tick (the station every
  ``~station_period`` once found; :mod:`drvs.robot.poll_schedule`). Obstacle outlines
  are forgotten ``~obstacle_ttl`` after their vision system last reported them.

Regions of interest (:class:`drvs.robot.perception.RegionPolicy`): itself and its
station over the whole floor until found; then itself in a box around its
predicted position grown by its radius plus ``~self_margin``, reaching further
ahead while it moves (the whole floor again when it loses itself), and the
station in its box plus ``~self_margin``; obstacles in the box spanned by itself
and the station plus ``~roi_margin`` (the paper's section 4.3). A watch moves
only when the robot nears the edge of its region, so a moving robot sends few
calls. Callbacks may come from several vision systems, in any order, late or
twice (:mod:`drvs.robot.perception`). Obstacle outlines go into an occupancy grid
inflated by ``~robot_radius`` (:mod:`drvs.robot.occupancy`); changed cells feed D* Lite,
and the controller (:mod:`drvs.robot.controller`) drives along the plan, predicting its
position between fixes from the velocities it commanded. Once arrived or failed
it stops moving and stops asking DRVS (with ``~once`` it exits).

Requests never hold up the control loop. The loop posts each tick's regions to
the schedule and a requester thread sends what the schedule says, one call at a
time, each call limited to ``~request_timeout``: a slow, hung or absent DRVS
delays the answers, never a control tick, and the loop keeps publishing
``~cmd_vel`` from the controller's prediction. How DRVS answers (``status`` of
the response, :mod:`drvs.common.status`):

- ``ACCEPTED``: forwarded to (or the watch served by) ``vision_systems`` vision
  systems (maybe none).
- ``BUSY``, ``RATE_LIMITED``, ``UNAVAILABLE``, and a call that fails (server down,
  timed out): that role is asked again after :func:`drvs.common.retry.retry_delay`
  seconds, never before the response's ``retry_after``, backing off up to
  ``~retry_cap`` while it keeps failing, with jitter. This never ends the mission;
  the robot's own deadlines do (no fix for ``~fix_timeout``). A status code the
  robot does not know is retried the same way, with a warning logged once.
- ``INVALID``, ``UNSUPPORTED``: the request is wrong and asking again cannot help;
  the robot fails with "DRVS refused the <role> request: <the server's message>".

Calls leave at most ``~max_request_rate`` per second, below the server's default
per-caller limit (50/s, bursts of 100); polling at the default ``~rate`` of 5 the
rounds alone come to at most 20/s, and retries only ever wait longer.

Time: every deadline and the control loop's pace are ROS time, so under
``/use_sim_time`` (a world with a ``real_time_factor`` below 1) the robot ticks
``~rate`` times per simulated second and waits for ``/clock`` before it starts.

Background loops (control, requester) are guarded (:class:`drvs.common.guard.LoopGuard`):
an unexpected exception in the control loop fails the node (exit code 1); the
requester is restarted, and fails the node if it keeps failing.

Parameters: the fields of :class:`RobotParams`, each declared with its default,
meaning and range; README.md's blind_robot table is generated from them.

Services and topics (``~`` = ``/robot`` when run as ``__name:=robot``):

``~callback_coordinates`` (drvs/CallbackCoordinates, served)
``~cmd_vel`` (geometry_msgs/Twist): ``linear.x``, ``linear.y`` velocity in ``map``.
``~path`` (nav_msgs/Path, latched): the current plan.
``~map`` (nav_msgs/OccupancyGrid, latched): 0 free, 99 inflated margin, 100 obstacle.
``~pose`` (geometry_msgs/PoseStamped, every tick once it has a fix): where the robot
believes it is (the newest fix carried forward by its own commands), in ``map``; the
orientation is the heading the cameras saw with an ``apriltag`` self model, else +x.
``~status`` (drvs/RobotStatus, latched, every tick): state (a constant and its name:
localising, moving, blocked, arriving, arrived, failed), reason, replans,
distance_to_goal, position (and the heading the cameras saw, with an ``apriltag``
self model), goal, path_length, requests (calls sent to the server, watch calls
included), watch_calls, watches (standing), failed_requests (no response), refused
(refusals per status name, e.g. BUSY: 3), callbacks, callback_bytes (their serialized
size), refused_callbacks, superseded, obstacles, vision_systems (per role, how many
its last accepted call reached), header.stamp (ROS time of the tick); when the
robot's ``self`` model is an ``apriltag``, also tag_pose (x, y, heading of its newest
fix: the heading seen by the cameras, not predicted) and tag_stamp (when those
frames were taken).
``/diagnostics`` (diagnostic_msgs/DiagnosticArray, 1 Hz): status ``drvs: <node name>``,
hardware_id the robot (the node's base name; :func:`drvs.common.health.robot_health`). ERROR
once failed (the reason); WARN while blocked, without a fix yet, with its newest fix older
than half ``~fix_timeout``, or when its last ``self`` request reached no vision system;
OK otherwise, and once arrived. Values: state, reason, fix age (from the frames' stamp),
``~fix_timeout``, covered.
"""

from __future__ import annotations

import collections
import io
import math
import threading
import time
from dataclasses import dataclass

import rospy
from geometry_msgs.msg import Pose, PoseStamped, Twist, Vector3
from nav_msgs.msg import OccupancyGrid, Path
from shapely.geometry import Point, Polygon
from shapely.ops import unary_union

from drvs.common.guard import RESTART, SHUTDOWN, LoopGuard
from drvs.common.health import Health, robot_health
from drvs.common.settings import NON_NEGATIVE, POSITIVE, REQUIRED, Settings, one_of, param
from drvs.common.status import name as status_name
from drvs.msg import RobotStatus
from drvs.robot.controller import ARRIVED, ARRIVING, FAILED, FINAL_STATES, Controller, ControllerSettings
from drvs.robot.occupancy import CostGrid, GridSpec, MapPublishing, ObstacleMemory
from drvs.robot.perception import (
    FLEET_ROLE,
    LOCALISATION_ROLES,
    STATIC_ROLES,
    Perception,
    PerceptionError,
    RegionPolicy,
    cut_bodies,
    exclude_bodies,
    merge_outlines,
    whole_floor,
)
from drvs.robot.poll_schedule import ACCEPT, RETRY, Request, RequestSchedule
from drvs.robot.watch_schedule import WatchCall, WatchSchedule
from drvs.ros.conversions import box_to_msg, polygon_to_points
from drvs.ros.diagnostics import DiagnosticsPublisher
from drvs.ros.messages import robot_status_to_msg
from drvs.ros.service_client import ServiceCallError, ServiceClient
from drvs.sim.world import FleetRobot, World, box_footprint
from drvs.sim.world_file import load_world
from drvs.srv import (
    CallbackCoordinates,
    CallbackCoordinatesResponse,
    DetectObjectBoundary,
    DetectObjectBoundaryRequest,
    WatchObjectBoundary,
    WatchObjectBoundaryRequest,
)

WATCH, POLL = 'watch', 'poll'
"""The values of ``~requests``: standing requests, or the paper's one-shot requests every tick."""
MAX_STAMP_AGE = 2.0
"""Seconds; a callback stamped older than this (or in the future) is timed by its arrival instead."""
IDLE_WAIT = 0.5
"""Seconds the idle requester sleeps at most before it checks for a stop (a new round wakes it at once)."""
STOP_GRACE = 2.0
"""Wall seconds the requester may spend cancelling the watches once the node stops."""
MIN_WAIT = 0.005
"""Seconds: the shortest wait of the control loop for its next tick (ROS time, waited in wall slices)."""
BODY_MARGIN = 0.08
"""Metres around the robot's body (placed by its tag) within which moving regions are the robot itself."""
OWN_TRAIL = 4.0
"""Seconds of the robot's own past positions whose moving regions are ghosts of itself, not obstacles."""


MAX_CELLS = 40_000
"""Cells of the default grid at most: D* Lite's first search over a 24 x 14 m warehouse at 0.05 m
(134,400 cells) holds the control loop, and with it the callbacks, for seconds on a loaded machine."""


def grid_resolution(floor_size) -> float:
    """The default cell size: 0.05 m, or the next centimetre that keeps the grid within MAX_CELLS.

    >>> grid_resolution((7.0, 5.5)), grid_resolution((24.0, 14.0))
    (0.05, 0.1)
    """
    width, height = floor_size
    return max(0.05, math.ceil(math.sqrt(width * height / MAX_CELLS) * 100) / 100)


@dataclass(frozen=True)
class RobotParams(Settings):
    world: str = param(REQUIRED, 'the world file: colour models, floor size, robot size and speed')
    robot: str | None = param(
        None,
        "the world's robot this node drives (its body, station and colour models)",
        default_text="the node's name if the world has a robot of that name, else the world's only robot",
    )
    requests: str = param(
        WATCH,
        'how it asks DRVS: `watch` (standing requests, renewed) or `poll` (the paper: '
        'one-shot requests every control tick)',
        check=one_of(WATCH, POLL),
    )
    rate: float = param(
        5.0, 'control ticks (and, polling, rounds of DRVS requests) per second', unit='Hz', check=POSITIVE
    )
    resolution: float | None = param(
        None,
        'occupancy grid cell size',
        unit='m',
        check=POSITIVE,
        default_text=f'0.05 m, coarser on a floor that would need more than {MAX_CELLS:,} cells',
    )
    robot_radius: float | None = param(
        None,
        'inflation of obstacles (the default contains the body whatever its heading)',
        unit='m',
        check=NON_NEGATIVE,
        default_text="half the diagonal of the robot's footprint",
    )
    roi_margin: float = param(
        0.75, 'added around the robot-station box for obstacle requests', unit='m', check=NON_NEGATIVE
    )
    obstacle_ttl: float = param(
        1.5,
        "polling, a vision system's obstacle outlines are forgotten this long after it last reported "
        'them; with watches, this long after it reported them gone (and after `~watch_duration` at most)',
        unit='s',
        check=POSITIVE,
    )
    goal_tolerance: float = param(
        0.1, "distance from the station's centre at which the robot stops", unit='m', check=POSITIVE
    )
    fix_timeout: float = param(
        5.0,
        'no new fix of the robot (at start, of the station) or no camera covering it for this long: '
        'the robot stops and fails',
        unit='s',
        check=POSITIVE,
    )
    unreachable_timeout: float = param(
        5.0, 'the station may stay unreachable this long before the robot fails', unit='s', check=POSITIVE
    )
    speed: float | None = param(
        None, 'top speed', unit='m/s', check=POSITIVE, default_text="the world's robot speed"
    )
    lookahead: float = param(
        0.2, 'distance along the plan to the point the robot steers to', unit='m', check=POSITIVE
    )
    replan_distance: float = param(
        0.3, 'map changes this close to the remaining plan trigger a repair', unit='m', check=NON_NEGATIVE
    )
    route_tolerance: float = param(
        0.15,
        'a repaired plan straying further from the old route counts as a re-plan',
        unit='m',
        check=POSITIVE,
    )
    map_period: float = param(
        1.0,
        'at most one `~map` per period while the map changes (it is the whole grid, a byte a cell); '
        '0: one per change. Unchanged, it is published every 5 s',
        unit='s',
        check=NON_NEGATIVE,
    )
    station_period: float = param(
        2.0,
        'time between station requests once the station was found; with watches, its evaluation period',
        unit='s',
        check=POSITIVE,
    )
    obstacle_period: float = param(
        0.5,
        'with watches, the evaluation period asked for static obstacles (the robot itself and moving '
        'obstacles: the control period)',
        unit='s',
        check=POSITIVE,
    )
    watch_duration: float = param(
        20.0,
        "a watch stands this long unless renewed (at half the granted time; the robot's own also "
        'when it heard nothing of itself for a quarter of `~fix_timeout`)',
        unit='s',
        check=POSITIVE,
    )
    self_margin: float = param(
        1.0,
        'once found, the robot is asked for around its predicted position, its radius plus this; '
        'its station in its box plus this',
        unit='m',
        check=POSITIVE,
    )
    request_timeout: float = param(
        1.0, 'limit on one DRVS call; a call that takes longer counts as failed', unit='s', check=POSITIVE
    )
    max_request_rate: float = param(
        40.0, 'DRVS calls per second, retries included', unit='/s', check=POSITIVE
    )
    retry_cap: float = param(
        1.0,
        'longest wait (before jitter) between retries of a role; keep it well below `~fix_timeout`',
        unit='s',
        check=POSITIVE,
    )
    drvs_service: str = param(
        '/drvs/detect_object_boundary', "the DRVS server's DetectObjectBoundary (with `poll`)"
    )
    watch_service: str = param(
        '/drvs/watch_object_boundary', "the DRVS server's WatchObjectBoundary (with `watch`)"
    )
    once: bool = param(False, 'exit when done: 0 at the station, 1 otherwise')


def request_schedule(params: RobotParams, **kwargs) -> RequestSchedule:
    """The robot's request schedule for ``params``; ``kwargs`` (clock, rng) are for tests."""
    return RequestSchedule(
        periods={'station': params.station_period},
        max_rate=params.max_request_rate,
        cap=params.retry_cap,
        **kwargs,
    )


def watch_schedule(params: RobotParams, roles, **kwargs) -> WatchSchedule:
    """The robot's watch schedule for ``params`` and ``roles``; ``kwargs`` (clock, rng) are for tests.

    The robot itself and moving obstacles are evaluated every control period, static obstacles
    every ``~obstacle_period``, the station every ``~station_period``; every watch stands
    ``~watch_duration``. The robot's own watch is renewed as well when it heard nothing of itself
    for a quarter of ``~fix_timeout``: with ``changes_only`` a robot standing still gets no
    callback, and a renewal makes the vision systems report in full, so its fix stays younger
    than half ``~fix_timeout`` (beyond which it would look for itself over the whole floor).
    The robot-station box of the obstacle roles shrinks a little at a time as the robot drives:
    its watches move only once it fell under a quarter of their area.
    """
    periods = dict.fromkeys(roles, 1.0 / params.rate)
    periods.update(dict.fromkeys(set(STATIC_ROLES) & set(roles), params.obstacle_period))
    periods['station'] = params.station_period
    return WatchSchedule(
        periods,
        params.watch_duration,
        keep_alive={'self': params.fix_timeout / 4},
        shrink={role: 0.25 for role in roles if role not in LOCALISATION_ROLES},
        max_rate=params.max_request_rate,
        cap=params.retry_cap,
        **kwargs,
    )


def fleet_robot(world: World, name: str | None, node_name: str) -> FleetRobot:
    """The world's robot named ``name``; by default the one named as the node (its base name),
    else the world's only robot.

    :raises drvs.sim.world.WorldError: no robot of that name (the message lists the known ones).
    """
    if name is not None:
        return world.fleet_robot(name)
    if len(world.robots) == 1:
        return world.robots[0]
    return world.fleet_robot(node_name.rsplit('/', 1)[-1])


class BlindRobot:
    """Wires DRVS requests and callbacks, the map, the planner and the controller; see the module doc."""

    def __init__(self, params: RobotParams):
        self.params = params
        world = load_world(params.world)
        me = fleet_robot(world, params.robot, rospy.get_name())
        # Only what a robot may know of the world file: its colour models, the floor, its size and speed.
        self.floor_size = world.floor_size
        self.speed = params.speed or me.body.speed
        size = me.body.size
        self.robot_size = tuple(size[:2])
        self.robot_radius = (
            params.robot_radius if params.robot_radius is not None else math.hypot(size[0], size[1]) / 2
        )
        self.watching = params.requests == WATCH
        self.perception = Perception(me.colour_models, rospy.get_name(), watch_keep=params.watch_duration)
        self.regions = RegionPolicy(
            self.floor_size,
            self.perception.obstacle_roles,
            self.robot_radius,
            params.self_margin,
            params.roi_margin,
            params.fix_timeout,
        )
        self._trail: collections.deque = collections.deque()  # (time, position) of recent fixes
        self._trail_shape = Polygon()  # their union, grown by the robot's radius
        # A watch's vision systems re-report in full at each renewal: outlines of a dead one expire.
        self.memory = ObstacleMemory(params.watch_duration if self.watching else params.obstacle_ttl)
        resolution = params.resolution or grid_resolution(self.floor_size)
        self.grid = CostGrid(GridSpec(self.floor_size, resolution), self.robot_radius)
        self.settings = ControllerSettings(
            speed=self.speed,
            goal_tolerance=params.goal_tolerance,
            fix_timeout=params.fix_timeout,
            unreachable_timeout=params.unreachable_timeout,
            lookahead=params.lookahead,
            replan_distance=params.replan_distance,
            route_tolerance=params.route_tolerance,
        )
        if self.watching:
            self.schedule = watch_schedule(params, tuple(me.colour_models), clock=rospy.get_time)
        else:
            self.schedule = request_schedule(params)
        self.controller: Controller | None = None
        self._lock = threading.Lock()  # guards perception, memory and the coverage and callback fields below
        self._requests = threading.Condition()  # guards schedule; wakes the requester for a new round
        self._counts = {'callbacks': 0, 'callback_bytes': 0, 'refused_callbacks': 0}
        self._tracking = False  # whether the robot's own region is around it (else the whole floor)
        self._vision_systems: dict[str, int] = {}  # role -> vision systems its last request reached
        self._no_coverage_since: float | None = None
        self._covered = False  # whether a self request ever reached a vision system
        self._started_at = 0.0
        self._obstacles = 0
        self._done = threading.Event()
        self._stop = threading.Event()
        self._last_path: list | None = None
        self._map_publishing = MapPublishing(params.map_period)
        self._client: ServiceClient | None = None
        self.guard = LoopGuard(on_fatal=lambda reason: rospy.signal_shutdown(reason), stop=self._stop)
        self.diagnostics = DiagnosticsPublisher(
            f'drvs: {rospy.get_name()}', rospy.get_name().rsplit('/', 1)[-1], self.health, guard=self.guard
        )

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> None:
        if self.watching:
            service = (self.params.watch_service, WatchObjectBoundary)
        else:
            service = (self.params.drvs_service, DetectObjectBoundary)
        self._client = ServiceClient(*service, self.params.request_timeout)
        self.cmd_vel = rospy.Publisher('~cmd_vel', Twist, queue_size=1)
        self.path_pub = rospy.Publisher('~path', Path, queue_size=1, latch=True)
        self.map_pub = rospy.Publisher('~map', OccupancyGrid, queue_size=1, latch=True)
        self.status_pub = rospy.Publisher('~status', RobotStatus, queue_size=1, latch=True)
        self.pose_pub = rospy.Publisher('~pose', PoseStamped, queue_size=1)
        self.callback_service = rospy.resolve_name('~callback_coordinates')
        self._service = rospy.Service('~callback_coordinates', CallbackCoordinates, self._on_callback)
        self._wait_for_clock()
        self._started_at = rospy.get_time()
        self.controller = Controller(self.grid, self.settings, now=self._started_at)
        rospy.on_shutdown(self._stop.set)
        self.guard.spawn(self._request_loop, 'requester', RESTART)
        self.guard.spawn(self._loop, 'control', SHUTDOWN)
        self.diagnostics.start()
        rospy.on_shutdown(self.diagnostics.stop)
        rospy.loginfo(
            'blind robot: radius %.3f m, speed %.2f m/s, %s %s at %.1f Hz',
            self.robot_radius,
            self.speed,
            'watching with' if self.watching else 'polling',
            service[0],
            self.params.rate,
        )

    def _wait_for_clock(self) -> None:
        """Under ``/use_sim_time`` ROS time is 0 until ``/clock`` first ticks: deadlines count from then."""
        if rospy.get_time() == 0.0:
            rospy.loginfo('waiting for /clock (simulated time)')
        while rospy.get_time() == 0.0 and not rospy.is_shutdown():
            self._stop.wait(0.05)

    def wait(self) -> int:
        """With ``~once``: block until done; 0 at the station, 1 on failure. Otherwise until shutdown.

        A background loop that crashed is a failure too (1, with or without ``~once``); with
        ``~once``, so is a shutdown (Ctrl-C) before the robot reached its station.
        """
        while not rospy.is_shutdown() and not (self.params.once and self._done.is_set()):
            self._done.wait(0.2)
        self._stop.set()
        self.diagnostics.stop()
        with self._requests:
            self._requests.notify_all()
        for thread in self.guard.threads:  # the requester cancels the watches first (STOP_GRACE)
            thread.join(self.params.request_timeout + STOP_GRACE + 5.0)
        self._halt()
        if self._client is not None:
            self._client.close()
        if self.guard.failure is not None:
            rospy.logerr('blind robot failed: %s', self.guard.failure)
            return 1
        if self.controller is not None and self.controller.state == FAILED:
            rospy.logerr('blind robot failed: %s', self.controller.reason)
            return 1 if self.params.once else 0
        if self.params.once and (self.controller is None or self.controller.state != ARRIVED):
            rospy.logwarn('blind robot stopped before it reached the station')
            return 1
        return 0

    def _halt(self) -> None:
        try:
            self.cmd_vel.publish(Twist())
        except rospy.ROSException as error:  # publishing after shutdown
            rospy.logdebug('could not publish the stop command: %s', error)

    # -- callbacks from vision systems -----------------------------------------------------
    def _on_callback(self, req) -> CallbackCoordinatesResponse:
        received = rospy.get_time()
        stamp = req.stamp.to_sec()
        if not (0 < received - stamp < MAX_STAMP_AGE or abs(received - stamp) < 0.05):
            stamp = received
        outlines = [polygon_to_points(obj.boundary) for obj in req.objects]
        serialized = io.BytesIO()
        req.serialize(serialized)
        with self._lock:
            self._counts['callbacks'] += 1
            self._counts['callback_bytes'] += serialized.tell()
            try:
                answer = self.perception.accept(
                    req.algorithm, req.request_id, req.vision_system, stamp, outlines
                )
            except PerceptionError as error:
                self._counts['refused_callbacks'] += 1
                rospy.logwarn('ignored a callback from %s: %s', req.vision_system or '?', error)
                return CallbackCoordinatesResponse()
            if answer is not None and answer.role in self.perception.obstacle_roles:
                # A watch's "all gone" keeps the outlines ~obstacle_ttl more, as polling would.
                source = (answer.role, answer.vision_system)
                self.memory.observe(source, answer.outlines, received, linger=self.params.obstacle_ttl)
        return CallbackCoordinatesResponse()

    # -- requests: the requester thread ------------------------------------------------------
    def _request_loop(self) -> None:
        """Send what the schedule says, one call at a time, until the node stops; then cancel the
        watches that may stand (best effort, for ``STOP_GRACE`` seconds at most)."""
        give_up_at = math.inf
        while True:
            with self._requests:
                if self._stop.is_set():
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
        message = DetectObjectBoundaryRequest(
            algorithm=algorithm,
            region_of_interest=box_to_msg(request.region_of_interest),
            callback_service=self.callback_service,
            request_id=request_id,
        )
        try:
            response = self._client.call(message)
        except ServiceCallError as error:
            with self._requests:
                outcome = self.schedule.on_failure(role)
            rospy.logwarn_throttle(
                5.0, 'DRVS request %s failed: %s; asking again in %.2f s', request_id, error, outcome.delay
            )
            return
        with self._requests:
            outcome = self.schedule.on_response(role, response.status, response.retry_after, response.message)
        self._answered(role, f'request {request_id}', outcome, response)

    def _send_watch(self, call: WatchCall) -> None:
        role = call.role
        with self._lock:
            request_id = self.perception.requests.watch_id(role)
            algorithm = self.perception.algorithms[role]
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
        )
        try:
            response = self._client.call(message)
        except ServiceCallError as error:
            with self._requests:
                outcome = self.schedule.on_failure(role)
            if call.duration:
                rospy.logwarn_throttle(
                    5.0,
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
                role,
                response.status,
                response.duration,
                response.retry_after,
                response.message,
            )
        if call.duration:
            self._answered(role, f'watch {request_id} ({call.reason})', outcome, response)

    def _answered(self, role: str, what: str, outcome, response) -> None:
        """Act on the outcome of an answered call (``what`` names it in the log)."""
        if outcome.action == ACCEPT:
            self._on_accepted(role, response.vision_systems)
        elif outcome.action == RETRY:
            rospy.logwarn_throttle(
                5.0,
                'DRVS refused %s (%s): %s; asking again in %.2f s',
                what,
                status_name(response.status),
                response.message,
                outcome.delay,
            )
        # GIVE_UP (INVALID, UNSUPPORTED): the control loop fails the mission with the server's message.

    def _on_accepted(self, role: str, vision_systems: int) -> None:
        now = rospy.get_time()
        with self._lock:
            self._vision_systems[role] = vision_systems
            if role != 'self':
                return
            if vision_systems == 0:
                # Never covered since start: count from the start, as the fix timeout does.
                since = self._started_at if not self._covered else now
                self._no_coverage_since = self._no_coverage_since or since
            else:
                self._covered = True
                self._no_coverage_since = None

    def _post_round(self, now: float, fix, station, velocity, lost) -> None:
        """Tell the requester which region each role needs now (or, once done, to stop asking).

        Watches reach ahead where the robot goes (it moves them seldom); polling asks anew each
        tick, around where it is.
        """
        velocity = velocity if self.watching else (0.0, 0.0)
        regions = self.regions.regions(now, fix, station, self.controller.position, velocity, lost)
        tracking = regions['self'].box != whole_floor(self.floor_size)
        if tracking != self._tracking:
            self._tracking = tracking
            if tracking:
                rospy.loginfo('found itself: asking for it around its position only')
            else:
                rospy.loginfo('lost itself: asking for it over the whole floor again')
        with self._requests:
            if self.controller.state in FINAL_STATES:
                self.schedule.stop()
            elif self.watching:
                heard = {'self': fix.stamp} if fix is not None else None
                # Stopped at the station: a full report confirms the arrival sooner than a keep-alive.
                fresh = ('self',) if self.controller.state == ARRIVING else ()
                self.schedule.post(regions, heard, fresh)
            else:
                found = [role for role, f in zip(LOCALISATION_ROLES, (fix, station), strict=True) if f]
                self.schedule.post({role: region.box for role, region in regions.items()}, found)
            self._requests.notify()

    # -- the control loop ------------------------------------------------------------------
    def _loop(self) -> None:
        period = 1.0 / self.params.rate
        next_tick = rospy.get_time()
        while not self._stop.is_set():
            self._tick(rospy.get_time())
            if self.controller.state in FINAL_STATES:
                self._done.set()
            next_tick = max(next_tick + period, rospy.get_time())  # fell behind: do not catch up
            self._sleep_until(next_tick, period)

    def _sleep_until(self, when: float, longest: float) -> None:
        """Wait until ROS time ``when`` or a stop. Simulated time (``/clock``) may run slower than
        the wall: wait in wall slices and look at the clock again."""
        while not self._stop.is_set():
            left = when - rospy.get_time()
            if left <= 0:
                return
            self._stop.wait(min(max(left, MIN_WAIT), longest))

    def _tick(self, now: float) -> None:
        """One control step; never waits for DRVS (the requester does)."""
        controller = self.controller
        with self._requests:
            invalid = self.schedule.invalid
        if invalid is not None:
            role, message = invalid
            controller.fail(f'DRVS refused the {role} request: {message}')
        with self._lock:
            fix, station = (self.perception.fix(role) for role in LOCALISATION_ROLES)
            lost = [role for role in LOCALISATION_ROLES if self.perception.lost(role)]
            sources = self.memory.current(now)
            no_coverage_since = self._no_coverage_since
        self._update_map(now, sources, fix, station)
        if no_coverage_since is not None and now - no_coverage_since > self.params.fix_timeout:
            controller.fail(
                f'no vision system covers the robot: DRVS forwarded its self request to none '
                f'for {self.params.fix_timeout:.1f} s'
            )
        vx, vy = controller.step(now, fix, station)
        self.cmd_vel.publish(Twist(linear=Vector3(vx, vy, 0.0)))
        self._post_round(now, fix, station, (vx, vy), lost)
        self._publish(now)

    def _own_trail(self, now: float, fix) -> Polygon:
        """Where the robot stood in the last ``OWN_TRAIL`` seconds: a background model that took the
        robot in while it stood still reports the floor it uncovers as "moving" for a while (a
        ghost of itself), which must not block it."""
        trail = self._trail
        changed = False
        if fix is not None and (not trail or trail[-1][1] != fix.position):
            trail.append((now, fix.position))
            changed = True
        while trail and now - trail[0][0] > OWN_TRAIL:
            trail.popleft()
            changed = True
        if changed:  # new fixes come a few times a second; the control loop ticks faster
            radius = self.robot_radius + BODY_MARGIN
            self._trail_shape = unary_union([Point(position).buffer(radius) for _, position in trail])
        return self._trail_shape

    def _update_map(self, now: float, sources, fix, station) -> None:
        bodies = [f.outline for f in (fix, station) if f is not None]
        if fix is not None and fix.heading is not None:
            # A tag is smaller than the robot: its own body, where the tag says, is not an obstacle
            # (motion finds the robot moving), with a margin for the time between the frames.
            body = Polygon(box_footprint(fix.position, self.robot_size, fix.heading)).buffer(BODY_MARGIN)
            bodies.append(body)
        bodies.append(self._own_trail(now, fix))
        objects = []
        for role in self.perception.obstacle_roles:
            merged = merge_outlines(o for (r, _), outlines in sources.items() if r == role for o in outlines)
            # The fleet's model finds this robot too, as one blob with another robot it touches:
            # its own body is cut out of those blobs, not the blob dropped.
            objects.extend(
                cut_bodies(merged, bodies) if role == FLEET_ROLE else exclude_bodies(merged, bodies)
            )
        self._obstacles = len(objects)
        changes = self.grid.apply(objects)
        if changes:
            self.controller.on_map_changed(changes)
        if self._map_publishing.due(now, bool(changes)):
            self._publish_map()

    # -- publications ----------------------------------------------------------------------
    def health(self) -> Health:
        """The robot's health now, for ``/diagnostics``."""
        now = rospy.get_time()
        controller = self.controller
        with self._lock:
            fix = self.perception.fix('self')
            covered = self._vision_systems.get('self', 0) > 0
        return robot_health(
            state=controller.state,
            reason=controller.reason,
            fix_age=None if fix is None else max(now - fix.stamp, 0.0),
            fix_timeout=self.params.fix_timeout,
            coverage=covered,
        )

    def _publish(self, now: float) -> None:
        controller = self.controller
        status = controller.status()
        with self._requests:
            status.update(
                requests=self.schedule.sent,
                failed_requests=self.schedule.failed,
                refused=dict(self.schedule.refused),
            )
            if self.watching:
                status.update(watch_calls=self.schedule.sent, watches=self.schedule.standing)
        with self._lock:
            status.update(
                self._counts,
                superseded=self.perception.superseded,
                vision_systems=dict(self._vision_systems),
            )
            fix = self.perception.fix('self')
            if fix is not None and fix.heading is not None:  # asked with apriltag: seen, not predicted
                status.update(tag_pose=[fix.position[0], fix.position[1], fix.heading], tag_stamp=fix.stamp)
        status.update(obstacles=self._obstacles, stamp=now)
        self.status_pub.publish(robot_status_to_msg(status))
        if controller.position is not None:
            heading = fix.heading if fix is not None and fix.heading is not None else None
            self.pose_pub.publish(self._pose_msg(controller.position, heading))
        if controller.path is not self._last_path:
            self._last_path = controller.path
            self.path_pub.publish(self._path_msg(controller.path))

    @staticmethod
    def _pose_msg(position, heading: float | None) -> PoseStamped:
        """Where the robot believes it is, in ``map``; facing +x when no camera saw its heading."""
        msg = PoseStamped()
        msg.header.frame_id = 'map'
        msg.header.stamp = rospy.Time.now()
        msg.pose.position.x, msg.pose.position.y = position
        yaw = heading or 0.0
        msg.pose.orientation.z, msg.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
        return msg

    def _path_msg(self, points) -> Path:
        msg = Path()
        msg.header.frame_id = 'map'
        msg.header.stamp = rospy.Time.now()
        for x, y in points:
            pose = PoseStamped()
            pose.header = msg.header
            pose.pose.position.x, pose.pose.position.y = x, y
            pose.pose.orientation.w = 1.0
            msg.poses.append(pose)
        return msg

    def _publish_map(self) -> None:
        spec = self.grid.spec
        msg = OccupancyGrid()
        msg.header.frame_id = 'map'
        msg.header.stamp = rospy.Time.now()
        msg.info.resolution = spec.resolution
        msg.info.width, msg.info.height = spec.cols, spec.rows
        msg.info.origin = Pose()
        msg.info.origin.orientation.w = 1.0
        msg.data = self.grid.occupancy().ravel().tolist()
        self.map_pub.publish(msg)
