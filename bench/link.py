"""A robot on a constrained link: DRVS against image sharing over the same 2 Mbit/s.

DRVS side: ``worlds/crossing.yaml`` run by ``scripts/run_scenario.sh --hosts --robot-link
2mbit`` (every part on a network host of its own, robot1's link limited to 2 Mbit/s both
ways by a tc token bucket), the robots on their default watches. Measured: whether robot1
reaches its station and when, its callbacks' bytes per second (summary.json), and the
bytes per second its link carried, counted by the kernel on the robot host's eth0
(sampled every half second: every header and every other topic of the robot included).

Image-sharing side: the same kind of hosts made here (a master host, a camera host, a
robot host with the same 2 Mbit/s bucket); ``bench/nodes/image_camera.py`` streams, at
10 Hz each, a sensor_msgs/CompressedImage (JPEG quality 80, 800×600) for every camera
robot1 would need (those whose floor footprint meets the box from robot1 to its station:
all four in this world), and ``bench/nodes/image_robot.py`` on the robot host subscribes
to them without decoding (``_segment:=false``: the link is measured, not the robot's
CPU, which the ``wire`` section measures). Measured over a window after a warm-up:
frames per second per camera, latency (arrival - header.stamp, one kernel clock) p50 and
p99, and the bytes per second on the robot's eth0. Frames: the natural photograph
``scipy.misc.face()`` (Debian's python3-scipy ships it; 1024×768 scaled to 800×600) at
every size, and also each camera's rendered 800×600 view of the world at ``full``.

Sizes: ``tiny`` runs the image side only (photo, a 1.5 s window; the DRVS column is a
canned row, not a measurement); ``quick`` runs the scenario and the photo (a 6 s window);
``full`` the scenario, the photo and the rendered views (30 s windows). The watch run is
left in this section's work folder, where the ``fleet`` section takes it at ``quick``.
Without network namespaces (not root) nothing can be limited: the section says why.
"""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path

import cv2

from bench.common import Context, Section, figure, save, spread, table
from bench.fleet import FIXTURE_NOT_A_MEASUREMENT, ROBOT_LINK, link_counters, run_to_arrival, scenario_options
from drvs.sim.world_file import load_world
from drvs.testing.harness import REPO, RosHarness, read_json_lines, wait_for
from drvs.testing.netns import NetworkHosts, unavailable
from drvs.vision.camera import PinholeCamera

NAME = 'link'
TITLE = 'A robot on a 2 Mbit/s link: DRVS against image sharing'
WORLD = 'worlds/crossing.yaml'
LINK_BYTES_PER_S = 2e6 / 8  # the bucket's rate (tc's mbit is 10^6 bit)
CAMERA_RATE = 10.0  # frames per second each camera would serve
FRAME_SIZE = (800, 600)
QUALITY = 80
NODES = REPO / 'bench' / 'nodes'


def needed_cameras(world_path: str, robot: str) -> list[str]:
    """The cameras whose floor footprint meets the box from ``robot``'s start to its station."""
    from shapely.geometry import Polygon, box

    world = load_world(REPO / world_path)
    fleet_robot = world.fleet_robot(robot)
    (x0, y0), (x1, y1) = fleet_robot.body.position, fleet_robot.station.position
    route = box(min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1))
    names = []
    for camera in world.vision_systems:
        footprint = PinholeCamera.from_config(camera).floor_footprint(world.floor_size)
        if footprint and Polygon(footprint).intersects(route):
            names.append(camera.name)
    return names


def natural_photo(path: Path) -> Path:
    """scipy's raccoon face (1024×768, Debian python3-scipy), scaled to 800×600, as a PNG."""
    from scipy import misc

    with warnings.catch_warnings():
        warnings.simplefilter('ignore', DeprecationWarning)  # moved to scipy.datasets (a download) in 1.10
        rgb = misc.face()
    bgr = cv2.resize(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), FRAME_SIZE, interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(path), bgr)
    return path


# -- image sharing on a limited link -------------------------------------------------------------
def image_sharing(ctx: Context, cameras: list[str], kind: str, warmup: float, window: float) -> dict:
    """Stream ``cameras`` JPEG frames at CAMERA_RATE to a robot host on a limited link; measure it.

    ``kind`` is ``photo`` or ``rendered``. Returns frames/s per camera, latency and link bytes/s
    over ``window`` seconds after the first frame of every camera plus ``warmup`` seconds.
    """
    frames_path = ctx.work_dir / f'frames-{kind}.jsonl'
    frames_path.unlink(missing_ok=True)
    if kind == 'photo':
        source = f'_image:={natural_photo(ctx.work_dir / "photo-800x600.png")}'
    else:
        source = f'_world:={REPO / WORLD}'
    with NetworkHosts() as hosts, RosHarness() as ros:
        ctx.progress(f'link: image sharing ({kind}): making hosts')
        master_ip = hosts.add('master')
        hosts.add('cameras')
        hosts.add('robot')
        hosts.limit('robot', ROBOT_LINK)
        env = {'ROS_MASTER_URI': f'http://{master_ip}:11311/'}
        ros.spawn('rosmaster', [*hosts.command('master'), 'rosmaster', '--core', '-p', '11311'], env=env)
        camera_argv = [
            *hosts.command('cameras'),
            sys.executable,
            str(NODES / 'image_camera.py'),
            '__name:=cams',
        ]
        camera_argv += [f'_cameras:={",".join(cameras)}', f'_rate:={CAMERA_RATE:g}', f'_quality:={QUALITY}']
        camera_argv += [f'_width:={FRAME_SIZE[0]}', f'_height:={FRAME_SIZE[1]}', source]
        camera_node = ros.spawn('image_camera', camera_argv, env=env)
        topics = ','.join(f'/cams/{camera}/image/compressed' for camera in cameras)
        robot_argv = [
            *hosts.command('robot'),
            sys.executable,
            str(NODES / 'image_robot.py'),
            '__name:=image_robot',
        ]
        robot_argv += [f'_topics:={topics}', f'_out:={frames_path}', '_segment:=false']
        robot_node = ros.spawn('image_robot', robot_argv, env=env)
        ctx.progress(f'link: image sharing ({kind}): waiting for a frame of each camera')

        def every_camera_arrived():
            for node in (camera_node, robot_node):
                if not node.running():
                    raise RuntimeError(f'{node.name} exited early\n{node.describe()}')
            if not frames_path.exists():
                return False
            return {frame['camera'] for frame in read_json_lines(frames_path)} >= set(topics.split(','))

        wait_for(every_camera_arrived, 60.0, 'a frame of every camera on the robot host', 0.2, ros.describe)
        ctx.progress(f'link: image sharing ({kind}): {warmup:g} s warm-up, {window:g} s measured')
        time.sleep(warmup)  # a measurement interval, not a wait for a condition
        namespace = hosts.namespace('robot')
        start, counters_start = time.time(), link_counters(namespace)
        time.sleep(window)
        end, counters_end = time.time(), link_counters(namespace)
        camera_line = [line for line in camera_node.log(tail=200).splitlines() if 'JPEG' in line][-1:]
    frames = [frame for frame in read_json_lines(frames_path) if start <= frame['received'] < end]
    per_camera = {}
    for topic, camera in zip(topics.split(','), cameras, strict=True):
        mine = [frame for frame in frames if frame['camera'] == topic]
        per_camera[camera] = {
            'frames_per_s': len(mine) / window,
            'latency_p50': spread([f['latency'] for f in mine])['p50'],
        }
    latencies = [frame['latency'] for frame in frames]
    counted = counters_start is not None and counters_end is not None
    received = (counters_end[0] - counters_start[0]) / window if counted else None
    sent = (counters_end[1] - counters_start[1]) / window if counted else None
    return {
        'kind': kind,
        'cameras': cameras,
        'offered_frames_per_s_per_camera': CAMERA_RATE,
        'frame_bytes': spread([frame['bytes'] for frame in frames])['p50'] if frames else None,
        'window_s': window,
        'frames': len(frames),
        'frames_per_s_per_camera': len(frames) / window / len(cameras),
        'per_camera': per_camera,
        'latency': spread(latencies),
        'link_rx_bytes_per_s': received,
        'link_tx_bytes_per_s': sent,
        'jpeg_bytes_per_s': sum(frame['bytes'] for frame in frames) / window,
        'camera_log': camera_line,
        'series': [(round(f['received'] - start, 3), round(f['latency'], 4)) for f in frames],
    }


# -- DRVS on the same link -----------------------------------------------------------------------
def drvs_side(ctx: Context, timeout: float) -> dict:
    """The crossing scenario with robot1 on the limited link; its row and its link's bytes/s."""
    options = scenario_options()
    run = run_to_arrival(ctx, WORLD, 'watch', options, timeout)
    result = {'code': run.code, 'wall_seconds': run.wall_seconds, 'options': options}
    result['failed_attempts'] = run.failed_attempts
    if run.summary is None:
        result['error'] = f'no summary.json (exit code {run.code})'
        result['log_tail'] = run.log_tail
        return result
    row = run.summary['robots'][0]
    result.update(robot_row(row))
    result['link'] = link_rates(run.link_samples)
    return result


def robot_row(row: dict) -> dict:
    elapsed = row.get('elapsed') or row['arrival']
    return {
        'robot': row['name'],
        'reached': row['reached'],
        'reason': row.get('reason') or row.get('state', ''),
        'arrival': row['arrival'],
        'requests': row['requests'],
        'callbacks': row['callbacks'],
        'callback_bytes': row['callback_bytes'],
        'callback_bytes_per_s': row['callback_bytes'] / elapsed if elapsed else None,
    }


def link_rates(samples: list) -> dict:
    """Mean bytes/s each way, and the peak received over about 1 s, from (s, rx, tx) samples.

    The span is the one in which the host sent anything (its robot ran): before it, the
    robot host only hears the bridge's broadcasts (ARP) while the other hosts start.
    """
    sending = [i for i in range(1, len(samples)) if samples[i][2] != samples[i - 1][2]]
    if not sending:
        return {'samples': len(samples)}
    first, last = samples[sending[0] - 1], samples[sending[-1]]
    span = last[0] - first[0]
    pairs = [(samples[i], samples[i + 2]) for i in range(sending[0] - 1, sending[-1] - 1)]
    peak = max(((b[1] - a[1]) / (b[0] - a[0]) for a, b in pairs), default=None)
    return {
        'samples': len(samples),
        'span_s': round(span, 2),
        'rx_bytes': last[1] - first[1],
        'tx_bytes': last[2] - first[2],
        'rx_bytes_per_s': (last[1] - first[1]) / span if span > 0 else None,
        'tx_bytes_per_s': (last[2] - first[2]) / span if span > 0 else None,
        'peak_rx_bytes_per_s': peak,
    }


# -- the section ---------------------------------------------------------------------------------
def run(ctx: Context) -> Section:
    section = Section(NAME, TITLE)
    reason = unavailable()
    if reason:
        section.results['unavailable'] = reason
        section.markdown = (
            f'Not measured here: a limited link needs network hosts, and {reason}. '
            f'As root: `.venv/bin/python -m bench.run --only {NAME}`.\n'
        )
        return section
    cameras = needed_cameras(WORLD, 'robot1')
    section.results['cameras'] = cameras
    if ctx.size == 'tiny':
        drvs = robot_row(FIXTURE_NOT_A_MEASUREMENT['watch']['robots'][0]) | {'canned': True}
    else:
        ctx.progress('link: the crossing scenario, robot1 on 2 Mbit/s')
        drvs = drvs_side(ctx, timeout=ctx.pick(0, 90, 120))
    section.results['drvs'] = drvs
    warmup, window = ctx.pick(0.5, 1.5, 5.0), ctx.pick(1.5, 4.0, 30.0)
    streamed = ctx.pick(cameras[:1], cameras, cameras)  # tiny: one camera, to be quick
    images = {}
    for kind in ctx.pick(('photo',), ('photo',), ('photo', 'rendered')):
        images[kind] = image_sharing(ctx, streamed, kind, warmup, window)
    section.results['image_sharing'] = {
        kind: {k: v for k, v in r.items() if k != 'series'} for kind, r in images.items()
    }
    section.plots.append(plot(ctx, images))
    section.markdown = markdown(ctx, cameras, drvs, images)
    return section


def plot(ctx: Context, images: dict) -> str:
    fig, axes, name = figure(ctx, f'{NAME}-latency')
    for kind, result in images.items():
        series = result['series']
        axes.plot(
            [t for t, _ in series],
            [latency for _, latency in series],
            'o',
            ms=3,
            label=f'image sharing, {kind}',
        )
    axes.set_xlabel('seconds into the measured window')
    axes.set_ylabel('frame latency, s (arrival - header.stamp)')
    cameras = len(next(iter(images.values()))['cameras'])
    axes.set_title(f'{cameras} cameras at {CAMERA_RATE:g} Hz to a robot on {ROBOT_LINK}')
    axes.legend()
    return save(ctx, fig, name)


def _rate(value) -> str:
    if value is None:
        return '—'
    return f'{value / 1000:.1f} kB/s ({100 * value / LINK_BYTES_PER_S:.0f} % of 2 Mbit/s)'


def map_bytes(world_path: str) -> int:
    """The data of the robot's map message (one byte a cell) in this world, at its default grid."""
    from drvs.robot.mapping import grid_resolution

    width, height = load_world(REPO / world_path).floor_size
    resolution = grid_resolution((width, height))
    return round(width / resolution) * round(height / resolution)


def markdown(ctx: Context, cameras: list[str], drvs: dict, images: dict) -> str:
    kinds = list(images.values())
    columns = ['robot1 on a 2 Mbit/s link', 'DRVS (watches)'] + [f'image sharing, {kind}' for kind in images]
    link = drvs.get('link', {})
    if drvs.get('canned'):
        reached = 'canned row (tiny: no scenario run), not a measurement'
    elif 'error' in drvs:
        reached = f'not measured: {drvs["error"]}'
    else:
        reached = f'yes, after {drvs["arrival"]:.1f} s' if drvs['reached'] else f'no: {drvs["reason"]}'
    callbacks = drvs.get('callback_bytes_per_s')
    each = f', {drvs["callback_bytes"] / drvs["callbacks"]:.0f} B each' if drvs.get('callbacks') else ''
    rows = [
        ['reached its station', reached] + ['— (must still decode and segment)'] * len(kinds),
        ['what it receives', f'callbacks: outlines of itself, station, obstacles, people, robots{each}']
        + [
            f'JPEG q{QUALITY} {FRAME_SIZE[0]}×{FRAME_SIZE[1]}, {_kb(r["frame_bytes"])} a frame' for r in kinds
        ],
        ['frames/s per camera (offered)', '—']
        + [f'{r["frames_per_s_per_camera"]:.2f} ({CAMERA_RATE:g})' for r in kinds],
        ['latency p50 / p99', 'not recorded (the summary has no callback latency)']
        + [
            f'{r["latency"]["p50"]:.2f} s / {r["latency"]["p99"]:.2f} s (n {r["latency"]["n"]})'
            for r in kinds
        ],
        ['received on the link (eth0)', _rate(link.get('rx_bytes_per_s'))]
        + [_rate(r['link_rx_bytes_per_s']) for r in kinds],
        ['sent on the link (eth0)', _rate(link.get('tx_bytes_per_s'))]
        + [_rate(r['link_tx_bytes_per_s']) for r in kinds],
        ['payload received', f'callbacks {_kb(callbacks)}/s']
        + [f'JPEG {_kb(r["jpeg_bytes_per_s"])}/s (frames arrived in the window)' for r in kinds],
    ]
    streamed = len(kinds[0]['cameras'])
    text = ''
    if ctx.size == 'tiny':
        text += '**Tiny size: no scenario ran; the DRVS column is a canned row, not a measurement.**\n\n'
    text += (
        f'robot1 of `{WORLD}` would need cameras {", ".join(cameras)} (their floor footprints meet the '
        f'box from it to its station). DRVS: `scripts/run_scenario.sh {WORLD} --hosts --robot-link '
        f'{ROBOT_LINK}`, bytes counted by the kernel on the robot host\'s eth0 (every header and every '
        f'topic), peak received over about 1 s {_rate(link.get("peak_rx_bytes_per_s"))}. Image sharing: '
        f'the same hosts and bucket, {streamed} camera(s) streaming at {CAMERA_RATE:g} Hz to a '
        'subscriber that does not decode.\n\n'
    )
    for attempt in drvs.get('failed_attempts', []):
        text += (
            f'A DRVS run before this one failed ({attempt["why"]}; load average '
            f'{attempt["load_average"][0]}) and was run again.\n\n'
        )
    text += table(columns, rows) + '\n'
    text += (
        "The anchor is the link itself, filled by image sharing (its bytes/s is the bucket's rate): "
        'the robot gets a fraction of the frames, each late by the frames queued ahead of it in '
        "the publishers' connections. DRVS receives a few percent of it. What the DRVS robot "
        f'sends is mostly not DRVS: its map (nav_msgs/OccupancyGrid, {map_bytes(WORLD) / 1000:.0f} kB, '
        'at most once a second while it changes: `~map_period`; each change, before it, took '
        '19-30 % of the link) and path topics, to which the scenario recorder subscribes.\n\n'
    )
    text += f'Again: `make bench` or `.venv/bin/python -m bench.run --only {NAME} --size quick` (root).\n'
    return text


def _kb(value) -> str:
    return '—' if value is None else f'{value / 1000:.1f} kB'
