"""The scenario recorder: watches a run and leaves its picture and summary.

It is the scenario's observer, not part of DRVS. :class:`RunRecorder` turns the
messages of a run — ground truth from world_sim, the robot's status, plans and
map, the server's registry, every vision system's traffic counters and the
recorder's own samples (drvs/RecorderSample) — into a :class:`drvs.report.RunRecord`.
It is fed either live, by the subscriptions of :class:`RecorderNode`, or from a
bag in recorded order (:mod:`drvs.ros.bag_report`, ``drvs_report``): the same
messages give the same summary. Nothing in it reads a clock or /proc: elapsed time
counts between the robot's status stamps, and what only the live node can know
(the per-node CPU use it samples from /proc, the first status it received, the
world file, where it stopped) reaches it, and a bag, as a drvs/RecorderSample.

:class:`RecorderNode` is the live node: it samples each node's CPU use and
publishes it latched on ``~samples``, keeps a one-line progress report in
``~out/status.line`` (``run_scenario.sh`` shows it), and on shutdown publishes
a final sample and writes ``~out/summary.json``, ``~out/trace.json`` (trajectory,
plans, re-plan points, humans' paths) and ``~out/run.png`` (:func:`drvs.report.write_report`).

Parameters: :class:`RecorderSettings` (the README's table is generated from it).

Topics read: ``/world_sim/ground_truth`` (JSON), ``/robot/status`` (drvs/RobotStatus),
``/robot/path``, ``/robot/map``, ``/drvs/registry`` (drvs/Registry), ``/<camera>/stats``
(drvs/VisionSystemStats) for every camera of the world. Published: ``~samples``
(drvs/RecorderSample, latched).
"""

from __future__ import annotations

import functools
import json
import math
import os
import threading
import time
import warnings
import xmlrpc.client
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import genpy
import numpy as np
import rospy
from nav_msgs.msg import OccupancyGrid
from nav_msgs.msg import Path as PathMsg
from std_msgs.msg import Header, String

from drvs.guard import RESTART, LoopGuard
from drvs.msg import NodeCpu, RecorderSample, Registry, RobotStatus, VisionSystemStats
from drvs.report import RunRecord, write_report
from drvs.ros.messages import registry_to_dict, robot_status_to_dict, stats_to_dict
from drvs.settings import POSITIVE, REQUIRED, Settings, param
from drvs.world import World, load_world

CLOCK_TICKS = os.sysconf('SC_CLK_TCK')
TRACE_STEP = 0.01
"""Metres between two recorded trajectory points."""
TAG_POSE_STEP = 0.4
"""Metres between two tag poses kept for the picture (one arrow every this far)."""
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
    what the live recorder had.
    """

    def __init__(self, world: World):
        self.world = world
        self.record = RunRecord(world=world)
        self._lock = threading.Lock()  # guards self.record and every field below
        self._closed = False
        self._status: dict = {}
        self._first_status: genpy.Time | None = None  # of the first /robot/status received or sampled
        self._counted_status: genpy.Time | None = None  # of the newest status up to arrival
        self._last_trace: tuple[float, float] | None = None
        self._robot_position: tuple[float, float] | None = None

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
            '/robot/status': (RobotStatus, self.on_status),
            '/robot/path': (PathMsg, self.on_path),
            '/robot/map': (OccupancyGrid, self.on_map),
            '/drvs/registry': (Registry, self.on_registry),
        }
        for camera in self.world.vision_systems:
            handler = functools.partial(self.on_stats, camera=camera.name)
            topics[f'/{camera.name}/stats'] = (VisionSystemStats, handler)
        return topics

    # -- the messages -----------------------------------------------------------------------------
    def on_truth(self, msg: String) -> None:
        truth = json.loads(msg.data)
        x, y = truth['robot']['position']
        with self._lock:
            if self._closed:
                return
            self._robot_position = (x, y)
            self.record.collisions = int(truth['contacts'])
            if self._last_trace is None or math.dist(self._last_trace, (x, y)) >= TRACE_STEP:
                self.record.trajectory.append((float(truth['time']), x, y))
                self._last_trace = (x, y)
            for obstacle in self.world.objects:
                pose = truth['objects'].get(obstacle.name)
                if obstacle.moving and pose:
                    trace = self.record.humans.setdefault(obstacle.name, [])
                    if not trace or math.dist(trace[-1], pose[:2]) >= TRACE_STEP:
                        trace.append((pose[0], pose[1]))

    def on_status(self, msg: RobotStatus) -> None:
        status = robot_status_to_dict(msg)
        with self._lock:
            if self._closed:
                return
            if self._first_status is None:
                self._first_status = msg.header.stamp
            replans = int(status.get('replans', 0))
            if replans > self.record.replans and self._robot_position is not None:
                self.record.replan_points.append(self._robot_position)
            self.record.replans = replans
            self.record.state = status.get('state', '')
            self.record.reason = status.get('reason') or ''
            if not self.record.reached:
                self._counted_status = msg.header.stamp
                self._update_elapsed()
            self.record.reached = self.record.reached or self.record.state == 'arrived'
            pose = status.get('tag_pose')
            poses = self.record.tag_poses
            if pose and (not poses or math.dist(poses[-1][:2], pose[:2]) >= TAG_POSE_STEP):
                poses.append(tuple(float(v) for v in pose))
            self._status = status

    def on_path(self, msg: PathMsg) -> None:
        """Keep the first plan and the plan of each re-plan, not every repair of the same route."""
        plan = [(p.pose.position.x, p.pose.position.y) for p in msg.poses]
        with self._lock:
            if not self._closed and plan and len(self.record.plans) <= self.record.replans:
                self.record.plans.append((msg.header.stamp.to_sec(), plan))

    def on_map(self, msg: OccupancyGrid) -> None:
        """Accumulate every cell the robot ever mapped as an obstacle: the run's detected objects."""
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

    def on_stats(self, msg: VisionSystemStats, camera: str) -> None:
        stats = stats_to_dict(msg)
        with self._lock:
            if self._closed:
                return
            self.record.vision_systems[camera] = {
                'requests': stats.get('requests', 0),
                'callbacks': stats.get('callbacks', 0),
                'callback_bytes': stats.get('callback_bytes', 0),
                'renders': stats.get('renders', 0),
                'cache_hits': stats.get('cache_hits', 0),
                'requests_by_algorithm': stats.get('requests_by_algorithm', {}),
            }

    def on_sample(self, msg: RecorderSample) -> None:
        """The live recorder's CPU figures and first status; a final one closes the recording."""
        with self._lock:
            if self._closed:
                return
            if not msg.first_status.is_zero():
                self._first_status = msg.first_status
                self._update_elapsed()
            self.record.cpu = cpu_summary(msg.cpu)
            self._closed = msg.final

    def _update_elapsed(self) -> None:
        """Seconds from the first status to the newest one up to arrival (under the lock)."""
        if self._first_status is not None and self._counted_status is not None:
            self.record.elapsed = (self._counted_status - self._first_status).to_sec()

    # -- progress ---------------------------------------------------------------------------------
    def status_line(self) -> str:
        """One line of progress: state, distance to goal, re-plans, collisions."""
        with self._lock:
            distance = self._status.get('distance_to_goal')
            return ' | '.join(
                (
                    f'state {self._status.get("state", "starting")}',
                    f'distance to goal {distance:.2f} m'
                    if isinstance(distance, int | float)
                    else 'distance to goal ?',
                    f'replans {self.record.replans}',
                    f'collisions {self.record.collisions}',
                )
            )


@dataclass(frozen=True)
class RecorderSettings(Settings):
    world: str = param(REQUIRED, 'the world file of the run')
    out: str = param(REQUIRED, 'the folder for `summary.json`, `trace.json`, `run.png` and `status.line`')
    cpu_period: float = param(1.0, 'time between CPU samples of every node', unit='s', check=POSITIVE)


class RecorderNode:
    """The live recorder: subscriptions into a :class:`RunRecorder`, CPU samples, the files."""

    def __init__(self, world_path: str, out: str, cpu_period: float = 1.0):
        self.world = load_world(world_path)
        self.out = Path(out)
        self.cpu_period = cpu_period
        self.recorder = RunRecorder(self.world)
        self._lock = threading.Lock()  # guards the fields below and the order of the samples
        self._cpu: dict[str, NodeCpu] = {}
        self._finished = False
        self.samples_pub: rospy.Publisher | None = None
        # The sampler asks the master for every node: it fails while a master restarts; it restarts.
        self.guard = LoopGuard(on_fatal=lambda reason: rospy.signal_shutdown(reason), restart_delay=1.0)

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
            queue_size = 1 if message_type is OccupancyGrid else 5
            rospy.Subscriber(topic, message_type, handler, queue_size=queue_size)
        rospy.on_shutdown(self.finish)  # runs before rospy's shutdown flag: it can still publish
        self.guard.spawn(self._sample_loop, 'cpu-sampler', RESTART)

    # -- CPU and progress -------------------------------------------------------------------------
    def _sample_loop(self) -> None:
        last_sample = -math.inf
        while not rospy.is_shutdown():
            if time.monotonic() - last_sample >= self.cpu_period:
                last_sample = time.monotonic()
                self._sample_cpu()
            self._write_status_line()
            time.sleep(min(self.cpu_period, STATUS_LINE_PERIOD))

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
        now = rospy.Time.now()
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
    def finish(self) -> None:
        """Publish the final sample, then write summary.json, trace.json and run.png (once)."""
        with self._lock:
            if self._finished:
                return
            self._finished = True
            self._publish_sample(final=True)
        write_report(self.recorder.record, self.out)
        rospy.loginfo('wrote %s and %s', self.out / 'summary.json', self.out / 'run.png')
