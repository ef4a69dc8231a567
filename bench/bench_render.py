"""What one vision-system frame costs: TinyRenderer at several resolutions, then outline projection.

    .venv/bin/python bench/bench_render.py [WORLD]

Prints, per resolution, the median time of a render and of locate_objects (segment,
lift with depth, clip) on it, and how a burst of simultaneous requests shares one
frame through the FrameCache (renders per request). Timings vary with the machine
and its load; compare ratios, not absolute numbers.
"""

import statistics
import sys
import threading
import time

from drvs.algorithms import parse_algorithm
from drvs.camera import PinholeCamera
from drvs.scene import Scene
from drvs.vision import FrameCache, locate_objects
from drvs.world import load_world

RESOLUTIONS = [(160, 120), (480, 360), (800, 600), (1280, 960)]
REPEATS = 7


def median_time(function, repeats=REPEATS):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main(path='test/worlds/accuracy.yaml'):
    world = load_world(path)
    model = parse_algorithm(world.colour_models['obstacle'])
    region = (0.0, 0.0, *world.floor_size)
    config = world.vision_systems[0]
    with Scene(world) as scene:
        print(f'{"resolution":>12} {"render ms":>10} {"locate ms":>10} {"objects":>8}')
        for resolution in RESOLUTIONS:
            camera = PinholeCamera.from_config(config, resolution)
            frame = scene.render(camera)
            render = median_time(lambda camera=camera: scene.render(camera))
            locate = median_time(lambda frame=frame: locate_objects(frame, model, region))
            found = len(locate_objects(frame, model, region))
            size = f'{resolution[0]}x{resolution[1]}'
            print(f'{size:>12} {render * 1e3:>10.1f} {locate * 1e3:>10.1f} {found:>8}')

        camera = PinholeCamera.from_config(config)
        cache = FrameCache(lambda stamp: scene.render(camera, stamp), max_age=0.1, clock=time.monotonic)
        barrier = threading.Barrier(10)

        def request():
            barrier.wait()
            cache.get(time.monotonic())

        threads = [threading.Thread(target=request) for _ in range(10)]
        start = time.perf_counter()
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        elapsed = time.perf_counter() - start
        print(
            f'10 simultaneous requests at {camera.width}x{camera.height}: {cache.renders} render(s), '
            f'{cache.hits} cache hit(s), {elapsed * 1e3:.0f} ms in all'
        )


if __name__ == '__main__':
    main(*sys.argv[1:])
