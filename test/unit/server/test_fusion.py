"""The fusion stage's bookkeeping: one delivery per fused request, one per watch period, refusals
passed on, deadlines, gone tracks once, bounded rounds (drvs.server.fusion)."""

import pytest

from drvs.common.status import BUSY, INVALID, UNAVAILABLE
from drvs.server.fusion import OK, FusionSettings, FusionStage
from drvs.server.tracker import Observation, TrackerSettings
from drvs.testing import ManualClock

FIELDS = {
    '/cam1/detect_object_boundary': [(0.0, 0.0), (6.0, 0.0), (6.0, 6.0), (0.0, 6.0)],
    '/cam2/detect_object_boundary': [(3.0, 0.0), (9.0, 0.0), (9.0, 6.0), (3.0, 6.0)],
}
CAM1, CAM2 = sorted(FIELDS)
GREEN = 'colour:0,150,0,80,255,80'
REGION = (0.0, 0.0, 9.0, 6.0)


def square(x, y, side=0.4, shift=0.0):
    x += shift
    return Observation(((x, y), (x + side, y), (x + side, y + side), (x, y + side)))


@pytest.fixture
def clock():
    return ManualClock(100.0)


def make_stage(clock, **settings):
    tracker = TrackerSettings(coast=settings.pop('coast', 1.0))
    return FusionStage(clock, FIELDS.get, FusionSettings(tracker=tracker, **settings))


def test_a_fused_request_is_answered_once_with_every_object_once(clock):
    stage = make_stage(clock)
    wire = stage.open_round('/robot', 'r1', GREEN, REGION, '/robot/cb', [CAM1, CAM2])
    for camera, shift in ((CAM1, 0.0), (CAM2, 0.05)):  # both see the same box, 5 cm apart
        stage.forward_answer(wire, camera, OK)
        assert stage.callback(wire, camera, 100.0, GREEN, [square(4.0, 2.0, shift=shift)])
    (delivery,) = stage.due()
    assert (delivery.status, delivery.request_id, delivery.callback_service) == (OK, 'r1', '/robot/cb')
    assert delivery.answered == (CAM1, CAM2) and delivery.missing == delivery.refused == ()
    (track,) = delivery.objects
    assert track.track_id >= 1 and track.seen_by == (CAM1, CAM2)
    assert stage.due() == [] and stage.waiting == 0


def test_nothing_found_is_still_answered_and_no_camera_at_once(clock):
    stage = make_stage(clock)
    wire = stage.open_round('/robot', 'r1', GREEN, REGION, '/robot/cb', [CAM1])
    stage.callback(wire, CAM1, 100.0, GREEN, [])
    (delivery,) = stage.due()
    assert (delivery.status, delivery.objects) == (OK, ())
    stage.open_round('/robot', 'r2', GREEN, (50.0, 50.0, 51.0, 51.0), '/robot/cb', [])
    (delivery,) = stage.due()
    assert (delivery.request_id, delivery.status, delivery.objects) == ('r2', OK, ())
    assert 'no vision system covers the region' in delivery.message


def test_a_camera_that_never_answers_is_missing_after_the_deadline(clock):
    stage = make_stage(clock, deadline=2.0, coast=5.0)
    wire = stage.open_round('/robot', 'r1', GREEN, REGION, '/robot/cb', [CAM1, CAM2])
    stage.callback(wire, CAM1, 100.0, GREEN, [square(1.0, 1.0)])
    assert stage.due() == [] and stage.next_due() == pytest.approx(102.0)
    clock.now = 102.0
    (delivery,) = stage.due()
    assert delivery.status == OK and delivery.answered == (CAM1,) and delivery.missing == (CAM2,)
    assert len(delivery.objects) == 1


def test_refusals_reach_the_requester(clock):
    stage = make_stage(clock)
    wire = stage.open_round('/robot', 'r1', 'blob:nonsense', REGION, '/robot/cb', [CAM1, CAM2])
    for camera in (CAM1, CAM2):
        stage.forward_answer(wire, camera, INVALID, 'algorithm: blob: expected MIN_AREA, got nonsense')
    (delivery,) = stage.due()
    assert delivery.status == INVALID and delivery.objects == ()
    assert delivery.refused == tuple(
        f'{c}: INVALID: algorithm: blob: expected MIN_AREA, got nonsense' for c in (CAM1, CAM2)
    )
    assert 'expected MIN_AREA' in delivery.message


def test_failed_forwards_and_silence_are_unavailable(clock):
    stage = make_stage(clock)
    wire = stage.open_round('/robot', 'r1', GREEN, REGION, '/robot/cb', [CAM1, CAM2])
    stage.forward_answer(wire, CAM1, None)
    stage.forward_answer(wire, CAM2, None)
    (delivery,) = stage.due()
    assert delivery.status == UNAVAILABLE and delivery.missing == (CAM1, CAM2)


def test_rounds_are_bounded(clock):
    stage = make_stage(clock, max_rounds=2)
    for n in range(2):
        stage.open_round('/robot', f'r{n}', GREEN, REGION, '/robot/cb', [CAM1])
    with pytest.raises(Exception) as refused:
        stage.open_round('/robot', 'r3', GREEN, REGION, '/robot/cb', [CAM1])
    assert refused.value.status == BUSY and refused.value.retry_after > 0


def test_a_late_frame_still_feeds_the_tracks(clock):
    stage = make_stage(clock, deadline=1.0)
    wire = stage.open_round('/robot', 'r1', GREEN, REGION, '/robot/cb', [CAM1])
    clock.now = 101.0
    (delivery,) = stage.due()
    assert delivery.missing == (CAM1,)
    assert not stage.callback(wire, CAM1, 100.9, GREEN, [square(2.0, 2.0)])
    assert stage.late == 1 and stage.track_count() == 1


def test_a_fused_watch_delivers_each_period_and_reports_a_gone_track_once(clock):
    stage = make_stage(clock, coast=1.0)
    key = ('/robot', 'people')
    wire = stage.set_watch(key, GREEN, REGION, '/robot/cb', 0.5, changes_only=True)
    assert stage.wire_id(key) == wire
    stage.keep_watches({key: [CAM1, CAM2]})
    ids = set()
    for step in range(4):  # a person walking at 1 m/s, seen by both cameras
        stamp = 100.0 + 0.25 * step
        clock.now = stamp
        for camera in (CAM1, CAM2):
            stage.callback(wire, camera, stamp, GREEN, [square(3.5 + 0.25 * step, 2.0)])
        for delivery in stage.due():
            assert delivery.watch and delivery.request_id == 'people' and delivery.status == OK
            ids |= {track.track_id for track in delivery.objects}
    assert len(ids) == 1
    deliveries = []
    for step in range(1, 12):  # nobody sees it any more: it coasts, then is gone, once
        clock.now = 101.0 + 0.25 * step
        deliveries += stage.due()
    gone = [d.gone for d in deliveries if d.gone]
    assert gone == [tuple(ids)]
    assert deliveries[-1].objects == ()


def test_a_refused_watch_says_so_in_its_callback(clock):
    stage = make_stage(clock)
    key = ('/robot', 'boxes')
    wire = stage.set_watch(key, 'blob:x', REGION, '/robot/cb', 0.5, changes_only=False)
    stage.keep_watches({key: [CAM1]})
    stage.watch_refused(wire, CAM1, INVALID, 'blob: bad')
    clock.now = 100.5
    (delivery,) = stage.due()
    assert delivery.status == INVALID and delivery.refused == (f'{CAM1}: INVALID: blob: bad',)
    stage.keep_watches({})
    assert stage.watches == 0 and stage.wire_id(key) is None


def test_one_tracker_per_algorithm_bounded(clock):
    stage = make_stage(clock, max_algorithms=1)
    stage.open_round('/robot', 'r1', GREEN, REGION, '/robot/cb', [CAM1])
    with pytest.raises(Exception) as refused:
        stage.open_round('/robot', 'r2', 'colour:1,1,1,2,2,2', REGION, '/robot/cb', [CAM1])
    assert refused.value.status == BUSY
    stage.due()  # r1 still waits for its camera: its tracker is in use
    clock.now += 10.0
    stage.due()  # r1 answered at its deadline: the idle tracker makes room
    stage.open_round('/robot', 'r3', 'colour:1,1,1,2,2,2', REGION, '/robot/cb', [CAM1])


def test_a_flood_of_outlines_is_bounded_and_said_in_the_answer(clock):
    stage = FusionStage(clock, FIELDS.get, FusionSettings(tracker=TrackerSettings(max_tracks=5)))
    wire = stage.open_round('/robot', 'flood', GREEN, REGION, '/robot/cb', [CAM1])
    flood = [square(0.5 * (i % 10), 0.5 * (i // 10), side=0.2) for i in range(40)]
    stage.callback(wire, CAM1, 100.0, GREEN, flood)
    (delivery,) = stage.due()
    assert delivery.status == OK and len(delivery.objects) == 5
    assert stage.untracked == 35 and '35 outlines left untracked' in delivery.message
