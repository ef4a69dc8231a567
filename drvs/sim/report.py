"""A scenario run's picture, summary and figures, from what was recorded while it ran.

:class:`RunRecord` holds the recording (a :class:`RobotRecord` per robot and what the run
shares); :func:`summary`, :func:`figures_table` and :func:`picture` turn it into
``summary.json``, the table ``run_scenario.sh`` prints and ``run.png``, and
:func:`write_report` writes them (the live recorder and ``drvs_report`` share it). What
they hold: docs/running-scenarios.md ("What a run leaves") and docs/nodes/scenario_recorder.md.
"""

from __future__ import annotations

import heapq
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from shapely.geometry import LineString, Point, Polygon, box
from shapely.ops import unary_union
from shapely.prepared import prep

from drvs.sim.tracking import TrackPeriod, evaluate
from drvs.sim.world import Body, World

if TYPE_CHECKING:
    from matplotlib.figure import Figure

ROBOT_FIGURES = ('requests', 'watch_calls', 'callbacks', 'callback_bytes')
"""The counters of drvs/RobotStatus a robot's row of the summary carries."""
CAMERA_FIGURES = (
    'requests',
    'watch_calls',
    'renders',
    'callbacks',
    'callback_bytes',
    'watch_evaluations',
    'cache_hits',
)
"""The counters of drvs/VisionSystemStats a camera's entry of the summary carries."""
SERVER_FIGURES = (
    'requests',
    'watch_requests',
    'refused',
    'forwards',
    'watch_forwards',
    'fallback_forwards',
    'forward_failures',
)
"""The counters of drvs/ServerStats the summary's ``server`` carries."""


@dataclass
class RobotRecord:
    """One robot's part of the run."""

    name: str
    reached: bool = False
    elapsed: float = 0.0  # seconds (ROS time) from the run's first status to this robot's arrival or failure
    state: str = 'starting'
    reason: str = ''
    replans: int = 0
    collisions: int = 0
    touches: list[tuple[str, float, float]] = field(default_factory=list)  # (what, x, y) of each contact seen
    travelled: float = 0.0  # metres its body moved (world_sim's odometer): the driven length
    requests: int = 0
    watch_calls: int = 0
    callbacks: int = 0
    callback_bytes: int = 0
    trajectory: list[tuple[float, float, float]] = field(default_factory=list)  # (t, x, y), ground truth
    plans: list[tuple[float, list[tuple[float, float]]]] = field(default_factory=list)  # (t, path)
    replan_points: list[tuple[float, float]] = field(default_factory=list)
    tag_poses: list[tuple[float, float, float]] = field(default_factory=list)  # (x, y, heading) seen


@dataclass
class RunRecord:
    """Everything a scenario run leaves behind for its picture and summary.

    ``robots`` holds a :class:`RobotRecord` for every robot of the world, in its order (an
    empty one for each not given).
    """

    world: World
    robots: dict[str, RobotRecord] = field(default_factory=dict)
    humans: dict[str, list[tuple[float, float]]] = field(default_factory=dict)  # name -> [(x, y)]
    fields_of_view: dict[str, list[tuple[float, float]]] = field(default_factory=dict)
    grid: np.ndarray | None = None  # every cell a robot mapped (rows = y), 0-100 or -1, over the run
    grid_origin: tuple[float, float] = (0.0, 0.0)
    grid_resolution: float = 0.05
    vision_systems: dict[str, dict] = field(default_factory=dict)  # name -> counters
    server: dict[str, int] = field(default_factory=dict)  # SERVER_FIGURES
    cpu: dict[str, dict] = field(default_factory=dict)  # node -> {'seconds':, 'percent':}
    wall_seconds: float = 0.0  # wall-clock seconds from the run's first status to its last counted one
    # The tracking metrics' inputs: the moving bodies' ground truth and each /drvs/objects message.
    truth: dict[str, list[tuple[float, float, float]]] = field(default_factory=dict)  # name -> [(t, x, y)]
    track_periods: list[TrackPeriod] = field(default_factory=list)
    # (from, to): the stamps the tracking metrics count, the same for the live recorder and a bag
    # (None: all). Another subscriber (rosbag record) sees messages near the ends in another order.
    tracking_window: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        self.robots = {r.name: self.robots.get(r.name) or RobotRecord(r.name) for r in self.world.robots}


def clearance(body: Body) -> float:
    """The radius a robot's body keeps from obstacles: half its diagonal."""
    return math.hypot(*body.size[:2]) / 2.0


def hindsight_shortest_length(
    world: World,
    radius: float,
    start: tuple[float, float] | None = None,
    goal: tuple[float, float] | None = None,
) -> float:
    """Length of the shortest route from ``start`` to ``goal`` among static obstacles.

    By default from the (first) robot's start to its station. Obstacles are the static
    objects' footprints grown by ``radius`` (the robot's clearance); the route must stay
    ``radius`` inside the floor. Humans move, so they are not obstacles in hindsight.
    Returns ``inf`` when no route exists.
    """
    start = Point(start or world.robot.position)
    goal = Point(goal or world.station.position)
    floor = box(0.0, 0.0, *world.floor_size).buffer(-radius, join_style=2)
    grown = [Polygon(o.footprint()).buffer(radius, join_style=2) for o in world.objects if o.kind == 'static']
    blocked = unary_union(grown) if grown else Polygon()
    free = prep(floor.difference(blocked).buffer(1e-6))  # a route may run along an obstacle's edge
    nodes = [start, goal]
    if not blocked.is_empty:
        corners = blocked.buffer(1e-3, join_style=2)
        parts = corners.geoms if hasattr(corners, 'geoms') else [corners]
        nodes += [Point(c) for part in parts for c in part.exterior.coords[:-1] if free.contains(Point(c))]

    # A*: the straight distance to the goal never overestimates the rest of the route.
    distance = {0: 0.0}
    queue = [(start.distance(goal), 0.0, 0)]
    goal_index = 1
    done = set()
    while queue:
        _, d, i = heapq.heappop(queue)
        if i in done:
            continue
        if i == goal_index:
            return d
        done.add(i)
        for j, other in enumerate(nodes):
            if j in done:
                continue
            nd = d + nodes[i].distance(other)
            if nd < distance.get(j, math.inf) and free.contains(LineString([nodes[i], other])):
                distance[j] = nd
                heapq.heappush(queue, (nd + other.distance(goal), nd, j))
    return math.inf


def best_lengths(world: World) -> dict[str, float]:
    """Each robot's hindsight shortest route to its station, for its own clearance."""
    return {
        robot.name: hindsight_shortest_length(
            world, clearance(robot.body), robot.body.position, robot.station.position
        )
        for robot in world.robots
    }


def _rounded(value: float, digits: int) -> float | None:
    return round(value, digits) if math.isfinite(value) else None


COLLISION_FAILS = "a collision fails a blind robot's mission"
"""What the summary's reason adds to a robot's collisions: they fail the run whatever else happened."""


def collision_reason(robot: RobotRecord) -> str:
    """Why ``robot``'s collisions fail the run ('' without any): how many, and what it touched where.

    >>> collision_reason(RobotRecord('robot1', collisions=2, touches=[('robot2', 9.31, 3.84)]))
    "robot1 collided 2 times (robot2 at (9.3, 3.8), ...): a collision fails a blind robot's mission"
    """
    if robot.collisions <= 0:
        return ''
    places = [f'{what} at ({x:.1f}, {y:.1f})' for what, x, y in robot.touches[: robot.collisions]]
    if len(places) < robot.collisions:
        places.append('...')  # touches between two ground truths the recorder saw
    times = 'once' if robot.collisions == 1 else f'{robot.collisions} times'
    return f'{robot.name} collided {times} ({", ".join(places)}): {COLLISION_FAILS}'


def run_reason(rows: list[dict]) -> str:
    """Why a run with the summary rows ``rows`` failed ('' when every robot reached its station
    without a collision): each robot that did not reach it, and each collision."""
    reasons = []
    for row in rows:
        if not row['reached']:
            why = f'{row["state"]}: {row["reason"]}' if row['reason'] else row['state']
            reasons.append(f'{row["name"]} did not reach its station ({why})')
        if row['collisions']:
            reasons.append(row['collided'])
    return '; '.join(reasons)


def collision_failure(summary: dict) -> str:
    """Why the collisions in a ``summary.json`` content fail the run ('' without any): the
    ``collided`` text of each robot that collided. ``run_scenario.sh`` exits 1 on it."""
    return '; '.join(row['collided'] for row in summary.get('robots', ()) if row.get('collisions'))


def robot_row(robot: RobotRecord, best_length: float) -> dict:
    """A robot's row of the summary: outcome, lengths and its figures."""
    return {
        'name': robot.name,
        'reached': bool(robot.reached),
        'state': robot.state,
        'reason': robot.reason,
        'collided': collision_reason(robot),
        'collisions': robot.collisions,
        'elapsed': round(robot.elapsed, 2),
        'arrival': round(robot.elapsed, 2) if robot.reached else None,
        'driven_length': round(robot.travelled, 3),
        'best_length': _rounded(best_length, 3),
        'replans': robot.replans,
        **{key: getattr(robot, key) for key in ROBOT_FIGURES},
    }


SINGLE_ROBOT_KEYS = ('state', 'driven_length', 'best_length')
"""A lone robot's row keys repeated at the top level of the summary (its other keys are totals)."""


def summary(record: RunRecord, best_length: Mapping[str, float]) -> dict:
    """The ``summary.json`` content: outcome, a row per robot, the totals, traffic, time and CPU.

    ``success`` is every robot at its station without a collision, ``reason`` why not
    (:func:`run_reason`). ``best_length``: each robot's hindsight route length, by name
    (:func:`best_lengths`).
    """
    rows = [robot_row(robot, best_length.get(name, math.inf)) for name, robot in record.robots.items()]
    reason = run_reason(rows)
    result = {
        'world': str(record.world.path),
        'success': not reason,
        'reason': reason,
        'reached': all(row['reached'] for row in rows),
        'elapsed': max((row['elapsed'] for row in rows), default=0.0),
        'replans': sum(row['replans'] for row in rows),
        'collisions': sum(row['collisions'] for row in rows),
        'real_time_factor': record.world.real_time_factor,
        'wall_seconds': round(record.wall_seconds, 2),
        'robots': rows,
        'server': {key: record.server.get(key, 0) for key in SERVER_FIGURES},
        'vision_systems': dict(sorted(record.vision_systems.items())),
        'cpu': dict(sorted(record.cpu.items())),
        'tracking': tracking(record),
    }
    if len(rows) == 1:
        result |= {key: rows[0][key] for key in SINGLE_ROBOT_KEYS}
    return result


TRACKING_TAIL = 1.0
"""Seconds before the final sample's stamp whose tracks the metrics leave out: a /drvs/objects
message stamped then may reach the live recorder after its final sample, and a bag has it."""


def tracking(record: RunRecord) -> dict:
    """The summary's ``tracking`` block: fused tracks against ground truth (:func:`.tracking.evaluate`),
    the tracks stamped in :attr:`RunRecord.tracking_window` (its end less :data:`TRACKING_TAIL`)."""
    periods = record.track_periods
    if record.tracking_window is not None:
        start, end = record.tracking_window[0], record.tracking_window[1] - TRACKING_TAIL
        periods = [p for p in periods if start <= p.stamp <= end]
    return evaluate(record.world, record.truth, periods)


def trace(record: RunRecord) -> dict:
    """The ``trace.json`` content: the run's geometry over time, for tests and later plots."""
    robots = {
        name: {
            'trajectory': robot.trajectory,
            'plans': [plan for _, plan in robot.plans],
            'replan_points': robot.replan_points,
            'tag_poses': robot.tag_poses,
        }
        for name, robot in record.robots.items()
    }
    result = {'robots': robots, 'humans': record.humans, 'fields_of_view': record.fields_of_view}
    if len(robots) == 1:
        result |= next(iter(robots.values()))
    return result


def write_report(record: RunRecord, out: str | Path) -> dict:
    """Write ``summary.json``, ``trace.json`` and ``run.png`` into ``out``; return the summary."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    result = summary(record, best_lengths(record.world))
    (out / 'summary.json').write_text(json.dumps(result, indent=2) + '\n')
    (out / 'trace.json').write_text(json.dumps(trace(record)) + '\n')
    draw(record, out / 'run.png')
    return result


# -- the figures ----------------------------------------------------------------------------------
def _cell(value) -> str:
    if value is None:
        return '-'
    if isinstance(value, bool):
        return 'yes' if value else 'no'
    if isinstance(value, float):
        return f'{value:.1f}'
    return str(value)


def _table(headers: tuple[str, ...], rows: list[tuple]) -> list[str]:
    """Columns aligned: the first to the left, the others to the right."""
    cells = [headers, *[tuple(_cell(v) for v in row) for row in rows]]
    widths = [max(len(row[i]) for row in cells) for i in range(len(headers))]
    return [
        '  '.join(
            c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths, strict=True))
        )
        for row in cells
    ]


ROBOT_COLUMNS = (
    ('robot', 'name'),
    ('reached', 'reached'),
    ('arrival s', 'arrival'),
    ('requests', 'requests'),
    ('watch calls', 'watch_calls'),
    ('callbacks', 'callbacks'),
    ('callback bytes', 'callback_bytes'),
    ('re-plans', 'replans'),
)
"""The robots' table of :func:`figures_table`: (header, key of the summary's row)."""
CAMERA_COLUMNS = (
    ('requests', 'requests'),
    ('watch calls', 'watch_calls'),
    ('renders', 'renders'),
    ('callbacks', 'callbacks'),
    ('watch evaluations', 'watch_evaluations'),
)
"""The cameras' table of :func:`figures_table` after the name: (header, key of its counters)."""


def figures_table(summary: dict) -> str:
    """The run's figures as text: a row per robot, the server's totals, a row per camera, time.

    >>> print(figures_table({'robots': [], 'server': {'requests': 3}, 'vision_systems': {}, 'cpu': {},
    ...                      'elapsed': 2.0, 'wall_seconds': 2.5, 'real_time_factor': 1.0}))
    robot  reached  arrival s  requests  watch calls  callbacks  callback bytes  re-plans  cpu s
    server: requests 3
    camera  requests  watch calls  renders  callbacks  watch evaluations  cpu s
    time: 2.0 s elapsed in ROS time (real-time factor 1.0), 2.5 s on the wall clock
    """

    def cpu(node: str) -> float | None:
        return summary['cpu'].get(f'/{node}', {}).get('seconds')

    robots = [(*(row[key] for _, key in ROBOT_COLUMNS), cpu(row['name'])) for row in summary['robots']]
    lines = _table((*(header for header, _ in ROBOT_COLUMNS), 'cpu s'), robots)
    server = ', '.join(f'{key.replace("_", " ")} {n}' for key, n in summary['server'].items())
    lines.append(f'server: {server}')
    cameras = [
        (name, *(stats.get(key, 0) for _, key in CAMERA_COLUMNS), cpu(name))
        for name, stats in summary['vision_systems'].items()
    ]
    lines += _table(('camera', *(header for header, _ in CAMERA_COLUMNS), 'cpu s'), cameras)
    lines.append(
        f'time: {summary["elapsed"]:.1f} s elapsed in ROS time (real-time factor '
        f'{summary["real_time_factor"]}), {summary["wall_seconds"]:.1f} s on the wall clock'
    )
    if 'tracking' in summary:
        lines += tracking_lines(summary['tracking'])
    return '\n'.join(lines)


TRACKING_COLUMNS = (
    ('MOTA', 'mota', '.3f'),
    ('IDF1', 'idf1', '.3f'),
    ('switches', 'switches', 'd'),
    ('fragmentations', 'fragmentations', 'd'),
    ('duplicates', 'duplicates', 'd'),
    ('switches/100 track-s', 'switches_per_100_track_seconds', '.2f'),
    ('error mean m', 'position_error_mean', '.3f'),
    ('p50 m', 'position_error_p50', '.3f'),
    ('p95 m', 'position_error_p95', '.3f'),
)
"""The tracking table of :func:`tracking_lines`: (header, key of a row of the block, format)."""


def tracking_lines(block: dict) -> list[str]:
    """The tracking block as text: a row per algorithm and over all, then the targets.

    >>> tracking_lines({'measured': False, 'reason': 'no /drvs/objects messages', 'gate': 0.5})
    ['tracking: not measured: no /drvs/objects messages']
    """
    if not block.get('measured'):
        return [f'tracking: not measured: {block["reason"]}']

    def cells(name: str, kind: str, row: dict) -> tuple:
        values = (
            format(row[key], spec) if row[key] is not None else None for _, key, spec in TRACKING_COLUMNS
        )
        return (name, kind, *values)

    lines = [
        f'tracking: {block["periods"]} periods of /drvs/objects over {block["span"]:.1f} s, against ground '
        f'truth within {block["gate"]} m'
    ]
    rows = [cells(row['algorithm'], row['kind'], row) for row in block['algorithms']]
    rows.append(cells('all', '', block['overall']))
    lines += _table(('algorithm', 'kind', *(header for header, _, _ in TRACKING_COLUMNS)), rows)
    met = []
    for name, entry in block['targets'].items():
        value = '-' if entry['value'] is None else format(entry['value'], '.3g')
        limit = f'{"≤" if entry["at_most"] else "≥"} {entry["target"]}'
        met.append(f'{name} {value} ({limit}: {"met" if entry["met"] else "NOT met"})')
    lines.append('tracking targets: ' + ', '.join(met))
    return lines


# Colours of the picture: each robot's trajectory and station edge in its own colour (the
# first robot's red, as in the paper's worlds); cameras and humans from palettes without
# them (the plans are blue to green, the robots' map orange).
ROBOT_COLOURS = (
    'red',
    'darkviolet',
    'limegreen',
    'deeppink',
    'darkorange',
    'dodgerblue',
    'black',
    'sienna',
    'turquoise',
    'olivedrab',
)
TRAJECTORY_COLOUR = ROBOT_COLOURS[0]
CAMERA_COLOURS = ('tab:blue', 'tab:cyan', 'tab:olive', 'tab:gray', 'navy', 'teal', 'goldenrod', 'slategray')
HUMAN_COLOURS = ('tab:brown', 'tab:pink', 'darkmagenta')
CAMERA_LEGEND_LIMIT = len(CAMERA_COLOURS)
"""More cameras than this share one legend entry (their names are on the floor)."""


def camera_name(service: str) -> str:
    """The vision system a registered service belongs to.

    >>> camera_name('/vs1/detect_object_boundary')
    'vs1'
    """
    return service.strip('/').split('/')[0]


def draw(record: RunRecord, path: str | Path) -> None:
    """Write the run's picture (:func:`picture`) to ``path`` (a PNG)."""
    picture(record).savefig(path, bbox_inches='tight')


def picture(record: RunRecord) -> Figure:
    """The run's picture as a matplotlib Figure (no pyplot, nothing global), its legend beside it.

    Floor, the robots' map, every camera (position and dashed field of view, one legend
    entry each, by name, up to :data:`CAMERA_LEGEND_LIMIT` cameras; a camera of the world that
    never registered is marked so), obstacles, each human's walk and last position, and per
    robot in its colour (:data:`ROBOT_COLOURS`): its station, plans, driven trajectory with its
    start and final position, tag poses and re-plans. A legend entry that the robots share
    is there once; with several robots each trajectory's entry names its robot.
    """
    import matplotlib
    from matplotlib.colors import ListedColormap
    from matplotlib.figure import Figure
    from matplotlib.patches import Polygon as Patch
    from matplotlib.patches import Rectangle

    world = record.world
    width, height = world.floor_size
    figure = Figure(figsize=(10, 10 * height / width + 0.8), dpi=110)
    axes = figure.subplots()
    axes.add_patch(Rectangle((0, 0), width, height, facecolor='#f4f4f0', edgecolor='black'))

    if record.grid is not None and record.grid.size:
        rows, cols = record.grid.shape
        extent = (
            record.grid_origin[0],
            record.grid_origin[0] + cols * record.grid_resolution,
            record.grid_origin[1],
            record.grid_origin[1] + rows * record.grid_resolution,
        )
        # Cells a robot ever mapped: 100 = an obstacle outline, 99 = its inflated margin.
        layers = np.ma.masked_less(record.grid.astype(float), 99)
        axes.imshow(
            layers,
            origin='lower',
            extent=extent,
            cmap=ListedColormap(['#fde0c5', '#f08030']),
            vmin=99,
            vmax=100,
            interpolation='nearest',
            zorder=1,
        )
        axes.add_patch(
            Rectangle((0, 0), 0, 0, facecolor='#f08030', label='detected through DRVS (robot map)')
        )
        axes.add_patch(Rectangle((0, 0), 0, 0, facecolor='#fde0c5', label='inflated by the robot radius'))

    cameras = {camera.name: camera for camera in world.vision_systems}
    views = {camera_name(service): fov for service, fov in record.fields_of_view.items()}
    names = sorted(set(cameras) | set(views))
    each = len(names) <= CAMERA_LEGEND_LIMIT
    for i, name in enumerate(names):
        colour = CAMERA_COLOURS[i % len(CAMERA_COLOURS)]
        fov = views.get(name)
        if fov:
            label = f'{name} field of view' if each else ('fields of view' if i == 0 else None)
            axes.add_patch(
                Patch(
                    fov,
                    closed=True,
                    fill=False,
                    linestyle='--',
                    linewidth=1.3,
                    edgecolor=colour,
                    zorder=2,
                    label=label,
                )
            )
        if name in cameras:
            cx, cy = cameras[name].position[:2]
        else:
            cx, cy = np.mean(np.asarray(fov), axis=0)
        axes.plot(
            cx,
            cy,
            marker='s',
            color='gold' if fov else 'lightgrey',
            markeredgecolor='black',
            markersize=9,
            linestyle='none',
            zorder=6,
            label=None if fov else f'{name}: no field of view registered',
        )
        axes.annotate(
            name, (cx, cy), xytext=(6, 6), textcoords='offset points', color=colour, fontsize=9, zorder=6
        )
    if views:
        axes.plot([], [], 's', color='gold', markeredgecolor='black', markersize=9, label='camera')

    def rgb(colour: tuple[int, int, int]) -> tuple[float, ...]:
        return tuple(c / 255.0 for c in colour)

    for obstacle in world.objects:
        if obstacle.kind == 'static':
            axes.add_patch(
                Patch(
                    obstacle.footprint(),
                    closed=True,
                    facecolor=rgb(obstacle.colour),
                    alpha=0.8,
                    edgecolor='black',
                    zorder=3,
                )
            )
    for i, (name, trace) in enumerate(sorted(record.humans.items())):
        if trace:
            xs, ys = zip(*trace, strict=True)
            axes.plot(
                xs,
                ys,
                ':',
                color=HUMAN_COLOURS[i % len(HUMAN_COLOURS)],
                linewidth=1.5,
                marker='o',
                markersize=10,
                markevery=[len(xs) - 1],
                zorder=3,
                label=f'human {name}: walk and last position',
            )

    fleet = len(world.robots) > 1
    shown: set[str] = set()

    def once(text: str) -> str | None:
        """A legend entry that every robot shares: for the first that draws it."""
        if text in shown:
            return None
        shown.add(text)
        return text

    plan_colours = matplotlib.colormaps['winter']
    for i, fleet_robot in enumerate(world.robots):
        robot = record.robots[fleet_robot.name]
        colour = ROBOT_COLOURS[i % len(ROBOT_COLOURS)]
        axes.add_patch(
            Patch(
                fleet_robot.station.footprint(),
                closed=True,
                facecolor=rgb(fleet_robot.station.colour),
                edgecolor=colour if fleet else 'black',
                linewidth=2.5 if fleet else 1.0,
                zorder=3,
                label=once(
                    "charging stations, edged in their robot's colour" if fleet else 'charging station'
                ),
            )
        )
        for j, (_, plan) in enumerate(robot.plans):
            if len(plan) >= 2:
                xs, ys = zip(*plan, strict=True)
                plan_colour = plan_colours(j / max(1, len(robot.plans) - 1)) if j else 'blue'
                axes.plot(
                    xs,
                    ys,
                    '-',
                    color=plan_colour,
                    linewidth=1.5,
                    alpha=0.8,
                    zorder=4,
                    label=once('first plan') if j == 0 else (once('re-plans') if j == 1 else None),
                )
        if robot.trajectory:
            _, xs, ys = zip(*robot.trajectory, strict=True)
            label = f'{robot.name}: driven trajectory' if fleet else 'driven trajectory'
            axes.plot(xs, ys, '-', color=colour, linewidth=2.5, zorder=5, label=label)
            axes.plot(
                xs[0],
                ys[0],
                'o',
                color='green',
                markeredgecolor='black',
                markersize=10,
                zorder=6,
                label=once('start'),
            )
            axes.plot(
                xs[-1],
                ys[-1],
                '*',
                color=colour,
                markeredgecolor='black',
                markersize=17,
                zorder=7,
                label=once('robot at the end'),
            )
        if robot.tag_poses:
            # The robot's poses as DRVS saw its tag: position and heading, not predicted.
            tag_xs, tag_ys, headings = (np.asarray(v) for v in zip(*robot.tag_poses, strict=True))
            axes.quiver(
                tag_xs,
                tag_ys,
                np.cos(headings),
                np.sin(headings),
                angles='xy',
                scale_units='xy',
                scale=1 / 0.25,
                width=0.004,
                color='purple',
                zorder=6,
                label=once('tag pose seen (heading)'),
            )
        if robot.replan_points:
            xs, ys = zip(*robot.replan_points, strict=True)
            axes.plot(
                xs, ys, 'x', color='black', markersize=10, markeredgewidth=2, zorder=7, label=once('re-plan')
            )

    axes.set_title(_title(record))
    axes.set_xlim(-0.2, width + 0.2)
    axes.set_ylim(-0.2, height + 0.2)
    axes.set_aspect('equal')
    axes.set_xlabel('x (m, map)')
    axes.set_ylabel('y (m, map)')
    axes.grid(True, linewidth=0.3)
    axes.legend(loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=8, framealpha=0.8)
    return figure


def _title(record: RunRecord) -> str:
    robots = list(record.robots.values())
    replans = sum(r.replans for r in robots)
    collisions = sum(r.collisions for r in robots)
    totals = f'{replans} re-plan(s), {collisions} collision(s)'
    if len(robots) == 1:
        (robot,) = robots
        outcome = 'reached the station' if robot.reached else f'did not reach the station ({robot.state})'
        return f'{record.world.path.stem}: {outcome} in {robot.elapsed:.1f} s, {totals}'
    reached = sum(r.reached for r in robots)
    elapsed = max(r.elapsed for r in robots)
    outcome = f'{reached} of {len(robots)} robots reached their stations'
    return f'{record.world.path.stem}: {outcome} in {elapsed:.1f} s, {totals}'
