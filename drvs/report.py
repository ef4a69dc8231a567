"""A scenario run's picture and summary, from what was recorded while it ran.

:class:`RunRecord` holds the recording (plans, driven trajectory, re-plans,
fields of view, the robot's map, per-camera traffic, CPU use). :func:`summary`
turns it into the ``summary.json`` dictionary and :func:`picture` into the
picture (a matplotlib Figure, which :func:`draw` writes as a PNG), in the style
of the paper's Figures 7, 8, 10 and 11; :func:`write_report` writes both and
``trace.json`` (the live recorder and ``drvs_report`` share it).
:func:`hindsight_shortest_length` is the shortest collision-free route among
the world's static obstacles, computed on a visibility graph (exact for
polygonal obstacles, unlike a grid).
"""

from __future__ import annotations

import heapq
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from shapely.geometry import LineString, Point, Polygon, box
from shapely.ops import unary_union

from drvs.world import World


@dataclass
class RunRecord:
    """Everything a scenario run leaves behind for its picture and summary."""

    world: World
    reached: bool = False
    elapsed: float = 0.0
    state: str = 'starting'
    reason: str = ''
    replans: int = 0
    collisions: int = 0
    trajectory: list[tuple[float, float, float]] = field(default_factory=list)  # (t, x, y), ground truth
    humans: dict[str, list[tuple[float, float]]] = field(default_factory=dict)  # name -> [(x, y)]
    plans: list[tuple[float, list[tuple[float, float]]]] = field(default_factory=list)  # (t, path)
    replan_points: list[tuple[float, float]] = field(default_factory=list)
    fields_of_view: dict[str, list[tuple[float, float]]] = field(default_factory=dict)
    grid: np.ndarray | None = None  # every cell the robot mapped (rows = y), 0-100 or -1, over the run
    grid_origin: tuple[float, float] = (0.0, 0.0)
    grid_resolution: float = 0.05
    vision_systems: dict[str, dict] = field(default_factory=dict)  # name -> stats
    cpu: dict[str, dict] = field(default_factory=dict)  # node -> {'seconds':, 'percent':}
    tag_poses: list[tuple[float, float, float]] = field(default_factory=list)  # (x, y, heading) seen


def path_length(points) -> float:
    points = [(p[-2], p[-1]) for p in points]
    return float(sum(math.dist(a, b) for a, b in zip(points, points[1:], strict=False)))


def hindsight_shortest_length(world: World, radius: float, start=None, goal=None) -> float:
    """Length of the shortest route from the robot's start to the station among static obstacles.

    Obstacles are the static objects' footprints grown by ``radius`` (the robot's
    clearance); the route must stay ``radius`` inside the floor. Humans move, so
    they are not obstacles in hindsight. Returns ``inf`` when no route exists.
    """
    start = Point(start or world.robot.position)
    goal = Point(goal or world.station.position)
    floor = box(0.0, 0.0, *world.floor_size).buffer(-radius, join_style=2)
    grown = [Polygon(o.footprint()).buffer(radius, join_style=2) for o in world.objects if o.kind == 'static']
    blocked = unary_union(grown) if grown else Polygon()
    free = floor.difference(blocked).buffer(1e-6)  # a route may run along an obstacle's edge
    nodes = [start, goal]
    if not blocked.is_empty:
        corners = blocked.buffer(1e-3, join_style=2)
        parts = corners.geoms if hasattr(corners, 'geoms') else [corners]
        nodes += [Point(c) for part in parts for c in part.exterior.coords[:-1] if free.contains(Point(c))]

    def visible(a: Point, b: Point) -> bool:
        return free.contains(LineString([a, b]))

    distance = {0: 0.0}
    queue = [(0.0, 0)]
    goal_index = 1
    done = set()
    while queue:
        d, i = heapq.heappop(queue)
        if i in done:
            continue
        if i == goal_index:
            return d
        done.add(i)
        for j, other in enumerate(nodes):
            if j in done or j == i:
                continue
            nd = d + nodes[i].distance(other)
            if nd < distance.get(j, math.inf) and visible(nodes[i], other):
                distance[j] = nd
                heapq.heappush(queue, (nd, j))
    return math.inf


def summary(record: RunRecord, best_length: float) -> dict:
    """The ``summary.json`` content: outcome, lengths, re-plans, collisions, traffic and CPU."""
    return {
        'world': str(record.world.path),
        'reached': bool(record.reached),
        'state': record.state,
        'reason': record.reason,
        'elapsed': round(record.elapsed, 2),
        'driven_length': round(path_length(record.trajectory), 3),
        'best_length': round(best_length, 3) if math.isfinite(best_length) else None,
        'replans': record.replans,
        'collisions': record.collisions,
        'vision_systems': dict(sorted(record.vision_systems.items())),
        'cpu': dict(sorted(record.cpu.items())),
    }


def trace(record: RunRecord) -> dict:
    """The ``trace.json`` content: the run's geometry over time, for tests and later plots."""
    return {
        'trajectory': record.trajectory,
        'plans': [plan for _, plan in record.plans],
        'replan_points': record.replan_points,
        'humans': record.humans,
        'fields_of_view': record.fields_of_view,
        'tag_poses': record.tag_poses,
    }


def write_report(record: RunRecord, out: str | Path) -> dict:
    """Write ``summary.json``, ``trace.json`` and ``run.png`` into ``out``; return the summary.

    The best length is the hindsight route for the robot's clearance (half its diagonal).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    radius = math.hypot(*record.world.robot.size[:2]) / 2.0
    result = summary(record, hindsight_shortest_length(record.world, radius))
    (out / 'summary.json').write_text(json.dumps(result, indent=2) + '\n')
    (out / 'trace.json').write_text(json.dumps(trace(record)) + '\n')
    draw(record, out / 'run.png')
    return result


# Colours of the picture: the driven trajectory alone in red; cameras and humans from
# palettes without it (the plans are blue to green, the robot's map orange).
TRAJECTORY_COLOUR = 'red'
CAMERA_COLOURS = ('tab:blue', 'tab:cyan', 'tab:olive', 'tab:gray', 'navy', 'teal', 'goldenrod', 'slategray')
HUMAN_COLOURS = ('tab:brown', 'tab:pink', 'darkmagenta')


def camera_name(service: str) -> str:
    """The vision system a registered service belongs to.

    >>> camera_name('/vs1/detect_object_boundary')
    'vs1'
    """
    return service.strip('/').split('/')[0]


def draw(record: RunRecord, path: str | Path) -> None:
    """Write the run's picture (:func:`picture`) to ``path`` (a PNG)."""
    picture(record).savefig(path, bbox_inches='tight')


def picture(record: RunRecord):
    """The run's picture as a matplotlib Figure (no pyplot, nothing global), its legend beside it.

    Floor, the robot's map, every camera (position and dashed field of view, one legend
    entry each, by name; a camera of the world that never registered is marked so),
    obstacles, each human's walk and last position, the station, the plans, the driven
    trajectory with its start and the robot's final position, tag poses and re-plans.
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
        # Cells the robot ever mapped: 100 = an obstacle outline, 99 = its inflated margin.
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
    for i, name in enumerate(sorted(set(cameras) | set(views))):
        colour = CAMERA_COLOURS[i % len(CAMERA_COLOURS)]
        fov = views.get(name)
        if fov:
            axes.add_patch(
                Patch(
                    fov,
                    closed=True,
                    fill=False,
                    linestyle='--',
                    linewidth=1.3,
                    edgecolor=colour,
                    zorder=2,
                    label=f'{name} field of view',
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

    def rgb(colour):
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
    axes.add_patch(
        Patch(
            world.station.footprint(),
            closed=True,
            facecolor=rgb(world.station.colour),
            edgecolor='black',
            zorder=3,
            label='charging station',
        )
    )

    plan_colours = matplotlib.colormaps['winter']
    for i, (_, plan) in enumerate(record.plans):
        if len(plan) >= 2:
            xs, ys = zip(*plan, strict=True)
            colour = plan_colours(i / max(1, len(record.plans) - 1)) if i else 'blue'
            axes.plot(
                xs,
                ys,
                '-',
                color=colour,
                linewidth=1.5,
                alpha=0.8,
                zorder=4,
                label='first plan' if i == 0 else ('re-plans' if i == 1 else None),
            )
    if record.trajectory:
        _, xs, ys = zip(*record.trajectory, strict=True)
        axes.plot(xs, ys, '-', color=TRAJECTORY_COLOUR, linewidth=2.5, zorder=5, label='driven trajectory')
        axes.plot(
            xs[0], ys[0], 'o', color='green', markeredgecolor='black', markersize=10, zorder=6, label='start'
        )
        axes.plot(
            xs[-1],
            ys[-1],
            '*',
            color=TRAJECTORY_COLOUR,
            markeredgecolor='black',
            markersize=17,
            zorder=7,
            label='robot at the end',
        )
    if record.tag_poses:
        # The robot's poses as DRVS saw its tag: position and heading, not predicted.
        xs, ys, headings = (np.asarray(v) for v in zip(*record.tag_poses, strict=True))
        axes.quiver(
            xs,
            ys,
            np.cos(headings),
            np.sin(headings),
            angles='xy',
            scale_units='xy',
            scale=1 / 0.25,
            width=0.004,
            color='purple',
            zorder=6,
            label='tag pose seen (heading)',
        )
    if record.replan_points:
        xs, ys = zip(*record.replan_points, strict=True)
        axes.plot(xs, ys, 'x', color='black', markersize=10, markeredgewidth=2, zorder=7, label='re-plan')

    outcome = 'reached the station' if record.reached else f'did not reach the station ({record.state})'
    axes.set_title(
        f'{world.path.stem}: {outcome} in {record.elapsed:.1f} s, {record.replans} re-plan(s), '
        f'{record.collisions} collision(s)'
    )
    axes.set_xlim(-0.2, width + 0.2)
    axes.set_ylim(-0.2, height + 0.2)
    axes.set_aspect('equal')
    axes.set_xlabel('x (m, map)')
    axes.set_ylabel('y (m, map)')
    axes.grid(True, linewidth=0.3)
    axes.legend(loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=8, framealpha=0.8)
    return figure
