"""The fusion tracker on real outlines: worlds/overlap.yaml's four tilted cameras, three people alike.

``overlap_frames.json.gz`` (made by ``make_overlap_frames.py``: rendered by the simulation, found
by the vision system's code) holds 12 s of every camera's frames while the people pass each other
at 0.6-1.2 m. A camera that sees two of them one behind the other finds one blob of both
(about a third of the frames): the tracker must not let it pull their tracks together, glue them
into one or start a ghost between them. Checked as the tracking bench measures it: each period's
fused outlines' centroids against where the people truly were.
"""

import gzip
import json
import math
from pathlib import Path

import pytest

from drvs.server.tracker import Observation, Tracker
from drvs.sim.world_file import load_world
from drvs.testing.harness import REPO
from drvs.vision.camera import PinholeCamera

FIXTURE = Path(__file__).with_name('overlap_frames.json.gz')
PERIOD = 0.2  # the fused watcher's


def centroid(outline):
    """The centroid of a polygon (shoelace)."""
    area = cx = cy = 0.0
    for (x0, y0), (x1, y1) in zip(outline, outline[1:] + outline[:1], strict=True):
        cross = x0 * y1 - x1 * y0
        area, cx, cy = area + cross, cx + (x0 + x1) * cross, cy + (y0 + y1) * cross
    return cx / (3 * area), cy / (3 * area)


@pytest.fixture(scope='module')
def replayed():
    """Each period: the people's true positions and the tracks' (id, fused outline's centroid); and
    how many outlines the tracker found to hold two people."""
    data = json.loads(gzip.decompress(FIXTURE.read_bytes()))
    world = load_world(REPO / data['world'])
    views = {
        c.name: PinholeCamera.from_config(c).floor_footprint(world.floor_size) for c in world.vision_systems
    }
    tracker = Tracker()
    periods, shared, due = [], 0, PERIOD
    for frame, truth in zip(data['frames'], data['truth'], strict=True):
        if frame['stamp'] >= due:
            tracks = [(v.track_id, centroid(list(v.outline))) for v in tracker.tracks(due)]
            periods.append((due, truth, tracks))
            tracker.expire(due)
            due += PERIOD
        outlines = [Observation(tuple(map(tuple, outline))) for outline in frame['outlines']]
        shared += tracker.frame(frame['camera'], frame['stamp'], outlines, views[frame['camera']]).shared
    return periods, shared


def test_the_fixture_has_blobs_of_two_people(replayed):
    _, shared = replayed
    assert shared >= 20


def test_each_person_is_one_track_with_one_id_where_they_are(replayed):
    periods, _ = replayed
    ids: dict[str, set[int]] = {}
    errors = []
    for stamp, truth, tracks in periods:
        assert len(tracks) == len(truth), stamp  # no duplicate, no ghost, nobody missed
        for name, where in truth.items():
            track_id, position = min(tracks, key=lambda track: math.dist(track[1], where))
            ids.setdefault(name, set()).add(track_id)
            errors.append(math.dist(position, where))
    assert all(len(seen) == 1 for seen in ids.values()), ids  # no ID switch
    assert len(set.union(*ids.values())) == len(ids)
    errors.sort()
    # A blob of one person and a sliver of another behind them (no second centroid inside it)
    # still joins the first person's track: one period's fused outline 0.24 m off.
    assert errors[len(errors) * 95 // 100] <= 0.05 and errors[-1] <= 0.3
