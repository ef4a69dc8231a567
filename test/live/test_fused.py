"""Fused mode on a live graph: the server's fusion stage with fake vision systems that answer,
refuse, stay silent or stamp their frames off the clock, and a callback recorder as the robot."""

import time

import pytest
from test_server import CALLBACK, COLOUR, square

from drvs.common.status import INVALID
from drvs.msg import BoundingBox
from drvs.ros.service_client import ServiceClient
from drvs.srv import DetectObjectBoundary, WatchObjectBoundary
from drvs.testing import echo, wait_for

pytestmark = pytest.mark.shared_master  # see test/conftest.py

BOX = [[4.0, 2.0], [4.4, 2.0], [4.4, 2.4], [4.0, 2.4]]
REGION = (0.0, 0.0, 9.0, 6.0)


def shifted(outline, dx):
    return [[x + dx, y] for x, y in outline]


def ask(graph, request_id, region=REGION, algorithm=COLOUR, fused=True):
    request = DetectObjectBoundary._request_class(
        algorithm=algorithm,
        region_of_interest=BoundingBox(*region),
        callback_service=CALLBACK,
        request_id=request_id,
        fused=fused,
    )
    return graph.detect_client.call(request)


def callbacks(graph, request_id):
    return [r for r in graph.records('callbacks', None) if r['request_id'] == request_id]


@pytest.fixture
def graph(ros, make_graph):
    made = make_graph(fused_deadline=1.5, track_coast=1.0)
    made.records = lambda name, kind: _records(made, name, kind)
    return made


def _records(graph, name, kind):
    from drvs.testing import read_json_lines

    path = graph.tmp_path / f'{name}.jsonl'
    rows = read_json_lines(path) if path.exists() else []
    return [r for r in rows if kind is None or r.get('kind') == kind]


def test_two_cameras_one_object_one_callback_with_a_track(ros, graph):
    graph.camera('cam1', square(0, 0, 6, 6), answer=True, objects=[BOX])
    graph.camera('cam2', square(3, 0, 9, 6), answer=True, objects=[shifted(BOX, 0.05)])
    answer = ask(graph, 'fused-1')
    assert (answer.accepted, answer.vision_systems) == (True, 2)
    wait_for(lambda: callbacks(graph, 'fused-1'), 15, 'the fused callback', on_timeout=ros.describe)
    (callback,) = callbacks(graph, 'fused-1')
    assert callback['fused'] and callback['status'] == 0 and callback['vision_system'] == '/drvs'
    assert callback['answered'] == ['/cam1/detect_object_boundary', '/cam2/detect_object_boundary']
    assert len(callback['objects']) == 1 and callback['track_ids'][0] >= 1
    assert callback['seen_by'][0] == callback['answered']
    # The paper's mode is unchanged: one callback per camera, no track.
    ask(graph, 'paper-1', fused=False)
    wait_for(lambda: len(callbacks(graph, 'paper-1')) == 2, 15, 'two per-camera callbacks')
    assert {c['vision_system'] for c in callbacks(graph, 'paper-1')} == set(callback['answered'])
    assert all(not c['fused'] and c['track_ids'] == [0] for c in callbacks(graph, 'paper-1'))
    objects = echo(ros, '/drvs/objects')
    assert objects['algorithms'] == [COLOUR] and objects['objects'][0]['track_id'] == callback['track_ids'][0]


def test_refusals_silence_and_empty_regions_are_answered_once(ros, graph):
    graph.camera(
        'picky', square(0, 0, 6, 6), refuse=INVALID, refuse_message='blob MIN_AREA must be a number, got x'
    )
    graph.camera('mute', square(10, 0, 16, 6))  # accepts, never calls back
    ask(graph, 'refused', region=(1, 1, 2, 2))
    ask(graph, 'silent', region=(11, 1, 12, 2))
    ask(graph, 'nobody', region=(30, 30, 31, 31))
    for request_id in ('refused', 'silent', 'nobody'):
        wait_for(lambda r=request_id: callbacks(graph, r), 15, f'the callback of {request_id}')
    (refused,) = callbacks(graph, 'refused')
    assert refused['status'] == INVALID and 'MIN_AREA must be a number, got x' in refused['message']
    assert refused['refused'] == [
        '/picky/detect_object_boundary: INVALID: blob MIN_AREA must be a number, got x'
    ]
    (silent,) = callbacks(graph, 'silent')
    assert silent['status'] == 4 and silent['missing'] == ['/mute/detect_object_boundary'], silent
    (nobody,) = callbacks(graph, 'nobody')
    assert nobody['status'] == 0 and nobody['objects'] == []


def test_a_watch_follows_a_moving_object_with_one_id_and_reports_it_gone(ros, graph):
    common = {'answer': True, 'watch': True, 'velocity': [0.5, 0.0], 'epoch': time.time()}
    walk1 = graph.camera('walk1', square(0, 0, 6, 6), objects=[BOX], **common)
    skewed = graph.camera('walk2', square(3, 0, 9, 6), objects=[BOX], stamp_offset=-0.2, **common)
    client = ServiceClient('/drvs/watch_object_boundary', WatchObjectBoundary, 10.0)
    request = WatchObjectBoundary._request_class(
        algorithm=COLOUR,
        region_of_interest=BoundingBox(*REGION),
        callback_service=CALLBACK,
        request_id='walker',
        period=0.2,
        duration=30.0,
        changes_only=True,
        fused=True,
    )
    answer = client.call(request)
    assert answer.accepted and answer.vision_systems == 2
    wait_for(
        lambda: len(callbacks(graph, 'walker')) >= 8, 20, 'eight watch callbacks', on_timeout=ros.describe
    )
    seen = [c for c in callbacks(graph, 'walker') if c['objects']]
    assert {len(c['objects']) for c in seen} == {1}, 'one object, never a duplicate from the skewed camera'
    assert len({c['track_ids'][0] for c in seen}) == 1
    assert seen[-1]['velocities'][0][0] == pytest.approx(0.5, abs=0.2)
    skewed.stop()  # both cameras killed mid-track: the track coasts, then is gone, once
    walk1.stop()
    wait_for(
        lambda: any(c['gone'] for c in callbacks(graph, 'walker')),
        20,
        'the gone report',
        on_timeout=ros.describe,
    )
    gone = [c['gone'] for c in callbacks(graph, 'walker') if c['gone']]
    assert gone == [[seen[-1]['track_ids'][0]]]
    client.close()


def test_a_camera_with_a_wrong_pose_is_left_out_and_named_on_diagnostics(ros, graph):
    boxes = [BOX, shifted(BOX, -2.0), [[x, y + 2.0] for x, y in BOX]]
    common = {'answer': True, 'watch': True}
    graph.camera('good1', square(0, 0, 6, 6), objects=boxes, **common)
    graph.camera('good2', square(0, 0, 6, 6), objects=[shifted(b, 0.03) for b in boxes], **common)
    graph.camera('skewed', square(0, 0, 6, 6), objects=[shifted(b, 0.8) for b in boxes], **common)
    client = ServiceClient('/drvs/watch_object_boundary', WatchObjectBoundary, 10.0)
    request = WatchObjectBoundary._request_class(
        algorithm=COLOUR,
        region_of_interest=BoundingBox(0, 0, 6, 6),
        callback_service=CALLBACK,
        request_id='boxes',
        period=0.2,
        duration=30.0,
        fused=True,
    )
    assert client.call(request).vision_systems == 3
    shown = ros.run(
        "timeout 30 rostopic echo -n 1 --filter \"m.status[0].name == 'drvs: /drvs' and "
        "'left out of fusion: /skewed' in m.status[0].message\" /diagnostics",
        timeout=40,
    )
    assert shown.returncode == 0, shown.stdout + shown.stderr + ros.describe()
    assert 'level: 1' in shown.stdout
    count = len(callbacks(graph, 'boxes'))
    wait_for(lambda: len(callbacks(graph, 'boxes')) >= count + 3, 10, 'three more periods')
    latest = callbacks(graph, 'boxes')[-1]
    assert len(latest['objects']) == 3, 'no ghosts from the skewed camera'
    assert all('/skewed/detect_object_boundary' not in seen for seen in latest['seen_by'])
    client.close()
