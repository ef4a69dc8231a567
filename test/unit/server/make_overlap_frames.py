"""Makes ``overlap_frames.json.gz``: what the fusion tracker gets from worlds/overlap.yaml's cameras.

The world's three people walk their loops (the robots parked in corners); every camera renders
each moment through the simulation's renderer (with its depth image, as the simulated vision
systems publish) and the vision system's own code finds the people's outlines on the floor
(:func:`drvs.vision.pipeline.locate_objects`). The four cameras take turns, each at ``RATE``
frames a second. Outlines are simplified to 1 cm and rounded to 1 mm. The file holds the frames
(camera, stamp, outlines) and where each person truly was at each frame's stamp.
``test_tracker_overlap.py`` replays it. Again::

    source scripts/env.sh && python test/unit/server/make_overlap_frames.py
"""

from __future__ import annotations

import gzip
import json
from pathlib import Path

from shapely.geometry import Polygon

from drvs.algorithms import parse_algorithm
from drvs.sim.scene import Scene
from drvs.sim.simulation import loop_of, position_on_loop
from drvs.sim.world_file import load_world
from drvs.testing.harness import REPO
from drvs.vision.camera import PinholeCamera
from drvs.vision.pipeline import locate_objects

SECONDS = 12.0
RATE = 5.0
"""Frames a second per camera: what the fused watcher's 0.2 s watches get."""
PARKED = {'robot1': (0.3, 0.3, 0.0), 'robot2': (0.3, 4.2, 0.0)}
FIXTURE = Path(__file__).with_name('overlap_frames.json.gz')


def frames(seconds: float = SECONDS, rate: float = RATE) -> dict:
    world = load_world(REPO / 'worlds' / 'overlap.yaml')
    people = [body for body in world.objects if body.kind == 'human']
    loops = {body.name: loop_of(body.position, body.waypoints) for body in people}
    cameras = [(c.name, PinholeCamera.from_config(c)) for c in world.vision_systems]
    algorithm = parse_algorithm(world.colour_models['human'])
    floor = (0.0, 0.0, *world.floor_size)
    found, truth = [], []
    with Scene(world) as scene:
        scene.apply_poses(PARKED)
        for k in range(round(seconds * rate)):
            for i, (name, camera) in enumerate(cameras):
                stamp = round((k + i / len(cameras)) / rate, 4)
                poses = {
                    b.name: (*position_on_loop(loops[b.name], b.speed, stamp, b.loop), 0.0) for b in people
                }
                scene.apply_poses(poses)
                outlines = [
                    [(round(x, 3), round(y, 3)) for x, y in Polygon(o).simplify(0.01).exterior.coords[:-1]]
                    for o in locate_objects(scene.render(camera, stamp), algorithm, floor)
                ]
                found.append({'camera': name, 'stamp': stamp, 'outlines': outlines})
                truth.append({n: [round(x, 4), round(y, 4)] for n, (x, y, _) in poses.items()})
    return {'world': 'worlds/overlap.yaml', 'rate': rate, 'frames': found, 'truth': truth}


if __name__ == '__main__':
    with gzip.open(FIXTURE, 'wt') as out:
        json.dump(frames(), out)
    print(f'wrote {FIXTURE}')
