"""Vision: what a request costs a vision system, stage by stage, and how far its outlines are from the truth.

Per request, at 320×240, 640×480, 800×600 and 1280×960, per algorithm:

- capture, ``render``: :meth:`drvs.sim.scene.Scene.render` of the camera (PyBullet
  TinyRenderer), what a ``~source:=render`` vision system does for a new frame;
  ``topic``: what a ``~source:=topic`` one spends turning a camera message into a
  frame: deserialising a serialised sensor_msgs/Image (rgb8) of the rendered view,
  then :class:`drvs.ros.frame_sources.TopicSource`'s own conversion (cv_bridge, the
  CameraInfo model, the tf lookup of the camera's pose); also for the
  CompressedImage (JPEG quality 80) a camera driver would publish beside it.
- segment: the algorithm's ``detect`` (image → pixel outlines); for motion also
  ``observe`` of the new frame, which the request path does when the stream has not.
- project: :func:`drvs.vision.pipeline.project_objects` and :func:`drvs.vision.pipeline.in_region`
  (pixel outlines → floor polygons in ``map``, lifted with the depth image, clipped
  to the region: the whole floor). Segment then project is exactly
  :func:`drvs.vision.pipeline.locate_labelled`.

Scenes: colour on ``test/worlds/accuracy.yaml`` seen by vs1 (the obstacle model:
three boxes, one tall, one turned); apriltag on ``worlds/tags.yaml`` (vs2 sees the
robot's tag, vs1 the station's); motion on ``worlds/tags.yaml``'s vs1 with the walker
walking its waypoints at its speed, one frame every 0.2 s (the motion algorithm's
stream rate), on a model warmed up on the frames before. Times are p50 over the
repeats of the CPU time of the thread doing the work, with OpenCV held to that one
thread for the section: a request's own cost, which other load on a shared machine
inflates far less than wall time. In a vision system OpenCV may spread some of it
over both cores, so on an idle machine its wall time is at most this.

Localisation error: the colour outlines of the bodies vs1 sees whole (the three
boxes and the robot) against their true footprints from the world file (centroid
distance, Hausdorff distance of the outline), and each tag's centre and heading
(:func:`drvs.algorithms.apriltag.tag_pose`) against its body's pose, per resolution.

Also, as bench_render.py did: how many renders 10 simultaneous requests cost
through :class:`drvs.vision.pipeline.FrameCache` (one, shared).
"""

from __future__ import annotations

import io
import math
import statistics
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from shapely.geometry import Polygon

from bench.common import Context, Section, figure, save, spread, table, target
from drvs.algorithms import load_algorithms, parse_algorithm
from drvs.algorithms.apriltag import tag_pose
from drvs.algorithms.motion import STREAM_RATE, Motion
from drvs.sim.scene import Scene
from drvs.sim.simulation import loop_of, position_on_loop
from drvs.sim.world_file import load_world
from drvs.vision.camera import PinholeCamera
from drvs.vision.pipeline import FrameCache, in_region, project_objects

NAME = 'vision'
TITLE = 'Vision: time per request by stage, and localisation error'
RESOLUTIONS = ((320, 240), (640, 480), (800, 600), (1280, 960))
TARGET_RESOLUTION = (800, 600)
TARGET_MS = 5.0
REPO = Path(__file__).resolve().parents[1]
COLOUR_WORLD = REPO / 'test' / 'worlds' / 'accuracy.yaml'
TAG_WORLD = REPO / 'worlds' / 'tags.yaml'
JPEG_QUALITY = 80
ALGORITHMS = ('colour', 'apriltag', 'motion')


def _ms(seconds: list[float]) -> dict:
    return spread([s * 1e3 for s in seconds])


def _label(resolution) -> str:
    return f'{resolution[0]}×{resolution[1]}'


clock = time.thread_time
"""Every stage runs in the calling thread (OpenCV is held to it, see :func:`run`)."""


def time_calls(function, repeats: int) -> tuple[list[float], object]:
    """CPU seconds of ``repeats`` calls of ``function``, and what the last one returned."""
    times, result = [], None
    for _ in range(repeats):
        start = clock()
        result = function()
        times.append(clock() - start)
    return times, result


def time_request(frame, detect, region) -> tuple[float, float, list]:
    """(segment s, project s, (outline, label, confidence) found) of one request on ``frame``."""
    t0 = clock()
    pixel_objects = detect(frame)
    t1 = clock()
    found = in_region(project_objects(frame, pixel_objects), region)
    return t1 - t0, clock() - t1, found


def stages(segment: list[float], project: list[float], capture: list[float], found: int) -> dict:
    return {
        'capture_ms': _ms(capture),
        'segment_ms': _ms(segment),
        'project_ms': _ms(project),
        'segment_project_ms': _ms([s + p for s, p in zip(segment, project, strict=True)]),
        'objects': found,
    }


# -- colour ------------------------------------------------------------------------------------
def colour(ctx: Context, resolutions, repeats: int, renders: int) -> tuple[dict, dict, dict, dict]:
    """Stages, localisation errors, frames and frame sharing (:func:`frame_sharing`, at the target
    resolution) of the colour algorithm on the accuracy world."""
    world = load_world(COLOUR_WORLD)
    region = (0.0, 0.0, *world.floor_size)
    obstacle = parse_algorithm(world.colour_models['obstacle'])
    view = Polygon(PinholeCamera.from_config(world.vision_systems[0]).floor_footprint(world.floor_size))
    bodies = {  # by colour model, the bodies vs1 sees whole (not the station: out of its view)
        role: [body for body in role_bodies if view.contains(Polygon(body.footprint()))]
        for role, role_bodies in (
            ('self', [world.robot]),
            ('station', [world.station]),
            ('obstacle', list(world.objects)),
        )
    }
    timings, errors, frames = {}, {}, {}
    sharing_at = TARGET_RESOLUTION if TARGET_RESOLUTION in resolutions else resolutions[-1]
    with Scene(world) as scene:
        for resolution in resolutions:
            label = _label(resolution)
            ctx.progress(f'vision: colour {label}')
            camera = PinholeCamera.from_config(world.vision_systems[0], resolution)
            capture, frame = time_calls(lambda camera=camera: scene.render(camera), renders)
            frames[label] = frame
            segment, project = [], []
            for _ in range(repeats):
                s, p, found = time_request(frame, obstacle.detect, region)
                segment.append(s)
                project.append(p)
            threshold, _ = time_calls(lambda frame=frame: obstacle.params.mask(frame.rgb), repeats)
            timings[label] = stages(segment, project, capture, len(found))
            timings[label]['in_range_ms'] = _ms(threshold)
            errors[label] = colour_errors(frame, world, bodies, region)
            if resolution == sharing_at:
                ctx.progress(f'vision: 10 simultaneous requests at {label}')
                sharing = frame_sharing(scene, camera)
                sharing['one_render_ms'] = timings[label]['capture_ms']['p50']
    return timings, errors, frames, sharing


def colour_errors(frame, world, bodies: dict, region) -> dict:
    """Per body: centroid and Hausdorff distance (m) of its located outline from its true footprint."""
    found = {}
    for role, role_bodies in bodies.items():
        algorithm = parse_algorithm(world.colour_models[role])
        outlines = [
            Polygon(o) for o, *_ in in_region(project_objects(frame, algorithm.detect(frame)), region)
        ]
        for body in role_bodies:
            truth = Polygon(body.footprint())
            seen = [o for o in outlines if o.intersects(truth)]
            if not seen:
                found[body.name] = None
                continue
            best = max(seen, key=lambda o: o.intersection(truth).area)
            found[body.name] = {
                'centroid_m': best.centroid.distance(truth.centroid),
                'hausdorff_m': best.hausdorff_distance(truth),
                'iou': best.intersection(truth).area / best.union(truth).area,
            }
    return found


# -- apriltag ----------------------------------------------------------------------------------


def apriltag(ctx: Context, resolutions, repeats: int, renders: int) -> tuple[dict, dict]:
    """Stages (vs2, the robot's tag in view) and tag pose errors (each tag from the camera that
    sees it whole) on the tags world."""
    world = load_world(TAG_WORLD)
    region = (0.0, 0.0, *world.floor_size)
    algorithm = parse_algorithm('apriltag:tag36h11', load_algorithms(tag_heights=world.tag_heights()))
    views = {'vs2': world.robot, 'vs1': world.station}
    timings, errors = {}, {}
    with Scene(world) as scene:
        for resolution in resolutions:
            label = _label(resolution)
            ctx.progress(f'vision: apriltag {label}')
            errors[label] = {}
            for name, body in views.items():
                camera = PinholeCamera.from_config(world.camera(name), resolution)
                if name == 'vs2':
                    capture, frame = time_calls(lambda camera=camera: scene.render(camera), renders)
                else:
                    frame = scene.render(camera)
                if name == 'vs2':
                    segment, project = [], []
                    for _ in range(repeats):
                        s, p, found = time_request(frame, algorithm.detect, region)
                        segment.append(s)
                        project.append(p)
                    timings[label] = stages(segment, project, capture, len(found))
                else:
                    found = in_region(project_objects(frame, algorithm.detect(frame)), region)
                errors[label][body.name] = tag_error(found, body)
    return timings, errors


def tag_error(found, body) -> dict | None:
    """Centre (m) and heading (degrees) error of ``body``'s tag among ``found``; None when not found."""
    label = f'{body.tag.family}:{body.tag.id}'
    outlines = [outline for outline, found_label, *_ in found if found_label == label]
    if not outlines:
        return None
    x, y, yaw = tag_pose(outlines[0])
    heading = math.degrees((yaw - body.yaw + math.pi) % (2 * math.pi) - math.pi)
    return {'centre_m': math.dist((x, y), body.position), 'heading_deg': abs(heading)}


# -- motion ------------------------------------------------------------------------------------
def motion(ctx: Context, resolutions, warm_up: int, repeats: int) -> dict:
    """Stages of the motion algorithm on a warm model while the walker walks (vs1 of the tags world)."""
    world = load_world(TAG_WORLD)
    region = (0.0, 0.0, *world.floor_size)
    walker = next(body for body in world.objects if body.kind == 'human')
    walk = loop_of(walker.position, walker.waypoints)
    timings = {}
    with Scene(world) as scene:
        for resolution in resolutions:
            label = _label(resolution)
            ctx.progress(f'vision: motion {label}')
            camera = PinholeCamera.from_config(world.camera('vs1'), resolution)
            algorithm = Motion()
            params = algorithm.parse('')
            capture, segment, project = [], [], []
            found = []
            for index in range(warm_up + repeats):
                stamp = index / STREAM_RATE
                # There and back again (closed), so that it is still walking in the last frames.
                x, y = position_on_loop(walk, walker.speed, stamp, closed=True)
                scene.set_pose(walker.name, x, y, walker.yaw)
                start = clock()
                frame = scene.render(camera, stamp)
                rendered = clock() - start
                if index < warm_up:
                    algorithm.observe(frame)
                    continue

                def detect(frame, algorithm=algorithm, params=params):
                    algorithm.observe(frame)  # a frame the stream has not seen: learnt, then judged
                    return algorithm.detect(frame, params)

                s, p, found = time_request(frame, detect, region)
                capture.append(rendered)
                segment.append(s)
                project.append(p)
            timings[label] = stages(segment, project, capture, len(found))
    return timings


# -- topic capture -----------------------------------------------------------------------------
def topic(ctx: Context, frames: dict, repeats: int) -> dict:
    """Per resolution: ms to turn a serialised Image (and a CompressedImage) into a frame, as
    TopicSource does on receipt, deserialisation included."""
    import rospy
    import tf2_ros
    from sensor_msgs.msg import CompressedImage, Image
    from std_msgs.msg import Header

    from drvs.ros.frame_sources import TopicSource, _Received
    from drvs.ros.sim_camera import camera_info_message, compressed_message, image_message
    from drvs.ros.tf_frames import camera_transform
    from drvs.sim.scene import TINY_RENDERER_SAMPLE
    from drvs.vision.optics import intrinsics_of

    results = {}
    for label, frame in frames.items():
        ctx.progress(f'vision: topic {label}')
        camera = frame.camera
        frame_id = 'bench_optical_frame'
        header = Header(stamp=rospy.Time(1, 0), frame_id=frame_id)
        params = SimpleNamespace(
            max_frame_age=1.0,
            frame_timeout=1.0,
            stale_after=2.0,
            compressed=False,
            depth=False,
            map_frame='map',
            tf_timeout=0.0,  # the pose is in the buffer already: no waiting
        )
        source = TopicSource(params, count=lambda **_: None)
        source.tf_buffer = tf2_ros.Buffer(debug=False)  # no ~tf2_frames service: no node here
        source.tf_buffer.set_transform_static(camera_transform(camera, frame_id, rospy.Time(0)), 'bench')
        info = camera_info_message(
            intrinsics_of(camera, TINY_RENDERER_SAMPLE), (0.0,) * 5, camera.width, camera.height, header
        )
        source._on_info(info)
        result = {}
        for kind, message, message_type in (
            ('raw', image_message(frame.rgb, 'rgb8', header), Image),
            ('jpeg', compressed_message(frame.rgb, header, 'jpeg', JPEG_QUALITY), CompressedImage),
        ):
            buffer = io.BytesIO()
            message.serialize(buffer)
            data = buffer.getvalue()

            def receive(data=data, message_type=message_type, info=info, source=source):
                received = message_type().deserialize(data)
                return source._frame_of(_Received(received, None, info))

            converted = receive()
            if converted.rgb.shape != frame.rgb.shape:
                raise RuntimeError(
                    f'topic {kind} {label}: frame {converted.rgb.shape}, sent {frame.rgb.shape}'
                )
            result[kind] = {'ms': _ms(time_calls(receive, repeats)[0]), 'bytes': len(data)}
        results[label] = result
    return results


def frame_sharing(scene: Scene, camera: PinholeCamera, requests: int = 10) -> dict:
    """``requests`` simultaneous requests on one :class:`drvs.vision.pipeline.FrameCache`: the renders they
    cost, and the wall time until the last has its frame."""
    cache = FrameCache(lambda stamp: scene.render(camera, stamp), max_age=0.1, clock=time.monotonic)
    barrier = threading.Barrier(requests)

    def request():
        barrier.wait()
        cache.get(time.monotonic())

    threads = [threading.Thread(target=request) for _ in range(requests)]
    start = time.perf_counter()
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return {
        'resolution': _label((camera.width, camera.height)),
        'requests': requests,
        'renders': cache.renders,
        'hits': cache.hits,
        'all_ms': (time.perf_counter() - start) * 1e3,
    }


# -- the section -------------------------------------------------------------------------------
def run(ctx: Context) -> Section:
    import cv2

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # all of OpenCV's work in the thread whose CPU time is measured
    try:
        return measure(ctx)
    finally:
        cv2.setNumThreads(threads)


def measure(ctx: Context) -> Section:
    resolutions = ctx.pick(RESOLUTIONS[:1], RESOLUTIONS, RESOLUTIONS)
    repeats = ctx.pick(3, 30, 100)
    renders = ctx.pick(1, 3, 7)
    colour_times, colour_error, frames, sharing = colour(ctx, resolutions, repeats, renders)
    tag_times, tag_errors = apriltag(ctx, resolutions, ctx.pick(2, 8, 30), ctx.pick(1, 1, 5))
    motion_times = motion(ctx, resolutions, warm_up=ctx.pick(3, 3, 8), repeats=ctx.pick(2, 3, 12))
    topic_times = topic(ctx, frames, ctx.pick(2, 10, 30))
    timings = {'colour': colour_times, 'apriltag': tag_times, 'motion': motion_times}

    target_label = _label(TARGET_RESOLUTION)
    if target_label in colour_times:
        value = colour_times[target_label]['segment_project_ms']['p50']
        objective = target(value, TARGET_MS)
    else:
        value = None
        objective = target(None, TARGET_MS, note=f'{target_label} is not measured at size {ctx.size}')

    markdown = describe(resolutions, timings, topic_times, colour_error, tag_errors, sharing, value)
    plots = [
        plot_stages(ctx, resolutions, timings, topic_times),
        plot_errors(ctx, resolutions, colour_error, tag_errors),
    ]
    return Section(
        NAME,
        TITLE,
        results={
            'stages': timings,
            'topic_capture': topic_times,
            'colour_error': colour_error,
            'tag_error': tag_errors,
            'frame_sharing': sharing,
        },
        targets={'segment_project_800x600_ms': objective},
        markdown=markdown,
        plots=plots,
    )


def _mm(value) -> str:
    return '—' if value is None else f'{value * 1e3:.1f}'


def describe(resolutions, timings, topic_times, colour_error, tag_errors, sharing, value) -> str:
    rows = []
    for algorithm in ALGORITHMS:
        for resolution in resolutions:
            label = _label(resolution)
            entry = timings[algorithm][label]
            topics = topic_times[label]
            rows.append(
                [
                    algorithm,
                    label,
                    entry['capture_ms']['p50'],
                    topics['raw']['ms']['p50'] if algorithm == 'colour' else '',
                    topics['jpeg']['ms']['p50'] if algorithm == 'colour' else '',
                    entry['segment_ms']['p50'],
                    entry['project_ms']['p50'],
                    entry['segment_project_ms']['p50'],
                    entry['objects'],
                ]
            )
    text = table(
        [
            'algorithm',
            'resolution',
            'capture: render ms',
            'topic Image ms',
            'topic JPEG ms',
            'segment ms',
            'project ms',
            'segment + project ms',
            'objects',
        ],
        rows,
    )
    target_label = _label(TARGET_RESOLUTION)
    if value is not None:
        anchor = timings['colour'][target_label]
        text += (
            f'\nColour at {target_label}: segment + project {value:.2f} ms (p50; target ≤ {TARGET_MS:g} ms) '
            f"next to the capture it follows, a render of {anchor['capture_ms']['p50']:.0f} ms "
            f"(ratio {value / anchor['capture_ms']['p50']:.2f}), and to the floor of any colour "
            f"segmentation, one cv2.inRange over the frame: {anchor['in_range_ms']['p50']:.2f} ms "
            f"(ratio {value / anchor['in_range_ms']['p50']:.1f}). "
        )
    text += (
        'Times are CPU ms of the thread serving the request (OpenCV held to it), p50: other load on '
        'the machine inflates them far less than wall time. '
        'Topic capture: a ~source:=topic vision system deserialising the camera\'s message and making '
        'the frame (cv_bridge, CameraInfo, tf), for the raw rgb8 Image and for JPEG 80; the render '
        'column is the simulation\'s own camera. Segment is the algorithm\'s detect (motion: learning '
        'the frame too), project is lifting the outlines with depth onto the floor and clipping them '
        'to the region. '
        f"{sharing['requests']} simultaneous requests at {sharing['resolution']} shared "
        f"{sharing['renders']} render(s) ({sharing['hits']} cache hits): {sharing['all_ms']:.0f} ms in all, "
        f"one render {sharing['one_render_ms']:.0f} ms (FrameCache).\n\n"
    )
    rows = []
    for resolution in resolutions:
        label = _label(resolution)
        errors = [e for e in colour_error[label].values() if e is not None]
        centroid = [e['centroid_m'] for e in errors]
        hausdorff = [e['hausdorff_m'] for e in errors]
        tags = tag_errors[label]
        rows.append(
            [
                label,
                f'{len(errors)}/{len(colour_error[label])}',
                _mm(statistics.median(centroid)) if centroid else '—',
                _mm(max(centroid)) if centroid else '—',
                _mm(statistics.median(hausdorff)) if hausdorff else '—',
                _mm(max(hausdorff)) if hausdorff else '—',
                *(
                    '—'
                    if tags[name] is None
                    else f"{_mm(tags[name]['centre_m'])} / {tags[name]['heading_deg']:.1f}°"
                    for name in tags
                ),
            ]
        )
    tag_names = list(next(iter(tag_errors.values())))
    text += table(
        [
            'resolution',
            'colour bodies found',
            'centroid mm (median)',
            'centroid mm (max)',
            'Hausdorff mm (median)',
            'Hausdorff mm (max)',
            *(f'tag on {name}: centre mm / heading' for name in tag_names),
        ],
        rows,
    )
    text += (
        '\nLocalisation error against the world file: the colour outlines (vs1 of the accuracy world: '
        'the three boxes and the robot, the bodies it sees whole) against their true footprints, and '
        "each tag's centre and heading (worlds/tags.yaml; — = not found) against its body's pose.\n\n"
        'Again: `make bench` or `.venv/bin/python -m bench.run --only vision`.\n'
    )
    return text


def plot_stages(ctx: Context, resolutions, timings, topic_times) -> str:
    fig, axes, name = figure(ctx, 'vision-stages')
    pixels = [w * h / 1e6 for w, h in resolutions]
    labels = [_label(r) for r in resolutions]
    axes.plot(
        pixels, [timings['colour'][k]['capture_ms']['p50'] for k in labels], 'k-o', label='capture: render'
    )
    axes.plot(
        pixels, [topic_times[k]['raw']['ms']['p50'] for k in labels], 'k--s', label='capture: topic Image'
    )
    axes.plot(
        pixels, [topic_times[k]['jpeg']['ms']['p50'] for k in labels], 'k:^', label='capture: topic JPEG'
    )
    for algorithm, colour_name in zip(ALGORITHMS, ('tab:blue', 'tab:orange', 'tab:green'), strict=True):
        for stage, style in (('segment', '-'), ('project', '--')):
            values = [timings[algorithm][k][f'{stage}_ms']['p50'] for k in labels]
            axes.plot(pixels, values, style, color=colour_name, marker='o', label=f'{algorithm}: {stage}')
    axes.axhline(
        TARGET_MS, color='red', linewidth=0.8, label=f'target: colour segment + project {TARGET_MS:g} ms'
    )
    axes.set_xscale('log')
    axes.set_yscale('log')
    axes.set_xticks(pixels, labels)
    axes.minorticks_off()
    axes.set_xlabel('resolution')
    axes.set_ylabel('ms per request (p50)')
    axes.legend(fontsize='x-small', ncol=2)
    return save(ctx, fig, name)


def plot_errors(ctx: Context, resolutions, colour_error, tag_errors) -> str:
    fig, axes, name = figure(ctx, 'vision-error')
    pixels = [w * h / 1e6 for w, h in resolutions]
    labels = [_label(r) for r in resolutions]
    bodies = list(colour_error[labels[0]])
    for body in bodies:
        values = [
            colour_error[k][body]['centroid_m'] * 1e3 if colour_error[k][body] else np.nan for k in labels
        ]
        axes.plot(pixels, values, '-o', label=f'colour {body}: centroid')
        values = [
            colour_error[k][body]['hausdorff_m'] * 1e3 if colour_error[k][body] else np.nan for k in labels
        ]
        axes.plot(
            pixels,
            values,
            ':',
            marker='.',
            color=axes.lines[-1].get_color(),
            label=f'colour {body}: Hausdorff',
        )
    for body in tag_errors[labels[0]]:
        values = [tag_errors[k][body]['centre_m'] * 1e3 if tag_errors[k][body] else np.nan for k in labels]
        axes.plot(pixels, values, '--s', label=f'tag on {body}: centre')
    axes.set_xscale('log')
    axes.set_xticks(pixels, labels)
    axes.minorticks_off()
    axes.set_xlabel('resolution')
    axes.set_ylabel('error against the world file, mm')
    axes.legend(fontsize='x-small', ncol=2)
    return save(ctx, fig, name)
