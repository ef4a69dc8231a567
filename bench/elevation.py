"""Elevation and foreground against ground truth: footprint IoU and height error per object, by
distance from the point below the camera and by depth noise; time per frame against colour.

A camera 3 m up looking straight down at six boxes of known size (a 5 cm pallet to a 1 m box,
0 to 2 m from the point below it), rendered by the simulation (:class:`drvs.sim.scene.Scene`)
at 640×480 and 800×600, its depth perfect or spoilt by :class:`drvs.sim.depth_noise.DepthNoise`
(a Kinect-class sensor, and one with twice its error and wider holes at edges). Per object:
the IoU of the footprint ``elevation`` reports with the box's true footprint, and its height
error; ``foreground`` (reference: the render of the empty world) on the same frames, and colour
segmentation with the boxes' colour model, whose outline met with the floor is the paper's
answer. Times are p50 CPU time of segment + project (:func:`bench.vision.time_request`) per
frame, OpenCV held to one thread, all three algorithms on the same frames in the same run.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import replace

import numpy as np
import yaml
from shapely.geometry import Polygon

from bench.common import Context, Section, figure, save, table
from bench.vision import _label, _ms, time_request
from drvs.algorithms import load_algorithms
from drvs.sim.depth_noise import DepthNoise
from drvs.sim.scene import Scene
from drvs.sim.world_file import load_world
from drvs.vision.camera import PinholeCamera

NAME = 'elevation'
TITLE = 'Elevation and foreground against ground truth'
RESOLUTIONS = ((640, 480), (800, 600))
CENTRE = (3.0, 3.0)
HEIGHT = 3.0
BOX_COLOUR = [150, 90, 40]
COLOUR = 'colour:120,60,20,180,120,70'
BOXES = {  # name: (offset from the point below the camera, size)
    'box30': ((0.0, 0.0), (0.4, 0.4, 0.3)),
    'box50': ((0.7, 0.6), (0.4, 0.6, 0.5)),
    'cart80': ((-0.6, 1.0), (0.3, 0.3, 0.8)),
    'pallet5': ((-1.3, -0.6), (0.8, 0.6, 0.05)),
    'box100': ((1.2, -0.6), (0.5, 0.3, 1.0)),
    'crate20': ((-1.8, 1.0), (0.6, 0.4, 0.2)),
}
NOISES = {
    'none': None,
    'kinect': DepthNoise(seed=1),
    'twice': DepthNoise(error=0.003, edge_width=3, seed=1),
}
BINS = ((0.0, 0.5), (0.5, 1.2), (1.2, 1.8), (1.8, 2.5))


def world_file(ctx: Context, resolution) -> str:
    objects = [
        {
            'name': name,
            'position': [CENTRE[0] + dx, CENTRE[1] + dy],
            'size': list(size),
            'colour': BOX_COLOUR,
        }
        for name, ((dx, dy), size) in BOXES.items()
    ]
    data = {
        'floor': {'size': [8.0, 7.0]},
        'robot': {'position': [7.6, 6.6], 'size': [0.3, 0.3, 0.2], 'colour': [0, 200, 0]},
        'station': {'position': [7.6, 0.4], 'size': [0.4, 0.3, 0.1], 'colour': [0, 0, 220]},
        'objects': objects,
        'vision_systems': [
            {'name': 'cam', 'position': [*CENTRE, HEIGHT], 'fov_deg': 60, 'resolution': list(resolution)}
        ],
        'colour_models': {
            'self': 'colour:0,150,0,80,255,80',
            'station': 'colour:0,0,150,80,80,255',
            'obstacle': COLOUR,
            'human': 'colour:200,0,200,255,60,255',
        },
    }
    path = ctx.work_dir / f'elevation-{_label(resolution)}.yaml'
    path.write_text(yaml.safe_dump(data))
    return str(path)


def truth() -> dict[str, tuple[Polygon, float, float]]:
    """name -> (true footprint, top height, distance of its centre from the point below the camera)."""
    found = {}
    for name, ((dx, dy), (sx, sy, sz)) in BOXES.items():
        x, y = CENTRE[0] + dx, CENTRE[1] + dy
        shape = Polygon(
            [
                (x - sx / 2, y - sy / 2),
                (x + sx / 2, y - sy / 2),
                (x + sx / 2, y + sy / 2),
                (x - sx / 2, y + sy / 2),
            ]
        )
        found[name] = (shape, sz, math.hypot(dx, dy))
    return found


def scores(found, truths) -> dict[str, dict]:
    """Per true box: the IoU of the found object overlapping it most, and that object's height error."""
    result = {}
    for name, (shape, height, _) in truths.items():
        best = max(found, key=lambda f: Polygon(f.outline).intersection(shape).area, default=None)
        if best is None or not Polygon(best.outline).intersects(shape):
            result[name] = {'iou': 0.0, 'height_error': None}
            continue
        outline = Polygon(best.outline)
        iou = outline.intersection(shape).area / outline.union(shape).area
        error = best.height - height if best.height else None
        result[name] = {'iou': iou, 'height_error': error}
    return result


def run(ctx: Context) -> Section:
    import cv2

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        return measure(ctx)
    finally:
        cv2.setNumThreads(threads)


def measure(ctx: Context) -> Section:
    repeats = ctx.pick(2, 10, 30)
    truths = truth()
    accuracy: dict = {}
    timings: dict = {}
    for resolution in RESOLUTIONS:
        label = _label(resolution)
        world = load_world(world_file(ctx, resolution))
        camera = PinholeCamera.from_config(world.vision_systems[0])
        region = (0.0, 0.0, *world.floor_size)
        with Scene(world) as scene:
            with Scene(replace(world, objects=(), robots=())) as empty:
                reference = empty.render(camera).rgb
            algorithms = load_algorithms(reference=reference)
            elevation = algorithms.parse('elevation')
            foreground = algorithms.parse('foreground')
            colour = algorithms.parse(COLOUR)
            accuracy[label] = {}
            for noise_name, noise in NOISES.items():
                ctx.progress(f'elevation: {label}, depth noise {noise_name}')
                rng = noise.generator('cam') if noise is not None else None
                frame = scene.render(camera, noise=noise, rng=rng)
                entry = {}
                times = {}
                flat = replace(frame, depth=None)  # a camera without depth: outlines met with the floor
                runs = (
                    ('elevation', elevation, frame),
                    ('foreground', foreground, flat),
                    ('colour', colour, flat),
                    ('colour with depth', colour, frame),
                )
                for name, algorithm, shown in runs:
                    if noise_name != 'none' and name != 'elevation':
                        continue  # the colour image is the same: measured once
                    segment, project, found = [], [], []
                    for _ in range(repeats):
                        s, p, found = time_request(shown, algorithm.detect, region)
                        segment.append(s)
                        project.append(p)
                    entry[name] = scores(found, truths)
                    times[name] = _ms([s + p for s, p in zip(segment, project, strict=True)])
                accuracy[label][noise_name] = entry
                if noise_name == 'kinect':
                    timings[label] = {**timings.get(label, {}), 'elevation_noisy': times['elevation']}
                if noise_name == 'none':
                    timings[label] = {**timings.get(label, {}), **times}
    summary = by_distance(accuracy, truths)
    return Section(
        NAME,
        TITLE,
        results={'accuracy': accuracy, 'by_distance': summary, 'time_ms': timings},
        markdown=describe(accuracy, summary, timings, truths),
        plots=[plot(ctx, summary)],
    )


def by_distance(accuracy, truths) -> dict:
    """Per resolution, algorithm and noise: mean IoU and largest |height error| per distance bin."""
    summary: dict = {}
    for label, noises in accuracy.items():
        for noise_name, algorithms in noises.items():
            for algorithm, objects in algorithms.items():
                key = f'{algorithm} {noise_name}' if algorithm == 'elevation' else algorithm
                rows = summary.setdefault(label, {}).setdefault(key, {})
                for low, high in BINS:
                    names = [n for n, (_, _, d) in truths.items() if low <= d < high]
                    if not names:
                        continue
                    errors = [
                        abs(objects[n]['height_error'])
                        for n in names
                        if objects[n]['height_error'] is not None
                    ]
                    rows[f'{low:g}-{high:g} m'] = {
                        'iou': statistics.fmean(objects[n]['iou'] for n in names),
                        'height_error': max(errors) if errors else None,
                    }
    return summary


def describe(accuracy, summary, timings, truths) -> str:
    text = (
        'Footprint IoU with the true footprint (1 is perfect) and height error of each box, a camera '
        '3 m up looking straight down; `elevation` on perfect depth and on two simulated sensors '
        '(`kinect`: `depth_noise: true`; `twice`: twice its error, 3-pixel holes at edges), '
        "`foreground` and `colour` (the boxes' colour model: its outline met with the floor, the "
        "paper's answer, and lifted with perfect depth) on the same colour image. The rays of a "
        'camera are worked out on its first frame (about 40 ms at 800×600) and kept.\n\n'
    )
    for label, noises in accuracy.items():
        rows = []
        for name, (_, height, distance) in sorted(truths.items(), key=lambda item: item[1][2]):
            row = [name, f'{height:g}', f'{distance:.2f}']
            for noise_name in NOISES:
                found = noises[noise_name]['elevation'][name]
                error = found['height_error']
                row += [found['iou'], '—' if error is None else f'{error * 100:+.1f}']
            row += [
                noises['none'][other][name]['iou'] for other in ('foreground', 'colour', 'colour with depth')
            ]
            rows.append(row)
        header = ['box', 'height m', 'from centre m']
        for noise_name in NOISES:
            header += [f'elevation IoU ({noise_name})', f'height error cm ({noise_name})']
        header += ['foreground IoU', 'colour IoU', 'colour with depth IoU']
        text += f'At {label}:\n\n' + table(header, rows) + '\n'
    text += 'Mean IoU by distance from the point below the camera:\n\n'
    for label, algorithms in summary.items():
        bins = list(next(iter(algorithms.values())))
        rows = [[key, *(algorithms[key][b]['iou'] for b in bins)] for key in algorithms]
        text += f'{label}:\n\n' + table(['algorithm', *bins], rows) + '\n'
    rows = []
    for label, times in timings.items():
        rows.append(
            [
                label,
                times['colour']['p50'],
                times['elevation']['p50'],
                times['elevation_noisy']['p50'],
                times['foreground']['p50'],
                times['elevation']['p50'] / times['colour']['p50'],
            ]
        )
    text += 'Time per frame, segment + project, ms (p50 CPU time, one thread):\n\n'
    text += table(
        ['resolution', 'colour', 'elevation', 'elevation (kinect depth)', 'foreground', 'elevation / colour'],
        rows,
    )
    return text


def plot(ctx: Context, summary) -> str:
    fig, axes, name = figure(ctx, f'{NAME}-iou')
    label = _label(RESOLUTIONS[-1])
    algorithms = summary[label]
    bins = list(next(iter(algorithms.values())))
    positions = np.arange(len(bins))
    width = 0.8 / len(algorithms)
    for i, (key, rows) in enumerate(algorithms.items()):
        axes.bar(positions + i * width, [rows[b]['iou'] for b in bins], width, label=key)
    axes.set_xticks(positions + 0.4 - width / 2, bins)
    axes.set_xlabel('distance of the box from the point below the camera')
    axes.set_ylabel(f'mean footprint IoU at {label}')
    axes.set_ylim(0, 1)
    axes.legend(fontsize='small')
    return save(ctx, fig, name)
