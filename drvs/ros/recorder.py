"""The scenario recorder node: watches a run and leaves its picture and summary.

It is the scenario's observer, not part of DRVS: it reads ground truth from
world_sim, the robot's status, plans and map, the server's registry and every
vision system's traffic counters, samples each node's CPU use, keeps a one-line
progress report in ``~out/status.line`` (``run_scenario.sh`` shows it), and on
shutdown writes ``~out/summary.json``, ``~out/trace.json`` (trajectory,
plans, re-plan points, humans' paths) and ``~out/run.png`` (:mod:`drvs.report`).

Parameters (private):

``~world`` (str, required)
    The world file of the run.
``~out`` (str, required)
    The folder for ``summary.json``, ``run.png`` and ``status.line``.
``~cpu_period`` (float, default 1)
    Seconds between CPU samples of every node.

Topics read: ``/world_sim/ground_truth`` (JSON), ``/robot/status`` (drvs/RobotStatus),
``/robot/path``, ``/robot/map``, ``/drvs/registry`` (drvs/Registry), ``/<camera>/stats``
(drvs/VisionSystemStats) for every camera of the world.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
import xmlrpc.client
from pathlib import Path

import numpy as np
import rospy
from nav_msgs.msg import OccupancyGrid
from nav_msgs.msg import Path as PathMsg
from std_msgs.msg import String

from drvs.guard import RESTART, LoopGuard
from drvs.msg import Registry, RobotStatus, VisionSystemStats
from drvs.report import RunRecord, draw, hindsight_shortest_length, summary, trace
from drvs.ros.messages import registry_to_dict, robot_status_to_dict, stats_to_dict
from drvs.world import load_world

CLOCK_TICKS = os.sysconf('SC_CLK_TCK')
TRACE_STEP = 0.01
"""Metres between two recorded trajectory points."""
TAG_POSE_STEP = 0.4
"""Metres between two tag poses kept for the picture (one arrow every this far)."""


def process_cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of a live process (and its reaped children), or None."""
    try:
        with open(f'/proc/{pid}/stat', 'rb') as handle:
            fields = handle.read().rsplit(b')', 1)[1].split()
    except OSError:
        return None
    return sum(int(v) for v in fields[11:15]) / CLOCK_TICKS


class RecorderNode:
    def __init__(self, world_path: str, out: str, cpu_period: float = 1.0):
        self.world = load_world(world_path)
        self.out = Path(out)
        self.cpu_period = cpu_period
        self.record = RunRecord(world=self.world)
        self._lock = threading.Lock()  # guards self.record and the fields below
        self._started = time.monotonic()
        self._first_status: float | None = None
        self._status: dict = {}
        self._cpu: dict[str, dict] = {}  # node -> {'pid', 'first', 'last', 'first_time', 'last_time'}
        self._last_trace: tuple[float, float] | None = None
        self._robot_position: tuple[float, float] | None = None
        self._written = False
        # The sampler asks the master for every node: it fails while a master restarts; it restarts.
        self.guard = LoopGuard(on_fatal=lambda reason: rospy.signal_shutdown(reason), restart_delay=1.0)

    def start(self) -> None:
        self.out.mkdir(parents=True, exist_ok=True)
        rospy.Subscriber('/world_sim/ground_truth', String, self._on_truth, queue_size=5)
        rospy.Subscriber('/robot/status', RobotStatus, self._on_status, queue_size=5)
        rospy.Subscriber('/robot/path', PathMsg, self._on_path, queue_size=5)
        rospy.Subscriber('/robot/map', OccupancyGrid, self._on_map, queue_size=1)
        rospy.Subscriber('/drvs/registry', Registry, self._on_registry, queue_size=5)
        for camera in self.world.vision_systems:
            rospy.Subscriber(
                f'/{camera.name}/stats',
                VisionSystemStats,
                self._on_stats,
                callback_args=camera.name,
                queue_size=5,
            )
        rospy.on_shutdown(self.finish)
        self.guard.spawn(self._sample_loop, 'cpu-sampler', RESTART)

    # -- subscriptions ----------------------------------------------------------------------------
    def _on_truth(self, msg: String) -> None:
        truth = json.loads(msg.data)
        x, y = truth['robot']['position']
        with self._lock:
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

    def _on_status(self, msg: RobotStatus) -> None:
        status = robot_status_to_dict(msg)
        now = time.monotonic()
        with self._lock:
            if self._first_status is None:
                self._first_status = now
            replans = int(status.get('replans', 0))
            if replans > self.record.replans and self._robot_position is not None:
                self.record.replan_points.append(self._robot_position)
            self.record.replans = replans
            self.record.state = status.get('state', '')
            self.record.reason = status.get('reason') or ''
            if not self.record.reached:
                self.record.elapsed = now - self._first_status
            self.record.reached = self.record.reached or self.record.state == 'arrived'
            pose = status.get('tag_pose')
            poses = self.record.tag_poses
            if pose and (not poses or math.dist(poses[-1][:2], pose[:2]) >= TAG_POSE_STEP):
                poses.append(tuple(float(v) for v in pose))
            self._status = status

    def _on_path(self, msg: PathMsg) -> None:
        """Keep the first plan and the plan of each re-plan, not every repair of the same route."""
        plan = [(p.pose.position.x, p.pose.position.y) for p in msg.poses]
        with self._lock:
            if plan and len(self.record.plans) <= self.record.replans:
                self.record.plans.append((time.monotonic() - self._started, plan))

    def _on_map(self, msg: OccupancyGrid) -> None:
        """Accumulate every cell the robot ever mapped as an obstacle: the run's detected objects."""
        grid = np.asarray(msg.data, dtype=np.int8).reshape(msg.info.height, msg.info.width)
        with self._lock:
            if self.record.grid is not None and self.record.grid.shape == grid.shape:
                grid = np.maximum(self.record.grid, grid)
            self.record.grid = grid
            self.record.grid_origin = (msg.info.origin.position.x, msg.info.origin.position.y)
            self.record.grid_resolution = msg.info.resolution

    def _on_registry(self, msg: Registry) -> None:
        entries = registry_to_dict(msg)['vision_systems']
        with self._lock:
            for entry in entries:
                self.record.fields_of_view[entry['service_name']] = [tuple(p) for p in entry['field_of_view']]

    def _on_stats(self, msg: VisionSystemStats, camera: str) -> None:
        stats = stats_to_dict(msg)
        with self._lock:
            self.record.vision_systems[camera] = {
                'requests': stats.get('requests', 0),
                'callbacks': stats.get('callbacks', 0),
                'callback_bytes': stats.get('callback_bytes', 0),
                'renders': stats.get('renders', 0),
                'cache_hits': stats.get('cache_hits', 0),
                'requests_by_algorithm': stats.get('requests_by_algorithm', {}),
            }

    # -- CPU and progress -------------------------------------------------------------------------
    def _sample_loop(self) -> None:
        while not rospy.is_shutdown():
            self._sample_cpu()
            self._write_status_line()
            time.sleep(min(self.cpu_period, 0.5))

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
        now = time.monotonic()
        try:
            pids = self._node_pids()
        except OSError:
            return
        with self._lock:
            for node, pid in pids.items():
                seconds = process_cpu_seconds(pid)
                if seconds is None:
                    continue
                entry = self._cpu.setdefault(node, {'first': seconds, 'first_time': now})
                entry.update(last=seconds, last_time=now)

    def _write_status_line(self) -> None:
        with self._lock:
            distance = self._status.get('distance_to_goal')
            line = ' | '.join(
                (
                    f'state {self._status.get("state", "starting")}',
                    f'distance to goal {distance:.2f} m'
                    if isinstance(distance, int | float)
                    else 'distance to goal ?',
                    f'replans {self.record.replans}',
                    f'collisions {self.record.collisions}',
                )
            )
        tmp = self.out / 'status.line.tmp'
        tmp.write_text(line)
        tmp.replace(self.out / 'status.line')

    def cpu_summary(self) -> dict[str, dict]:
        """CPU seconds and mean percent of one core per node, over the time it was sampled."""
        result = {}
        for node, entry in sorted(self._cpu.items()):
            span = entry['last_time'] - entry['first_time']
            used = entry['last'] - entry['first']
            result[node] = {
                'seconds': round(entry['last'], 2),
                'percent': round(100.0 * used / span, 1) if span > 0 else None,
            }
        return result

    # -- the end ----------------------------------------------------------------------------------
    def finish(self) -> None:
        """Write summary.json and run.png (once)."""
        with self._lock:
            if self._written:
                return
            self._written = True
            self.record.cpu = self.cpu_summary()
            record = self.record
        radius = math.hypot(*self.world.robot.size[:2]) / 2.0
        best = hindsight_shortest_length(self.world, radius)
        result = summary(record, best)
        (self.out / 'summary.json').write_text(json.dumps(result, indent=2) + '\n')
        (self.out / 'trace.json').write_text(json.dumps(trace(record)) + '\n')
        draw(record, self.out / 'run.png')
        rospy.loginfo('wrote %s and %s', self.out / 'summary.json', self.out / 'run.png')
