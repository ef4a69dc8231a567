"""The scenario recorder node: watches a run and leaves its picture, summary and figures.

It is the scenario's observer, not part of DRVS. :class:`RunRecorder` turns a run's messages,
fed live by :class:`RecorderNode` or from a bag (:mod:`drvs.tools.bag_report`), into a
:class:`drvs.sim.report.RunRecord`: the same messages give the same summary. Topics, files and
parameters: docs/nodes/scenario_recorder.md.
"""

from __future__ import annotations

import collections
import functools
import json
import logging
import math
import os
import threading
import time
import warnings
import xmlrpc.client
from collections.abc import Callable, Iterable
from pathlib import Path

import genpy
import numpy as np
import rospy
from nav_msgs.msg import OccupancyGrid
from nav_msgs.msg import Path as PathMsg
from std_msgs.msg import Header, String

from drvs.msg import (
    BodyPoses,
    NodeCpu,
    RecorderSample,
    Registry,
    RobotStatus,
    ServerStats,
    TrackedObjects,
    VisionSystemStats,
)
from drvs.ros.messages import body_poses_from_msg, registry_to_dict, robot_status_to_dict, stats_to_dict
from drvs.ros.node import NodeScaffold
from drvs.sim.report import CAMERA_FIGURES, ROBOT_FIGURES, SERVER_FIGURES, RunRecord, write_report
from drvs.sim.tracking import TrackPeriod, TrackPoint, centroid
from drvs.sim.world import World
from drvs.sim.world_file import load_world

LOG = logging.getLogger('rosout.' + __name__)
CLOCK_TICKS = os.sysconf('SC_CLK_TCK')
TRACE_STEP = 0.01
"""Metres between two recorded trajectory points."""
TAG_POSE_STEP = 0.4
"""Metres between two tag poses kept for the picture (one arrow every this far)."""
DONE = ('arrived', 'failed')
"""Robot states after which its status no longer counts towards its elapsed time."""
QUEUE = 200
"""Messages of one topic the live recorder may hold while it is busy (world_sim's truth comes every step)."""
TRUTH_STEP = 0.02
"""Seconds between two ground-truth poses kept for the tracking metrics (interpolated between)."""
STATUS_LINE_PERIOD = 0.5
"""Seconds between two updates of ``status.line`` (and, at most, between two CPU samples)."""


def process_cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of a live process (and its reaped children), or None."""
    try:
        with open(f'/proc/{pid}/stat', 'rb') as handle:
            fields = handle.read().rsplit(b')', 1)[1].split()
    except OSError:
        return None
    return sum(int(v) for v in fields[11:15]) / CLOCK_TICKS


def cpu_summary(entries: Iterable[NodeCpu]) -> dict[str, dict]:
    """CPU seconds and mean percent of one core per node, over the time it was sampled."""
    result = {}
    for entry in sorted(entries, key=lambda e: e.node):
        span = (entry.last_stamp - entry.first_stamp).to_sec()
        used = entry.last_seconds - entry.first_seconds
        result[entry.node] = {
            'seconds': round(entry.last_seconds, 2),
            'percent': round(100.0 * used / span, 1) if span > 0 else None,
        }
    return result


class RunRecorder:
    """A run's messages -> its :class:`RunRecord`, the same whether fed live or from a bag.

    Each ``on_*`` handler takes one message; they may be called from several
    threads. A final drvs/RecorderSample closes the recording: messages after it
    are ignored, so a bag, which goes on after the live recorder stopped, gives
    what the live recorder had. Nothing here reads a clock or /proc: a robot's
    elapsed time counts in ROS time from the run's first status, of any robot, to
    that robot's newest status up to its arrival or failure; what only the live node
    knows (CPU use, wall-clock seconds) comes in drvs/RecorderSample messages.
    """

    def __init__(self, world: World):
        self.world = world
        self.record = RunRecord(world=world)
        self._lock = threading.Lock()  # guards self.record and every field below
        self._closed = False
        self._status: dict[str, dict] = {}  # robot -> its newest status
        self._first_status: genpy.Time | None = None  # of the first robot status received or sampled
        self._counted_status: dict[str, genpy.Time] = {}  # robot -> its newest status up to the end
        self._last_trace: dict[str, tuple[float, float]] = {}
        self._robot_position: dict[str, tuple[float, float]] = {}
        # The bodies whose ground truth the tracking metrics need over time: robots and humans.
        self._moving = {r.name for r in world.robots} | {o.name for o in world.objects if o.moving}
        self._touching: dict[str, set[str]] = {}  # robot -> what it touched in the last ground truth

    @property
    def closed(self) -> bool:
        with self._lock:
            return self._closed

    @property
    def first_status(self) -> genpy.Time | None:
        """The header stamp of the first robot status it received (None before)."""
        with self._lock:
            return self._first_status

    def topics(self) -> dict[str, tuple[type, Callable]]:
        """Every topic it reads (not the samples) -> (message type, handler)."""
        topics: dict[str, tuple[type, Callable]] = {
            '/world_sim/ground_truth': (String, self.on_truth),
            '/drvs/registry': (Registry, self.on_registry),
            '/drvs/stats': (ServerStats, self.on_server_stats),
            '/world_sim/poses': (BodyPoses, self.on_poses),
            '/drvs/objects': (TrackedObjects, self.on_objects),
        }
        for robot in self.world.robots:
            for name, message_type, handler in (
                ('status', RobotStatus, self.on_status),
                ('path', PathMsg, self.on_path),
                ('map', OccupancyGrid, self.on_map),
            ):
                topics[f'/{robot.name}/{name}'] = (message_type, functools.partial(handler, robot=robot.name))
        for camera in self.world.vision_systems:
            handler = functools.partial(self.on_stats, camera=camera.name)
            topics[f'/{camera.name}/stats'] = (VisionSystemStats, handler)
        return topics

    # -- the messages -----------------------------------------------------------------------------
    def on_truth(self, msg: String) -> None:
        truth = json.loads(msg.data)
        robots = truth.get('robots') or {  # a bag from before fleets: the one robot's
            self.world.robots[0].name: {key: truth[key] for key in ('contacts', 'travelled')} | truth['robot']
        }
        with self._lock:
            if self._closed:
                return
            for name, robot in self.record.robots.items():
                if name not in robots:
                    continue
                x, y = robots[name]['position']
                self._robot_position[name] = (x, y)
                robot.collisions = int(robots[name]['contacts'])
                touching = set(robots[name].get('touching', ()))
                for other in sorted(touching - self._touching.get(name, set())):
                    robot.touches.append((other, x, y))
                self._touching[name] = touching
                robot.travelled = float(robots[name]['travelled'])
                last = self._last_trace.get(name)
                if last is None or math.dist(last, (x, y)) >= TRACE_STEP:
                    robot.trajectory.append((float(truth['time']), x, y))
                    self._last_trace[name] = (x, y)
            for obstacle in self.world.objects:
                pose = truth['objects'].get(obstacle.name)
                if obstacle.moving and pose:
                    trace = self.record.humans.setdefault(obstacle.name, [])
                    if not trace or math.dist(trace[-1], pose[:2]) >= TRACE_STEP:
                        trace.append((pose[0], pose[1]))

    # -- tracking: ground truth and the fused tracks (drvs.sim.tracking) ----------------------------
    def on_poses(self, msg: BodyPoses) -> None:
        """The moving bodies' poses, every :data:`TRUTH_STEP`, for the tracking metrics (from the
        first sample on, as every tracking message)."""
        stamp, poses = body_poses_from_msg(msg)
        with self._lock:
            if self._closed:
                return
            for name in self._moving & poses.keys():
                samples = self.record.truth.setdefault(name, [])
                # One per TRUTH_STEP of ROS time, on a grid fixed by the stamps (not by the first
                # pose this subscriber happened to receive): a bag gives the same samples.
                if not samples or math.floor(stamp / TRUTH_STEP) > math.floor(samples[-1][0] / TRUTH_STEP):
                    samples.append((stamp, *poses[name][:2]))

    def on_objects(self, msg: TrackedObjects) -> None:
        """One period of the fusion stage's tracks: each object's algorithm, track id and centroid."""
        if len(msg.algorithms) != len(msg.objects):
            LOG.warning(
                '/drvs/objects: %d algorithm(s) for %d object(s): message left out of the tracking metrics',
                len(msg.algorithms),
                len(msg.objects),
            )
            return
        tracks = tuple(
            TrackPoint(algorithm, int(obj.track_id), *centroid([(p.x, p.y) for p in obj.boundary.points]))
            for algorithm, obj in zip(msg.algorithms, msg.objects, strict=True)
        )
        with self._lock:
            if not self._closed:  # counted over the samples' stamps (RunRecord.tracking_window)
                self.record.track_periods.append(TrackPeriod(msg.header.stamp.to_sec(), tracks))

    def on_status(self, msg: RobotStatus, robot: str) -> bool:
        """One status of ``robot``; True if it counted towards the robot's elapsed time."""
        status = robot_status_to_dict(msg)
        with self._lock:
            if self._closed:
                return False
            record = self.record.robots[robot]
            if self._first_status is None:
                self._first_status = msg.header.stamp
            replans = int(status.get('replans', 0))
            if replans > record.replans and robot in self._robot_position:
                record.replan_points.append(self._robot_position[robot])
            record.replans = replans
            counted = record.state not in DONE
            record.state = status.get('state', '')
            record.reason = status.get('reason') or ''
            for key in ROBOT_FIGURES:
                setattr(record, key, getattr(msg, key))
            if counted:
                self._counted_status[robot] = msg.header.stamp
                self._update_elapsed()
            record.reached = record.reached or record.state == 'arrived'
            pose = status.get('tag_pose')
            poses = record.tag_poses
            if pose and (not poses or math.dist(poses[-1][:2], pose[:2]) >= TAG_POSE_STEP):
                poses.append(tuple(float(v) for v in pose))
            self._status[robot] = status
            return counted

    def on_path(self, msg: PathMsg, robot: str) -> None:
        """Keep the first plan and the plan of each re-plan, not every repair of the same route."""
        plan = [(p.pose.position.x, p.pose.position.y) for p in msg.poses]
        with self._lock:
            record = self.record.robots[robot]
            if not self._closed and plan and len(record.plans) <= record.replans:
                record.plans.append((msg.header.stamp.to_sec(), plan))

    def on_map(self, msg: OccupancyGrid, robot: str) -> None:
        """Accumulate every cell any robot ever mapped as an obstacle: the run's detected objects."""
        grid = np.asarray(msg.data, dtype=np.int8).reshape(msg.info.height, msg.info.width)
        with self._lock:
            if self._closed:
                return
            if self.record.grid is not None and self.record.grid.shape == grid.shape:
                grid = np.maximum(self.record.grid, grid)
            self.record.grid = grid
            self.record.grid_origin = (msg.info.origin.position.x, msg.info.origin.position.y)
            self.record.grid_resolution = msg.info.resolution

    def on_registry(self, msg: Registry) -> None:
        entries = registry_to_dict(msg)['vision_systems']
        with self._lock:
            if self._closed:
                return
            for entry in entries:
                self.record.fields_of_view[entry['service_name']] = [tuple(p) for p in entry['field_of_view']]

    def on_server_stats(self, msg: ServerStats) -> None:
        with self._lock:
            if not self._closed:
                self.record.server = {key: getattr(msg, key) for key in SERVER_FIGURES}

    def on_stats(self, msg: VisionSystemStats, camera: str) -> None:
        with self._lock:
            if self._closed:
                return
            self.record.vision_systems[camera] = {
                **{key: getattr(msg, key) for key in CAMERA_FIGURES},
                'requests_by_algorithm': stats_to_dict(msg)['requests_by_algorithm'],
            }

    def on_sample(self, msg: RecorderSample) -> None:
        """The live recorder's CPU figures, first status and wall time; a final one closes the recording."""
        with self._lock:
            if self._closed:
                return
            if not msg.first_status.is_zero():
                self._first_status = msg.first_status
                self._update_elapsed()
            self.record.cpu = cpu_summary(msg.cpu)
            self.record.wall_seconds = msg.wall_seconds
            self._closed = msg.final
            stamp = msg.header.stamp.to_sec()
            first = self.record.tracking_window[0] if self.record.tracking_window else stamp
            self.record.tracking_window = (first, stamp)

    def _update_elapsed(self) -> None:
        """Each robot's seconds from the first status to its newest counted one (under the lock)."""
        if self._first_status is not None:
            for name, stamp in self._counted_status.items():
                self.record.robots[name].elapsed = (stamp - self._first_status).to_sec()

    # -- progress ---------------------------------------------------------------------------------
    def status_line(self) -> str:
        """One line of progress: state, distance to goal (of the one robot; in a fleet how many are
        in each state and arrived), re-plans, collisions."""
        with self._lock:
            robots = self.record.robots.values()
            totals = (
                f'replans {sum(r.replans for r in robots)}',
                f'collisions {sum(r.collisions for r in robots)}',
            )
            if len(self.record.robots) == 1:
                (status,) = self._status.values() or ({},)
                distance = status.get('distance_to_goal')
                return ' | '.join(
                    (
                        f'state {status.get("state", "starting")}',
                        f'distance to goal {distance:.2f} m'
                        if isinstance(distance, int | float)
                        else 'distance to goal ?',
                        *totals,
                    )
                )
            states = collections.Counter(
                self._status.get(name, {}).get('state', 'starting') for name in self.record.robots
            )
            arrived = sum(r.reached for r in robots)
            return ' | '.join(
                (
                    'state ' + ', '.join(f'{state} {n}' for state, n in sorted(states.items())),
                    f'arrived {arrived} of {len(self.record.robots)}',
                    *totals,
                )
            )


class RecorderNode:
    """The live recorder: subscriptions into a :class:`RunRecorder`, CPU samples, the files."""

    def __init__(self, world_path: str, out: str, cpu_period: float = 1.0):
        self.world = load_world(world_path)
        self.out = Path(out)
        self.cpu_period = cpu_period
        self.recorder = RunRecorder(self.world)
        self._lock = threading.Lock()  # guards the fields below and the order of the samples
        self._cpu: dict[str, NodeCpu] = {}
        self._first_wall: float | None = None  # time.monotonic() of the first status counted
        self._wall_seconds = 0.0  # from the first counted status to the newest
        self._finished = False
        self.samples_pub: rospy.Publisher | None = None
        # No /diagnostics: the recorder is no part of DRVS. The sampler asks the master for every
        # node: it fails while a master restarts, and restarts.
        self.node = NodeScaffold(None)

    @property
    def record(self) -> RunRecord:
        return self.recorder.record

    def start(self) -> None:
        self.out.mkdir(parents=True, exist_ok=True)
        # Unqueued: publish() writes to each subscriber before it returns, so the final sample
        # reaches a bag recorder before this node exits (rospy warns about queue_size=None).
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', SyntaxWarning)
            self.samples_pub = rospy.Publisher('~samples', RecorderSample, queue_size=None, latch=True)
        for topic, (message_type, handler) in self.recorder.topics().items():
            # Every message, as the bag has it (a trajectory missing a step is another length);
            # of the maps, which each hold the robot's whole map, the newest.
            queue_size = 1 if message_type is OccupancyGrid else QUEUE
            if message_type is RobotStatus:
                handler = functools.partial(self._on_status, handler=handler)
            rospy.Subscriber(topic, message_type, handler, queue_size=queue_size)
        rospy.on_shutdown(self.stop)  # runs before rospy's shutdown flag: it can still publish
        self.node.spawn(self._sample_loop, 'cpu-sampler')

    def _on_status(self, msg: RobotStatus, handler: Callable[[RobotStatus], bool]) -> None:
        """A robot's status into the recorder; while it counts, the wall clock's seconds with it."""
        if handler(msg):
            now = time.monotonic()
            with self._lock:
                if self._first_wall is None:
                    self._first_wall = now
                self._wall_seconds = now - self._first_wall

    # -- CPU and progress -------------------------------------------------------------------------
    def _sample_loop(self) -> None:
        last_sample = -math.inf
        while not rospy.is_shutdown():
            if time.monotonic() - last_sample >= self.cpu_period:
                last_sample = time.monotonic()
                self._sample_cpu()
            self._write_status_line()
            if self.node.wait(min(self.cpu_period, STATUS_LINE_PERIOD)):
                return

    def _node_pids(self) -> dict[str, int]:
        master = rospy.get_master()
        pids = {}
        _, _, (publishers, subscribers, services) = master.getSystemState()
        nodes = {n for _, names in publishers + subscribers + services for n in names}
        for node in nodes:
            try:
                code, _, uri = master.lookupNode(node)
                if code != 1:
                    continue
                with xmlrpc.client.ServerProxy(uri) as proxy:
                    code, _, pid = proxy.getPid(rospy.get_name())
                if code == 1:
                    pids[node] = int(pid)
            except OSError:
                continue
        return pids

    def _sample_cpu(self) -> None:
        try:
            pids = self._node_pids()
        except OSError:
            return
        now = genpy.Time.from_sec(time.time())  # CPU use per wall second, also under sim time
        with self._lock:
            if self._finished:
                return
            for node, pid in pids.items():
                seconds = process_cpu_seconds(pid)
                if seconds is None:
                    continue
                entry = self._cpu.get(node)
                if entry is None or entry.pid != pid:  # a restarted node starts its count again
                    entry = self._cpu[node] = NodeCpu(
                        node=node, pid=pid, first_seconds=seconds, first_stamp=now
                    )
                entry.last_seconds, entry.last_stamp = seconds, now
            self._publish_sample(final=False)

    def _publish_sample(self, final: bool) -> None:
        """Publish the CPU figures so far and feed them to the recorder (under the lock)."""
        first_status = self.recorder.first_status
        msg = RecorderSample(
            header=Header(stamp=rospy.Time.now()),
            world=str(self.world.path),
            first_status=first_status if first_status is not None else genpy.Time(),
            final=final,
            cpu=[self._cpu[node] for node in sorted(self._cpu)],
            wall_seconds=self._wall_seconds,
        )
        try:
            self.samples_pub.publish(msg)
        except rospy.ROSException as error:  # the node is already shut down: the files still follow
            rospy.logwarn('recorder: sample not published: %s', error)
        self.recorder.on_sample(msg)

    def _write_status_line(self) -> None:
        tmp = self.out / 'status.line.tmp'
        tmp.write_text(self.recorder.status_line())
        tmp.replace(self.out / 'status.line')

    # -- the end ----------------------------------------------------------------------------------
    def stop(self) -> None:
        """Finish (:meth:`finish`), then end the sampler."""
        try:
            self.finish()
        finally:
            self.node.stop()

    def finish(self) -> None:
        """Publish the final sample, then write summary.json, trace.json and run.png (once)."""
        with self._lock:
            if self._finished:
                return
            self._finished = True
            self._publish_sample(final=True)
        write_report(self.recorder.record, self.out)
        rospy.loginfo('wrote %s and %s', self.out / 'summary.json', self.out / 'run.png')
