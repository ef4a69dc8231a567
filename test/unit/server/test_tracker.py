"""The fusion tracker: association, motion, faults and bad input, on explicit stamps (no ROS, no clock)."""

import math
import random

import pytest

from drvs.server.tracker import FrameResult, Observation, Tracker, TrackerSettings

RATE = 10.0  # frames a second per camera


def square(x, y, size=0.5):
    """A counter-clockwise square outline centred on (x, y)."""
    h = size / 2
    return ((x - h, y - h), (x + h, y - h), (x + h, y + h), (x - h, y + h))


def seen(x, y, size=0.5, label='', confidence=0.0):
    return Observation(square(x, y, size), label, confidence)


def ticks(seconds, start=0.0, rate=RATE):
    return [start + i / rate for i in range(round(seconds * rate))]


def ids_near(tracker, at, x, y, within):
    return [t.track_id for t in tracker.tracks(at) if math.dist(t.position, (x, y)) <= within]


# -- association ------------------------------------------------------------------------------------


@pytest.mark.parametrize('lateral', [0.0, 0.3])
def test_crossing_paths_keep_their_ids(lateral):
    tracker = Tracker()
    for t in ticks(4.0):
        a, b = (t, 0.0), (4.0 - t, lateral)  # through each other at t = 2 s, 1 m/s each
        tracker.frame('cam', t, [seen(*a), seen(*b)])
        if abs(t - 2.0) > 0.15:  # apart: each id where its person is
            assert (ids_near(tracker, t, *a, within=0.1), ids_near(tracker, t, *b, within=0.1)) == ([1], [2])
    assert len(tracker) == 2


def test_an_occlusion_shorter_than_the_coast_time_keeps_the_id():
    tracker = Tracker()
    for t in ticks(4.0):
        if not 2.0 <= t < 3.0:  # unseen for 1 s (coast: 2 s)
            tracker.frame('cam', t, [seen(t, 1.0)], field_of_view=square(2, 1, 10))
    views = tracker.tracks(3.9)
    assert [v.track_id for v in views] == [1]
    assert views[0].position == pytest.approx((3.9, 1.0), abs=0.05)


def test_two_cameras_with_a_constant_offset_give_one_track_per_object():
    tracker = Tracker()
    objects = [(0.0, 0.0), (2.0, 0.0), (2.0, 2.0)]
    for t in ticks(2.0):
        moved = [(x + 0.5 * t, y) for x, y in objects]
        tracker.frame('a', t, [seen(x, y) for x, y in moved])
        tracker.frame('b', t + 0.05, [seen(x + 0.08 + 0.025, y) for x, y in moved])  # 8 cm off
        assert len(tracker) == 3
    views = tracker.tracks(2.0)
    assert sorted(v.track_id for v in views) == [1, 2, 3]
    assert all(v.seen_by == ('a', 'b') for v in views)


def test_an_outline_whose_centroid_is_beyond_the_gate_joins_the_object_it_overlaps():
    tracker = Tracker()
    whole = ((0.0, 0.0), (4.0, 0.0), (4.0, 1.0), (0.0, 1.0))  # a 4 m shelf, centroid (2, 0.5)
    right = ((2.8, 0.0), (4.0, 0.0), (4.0, 1.0), (2.8, 1.0))  # what another camera sees: (3.4, 0.5)
    for t in ticks(1.0):
        tracker.frame('a', t, [Observation(whole)])
        result = tracker.frame('b', t + 0.01, [Observation(right)])
        assert (result.associated, result.created) == (1, 0)
    assert len(tracker) == 1


def test_a_camera_that_splits_an_object_in_two_blobs_adds_one_merged_outline():
    tracker = Tracker()
    box = ((0.0, 0.0), (2.0, 0.0), (2.0, 1.0), (0.0, 1.0))
    left = ((0.0, 0.0), (0.95, 0.0), (0.95, 1.0), (0.0, 1.0))
    right = ((1.05, 0.0), (2.0, 0.0), (2.0, 1.0), (1.05, 1.0))
    tracker.frame('a', 0.0, [Observation(box)])
    result = tracker.frame('b', 0.05, [Observation(left), Observation(right)])
    assert result == FrameResult(associated=2, created=0, untracked=0, ignored=False, merged=1)
    (view,) = tracker.tracks(0.05)
    assert view.position == pytest.approx((1.0, 0.5), abs=0.01)
    assert view.seen_by == ('a', 'b')


def test_two_people_walking_apart_are_not_merged():
    tracker = Tracker()
    tracker.frame('a', 0.0, [seen(0.0, 0.0, size=1.0)])
    result = tracker.frame('a', 0.1, [seen(-1.0, 0.0), seen(1.0, 0.0)])
    assert (result.merged, len(tracker)) == (0, 2)


def test_a_blob_of_two_people_passing_close_moves_neither_track():
    # Two people pass 0.6 m apart; cameras a and b see each, camera c sees them one behind the
    # other as one blob while they are within 1 m: it neither pulls them together nor starts a ghost.
    tracker = Tracker()
    shared = 0
    for t in ticks(4.0):
        a, b = (t, 0.0), (4.0 - t, 0.6)  # at 1 m/s each, closest at t = 2 s
        both = [seen(*a, size=0.3), seen(*b, size=0.3)]
        tracker.frame('a', t, both)
        tracker.frame('b', t + 0.03, [seen(a[0] + 0.03, a[1], size=0.3), seen(b[0] - 0.03, b[1], size=0.3)])
        c = t + 0.06
        a, b = (c, 0.0), (4.0 - c, 0.6)
        if math.dist(a, b) < 1.0:
            blob = (
                (min(a[0], b[0]) - 0.15, -0.15),
                (max(a[0], b[0]) + 0.15, -0.15),
                (max(a[0], b[0]) + 0.15, 0.75),
            )
            shared += tracker.frame('c', c, [Observation(blob + ((min(a[0], b[0]) - 0.15, 0.75),))]).shared
        else:
            tracker.frame('c', c, [seen(*a, size=0.3), seen(*b, size=0.3)])
        if t >= 0.5:
            assert ids_near(tracker, c, *a, within=0.05) == [1], t
            assert ids_near(tracker, c, *b, within=0.05) == [2], t
    assert shared > 0 and len(tracker) == 2


def test_a_tags_label_wins_over_proximity_and_two_tags_never_merge():
    tracker = Tracker()
    tracker.frame('cam', 0.0, [seen(0.0, 0.0, label='tag:1'), seen(3.0, 0.0, label='tag:2')])
    # tag 1 now where tag 2 was, tag 2 half a metre from tag 1's old spot: labels decide.
    tracker.frame('cam', 0.1, [seen(2.9, 0.0, label='tag:1'), seen(0.5, 0.0, label='tag:2')])
    views = {v.label: v for v in tracker.tracks(0.1)}
    assert (views['tag:1'].track_id, views['tag:2'].track_id) == (1, 2)
    for t in ticks(1.0, start=0.2):  # both on one spot: still two tracks
        result = tracker.frame('cam', t, [seen(1.0, 1.0, label='tag:1'), seen(1.0, 1.0, label='tag:2')])
        assert result.associated == 2
    assert len(tracker) == 2
    result = tracker.frame('cam', 1.3, [seen(1.0, 1.0, label='tag:1'), seen(5.0, 5.0, label='tag:1')])
    assert (result.associated, result.skipped) == (1, 1)  # one outline per label and frame


def test_labelled_and_plain_outlines_never_share_a_track():
    tracker = Tracker()
    tracker.frame('cam', 0.0, [seen(0.0, 0.0, label='tag:1')])
    tracker.frame('cam', 0.1, [seen(0.0, 0.0)])
    assert sorted(v.label for v in tracker.tracks(0.1)) == ['', 'tag:1']


# -- motion ---------------------------------------------------------------------------------------------


def test_the_velocity_converges_within_a_second_at_10_hz():
    tracker = Tracker()
    for t in ticks(1.0):
        tracker.frame('cam', t, [seen(1.0 + 0.6 * t, 2.0 - 0.8 * t)])  # 1 m/s
    (view,) = tracker.tracks(0.9)
    assert view.velocity == pytest.approx((0.6, -0.8), abs=0.1)
    assert not view.stationary


def test_a_still_object_becomes_stationary_after_the_stationary_time():
    tracker = Tracker()
    noise = random.Random(4)
    states = []
    for t in ticks(2.0):
        tracker.frame('a', t, [seen(1.0 + noise.gauss(0, 0.02), 1.0 + noise.gauss(0, 0.02))])
        tracker.frame('b', t + 0.03, [seen(1.06 + noise.gauss(0, 0.02), 1.0 + noise.gauss(0, 0.02))])
        (view,) = tracker.tracks(t + 0.03)
        states.append((t, view.stationary))
    assert all(not still for t, still in states if t < 0.9)
    assert all(still for t, still in states if t >= 1.2)
    assert tracker.tracks(2.0)[0].velocity == (0.0, 0.0)


def frames_of_two_cameras():
    """(camera, stamp, observations) of two people walking, seen by two cameras at 10 Hz."""
    frames = []
    for t in ticks(3.0):
        people = [(0.5 * t, 0.0), (3.0, 3.0 - 0.7 * t)]
        frames.append(('a', t, [seen(x, y) for x, y in people]))
        frames.append(('b', t + 0.04, [seen(x + 0.02 + 0.02, y) for x, y in people]))
    return frames


def test_frames_arriving_out_of_order_give_the_same_tracks():
    in_order, shuffled = Tracker(), Tracker()
    frames = frames_of_two_cameras()
    for frame in frames:
        in_order.frame(*frame)
    late = random.Random(7)
    arrivals = sorted(frames, key=lambda f: f[1] + late.uniform(0.0, 0.3))  # each up to 300 ms late
    assert arrivals != frames
    for frame in arrivals:
        shuffled.frame(*frame)
    expected = {v.track_id: v for v in in_order.tracks(3.0)}
    got = {v.track_id: v for v in shuffled.tracks(3.0)}
    assert len(in_order) == len(shuffled) == 2
    assert got.keys() == expected.keys()
    for track_id, view in expected.items():
        assert got[track_id].position == pytest.approx(view.position, abs=0.01)
        assert got[track_id].velocity == pytest.approx(view.velocity, abs=0.02)


# -- faults --------------------------------------------------------------------------------------------


def test_a_killed_cameras_tracks_carry_on_from_another_camera():
    tracker = Tracker()
    for t in ticks(4.0):
        if t < 2.0:
            tracker.frame('a', t, [seen(t, 0.0)])
        tracker.frame('b', t + 0.02, [seen(t, 0.0)])
    (view,) = tracker.tracks(4.0, since=2.5)
    assert (view.track_id, view.seen_by) == (1, ('b',))
    assert tracker.expire(4.0) == []


def test_a_killed_cameras_tracks_coast_then_are_reported_gone_once():
    tracker = Tracker()
    for t in ticks(2.0):
        tracker.frame('a', t, [seen(t, 0.0), seen(5.0, 5.0)])
    tracker.forget('a')
    assert tracker.expire(3.0) == []
    coasting = {v.track_id: v for v in tracker.tracks(3.0)}
    assert coasting[1].position == pytest.approx((3.0, 0.0), abs=0.05)  # predicted on
    assert 0 < coasting[1].confidence < 0.6
    assert tracker.expire(3.95) == [1, 2]
    assert tracker.expire(5.0) == []
    assert (len(tracker), tracker.tracks(5.0)) == (0, [])


def test_a_camera_with_a_wrong_pose_is_flagged_and_left_out():
    tracker = Tracker()
    objects = [(3.0 * i, 1.0) for i in range(5)]
    results = []
    for t in ticks(2.0):
        tracker.frame('a', t, [seen(x, y) for x, y in objects])
        tracker.frame('b', t + 0.02, [seen(x, y + 0.05) for x, y in objects])
        results.append(tracker.frame('c', t + 0.04, [seen(x + 0.8, y) for x, y in objects]))  # 0.8 m off
        assert len(tracker) == 5  # no ghosts
    assert results[-1] == FrameResult(0, 0, 0, True)
    assert all(r.ignored for r in results)  # flagged at its first frame
    assert list(tracker.flagged()) == ['c']
    assert tracker.flagged()['c'] == (
        "its outlines are 0.80 m from its neighbours' (median of 5 shared objects; tolerance 0.3 m)"
    )
    for view in tracker.tracks(2.0):
        assert view.seen_by == ('a', 'b')
        assert min(math.dist(view.position, o) for o in objects) < 0.06
    tracker.forget('c')
    assert tracker.flagged() == {}


def test_two_cameras_alone_that_disagree_are_not_flagged():
    tracker = Tracker()
    objects = [(3.0 * i, 1.0) for i in range(5)]
    for t in ticks(1.0):
        tracker.frame('a', t, [seen(x, y) for x, y in objects])
        tracker.frame('c', t + 0.04, [seen(x + 0.8, y) for x, y in objects])
    assert tracker.flagged() == {}  # which one is wrong? a third camera would tell
    assert len(tracker) == 5


def test_a_flood_of_outlines_is_bounded_and_counted():
    tracker = Tracker(TrackerSettings(max_tracks=10))
    result = tracker.frame('cam', 0.0, [seen(2.0 * i, 0.0) for i in range(25)])
    assert result == FrameResult(associated=0, created=10, untracked=15, ignored=False)
    assert len(tracker) == 10
    result = tracker.frame('cam', 0.1, [seen(2.0 * i, 0.0) for i in range(25)])
    assert (result.associated, result.created, result.untracked) == (10, 0, 15)


def test_a_full_table_makes_room_by_ending_tracks_past_their_coast_time():
    tracker = Tracker(TrackerSettings(max_tracks=2))
    tracker.frame('cam', 0.0, [seen(0.0, 0.0), seen(5.0, 0.0)])
    result = tracker.frame('cam', 3.0, [seen(10.0, 0.0)])
    assert (result.created, result.untracked) == (1, 0)
    assert tracker.expire(3.0) == [1, 2]


def test_a_camera_stamping_200_ms_late_gives_no_duplicates_and_a_bounded_error():
    tracker = Tracker()
    worst = 0.0
    for t in ticks(4.0):
        tracker.frame('a', t, [seen(t, 0.0)])
        tracker.frame('late', t + 0.05 + 0.2, [seen(t + 0.05, 0.0)])  # its clock 200 ms ahead
        assert len(tracker) == 1
        if t >= 1.0:
            (view,) = tracker.tracks(t + 0.05)
            worst = max(worst, math.dist(view.position, (t + 0.05, 0.0)))
    assert worst <= 0.2  # speed x skew: docs/fusion-tracking.md
    assert tracker.flagged() == {}


# -- confidence, queries, bad input --------------------------------------------------------------------


def test_confidence_is_between_0_and_1_rises_with_detections_and_falls_with_misses():
    tracker = Tracker()
    tracker.frame('a', 0.0, [seen(0.0, 0.0, confidence=0.9), seen(4.0, 0.0, confidence=7.0)])
    first = {v.track_id: v.confidence for v in tracker.tracks(0.0)}
    assert first == {1: pytest.approx(0.9), 2: 1.0}
    for t in ticks(1.0, start=0.1):
        tracker.frame('a', t, [seen(0.0, 0.0), seen(4.0, 0.0, confidence=-3)])
    assert all(0.0 <= v.confidence <= 1.0 for v in tracker.tracks(1.0))
    before = {v.track_id: v.confidence for v in tracker.tracks(1.1)}
    tracker.frame('b', 1.1, [], field_of_view=square(0.0, 0.0, 2.0))  # looks at track 1, sees nothing
    after = {v.track_id: v.confidence for v in tracker.tracks(1.1)}
    assert after == {1: pytest.approx(before[1] * 0.8), 2: before[2]}
    # fading linearly over the coast time (2 s) since last seen (1.0 s)
    assert tracker.tracks(2.9)[0].confidence == pytest.approx(after[1] / 0.95 * 0.05)


def test_tracks_in_a_region_and_seen_by_since():
    tracker = Tracker()
    tracker.frame('a', 0.0, [seen(0.0, 0.0), seen(5.0, 5.0)])
    tracker.frame('b', 0.5, [seen(5.0, 5.0)])
    inside = tracker.tracks(0.5, region=(4.0, 4.0, 4.8, 4.8))
    assert [v.track_id for v in inside] == [2]
    assert inside[0].seen_by == ('a', 'b')
    assert tracker.tracks(0.5, region=(4.0, 4.0, 4.8, 4.8), since=0.2)[0].seen_by == ('b',)
    assert tracker.tracks(0.5, region=(10, 10, 11, 11)) == []
    outline = inside[0].outline
    edges = zip(outline, outline[1:] + outline[:1], strict=True)
    area = sum(x0 * y1 - x1 * y0 for (x0, y0), (x1, y1) in edges)
    assert area > 0  # counter-clockwise


BAD = [
    ((0, 0), (1, 1)),  # two points
    ((0, 0), (1, 1), (2, 2)),  # no area
    ((0, 0), (1, float('nan')), (0, 1)),
    ((0, 0), (float('inf'), 0), (0, 1)),
    ((0, 0), (1e300, 0), (0, 1e300)),
    (('a', 'b'), (1, 0), (0, 1)),
    ((0, 0, 0), (1, 0, 0), (0, 1, 0)),
    (),
    None,
]


def test_degenerate_outlines_are_skipped_and_counted():
    tracker = Tracker()
    result = tracker.frame('cam', 0.0, [Observation(b) for b in BAD] + [seen(0, 0)])
    assert result == FrameResult(associated=0, created=1, untracked=0, ignored=False, skipped=len(BAD))
    assert tracker.frame('cam', float('nan'), [seen(0, 0)]).skipped == 1
    result = tracker.frame('cam', 0.1, [seen(0, 0)], field_of_view=[(0, 0), (float('nan'), 1)])
    assert result.associated == 1


def test_random_input_never_raises():
    tracker = Tracker(TrackerSettings(max_tracks=30))
    rng = random.Random(11)
    values = [0.0, 1.0, -1.0, 0.5, 1e-9, 1e9, float('nan'), float('inf'), -float('inf')]

    def coordinate():
        return rng.choice(values) if rng.random() < 0.2 else rng.uniform(-10, 10)

    for i in range(300):
        outlines = [
            Observation(
                tuple((coordinate(), coordinate()) for _ in range(rng.randint(0, 6))),
                rng.choice(['', '', 'tag:1', 'tag:2']),
                rng.choice(values),
            )
            for _ in range(rng.randint(0, 8))
        ]
        stamp = rng.choice([0.1 * i, 0.1 * i - 0.5, 0.1 * i + 3.0, float('nan')])
        field = rng.choice([None, square(0, 0, 10), [(0, 0), (1, float('nan')), (0, 1)], []])
        result = tracker.frame(rng.choice('abc'), stamp, outlines, field_of_view=field)
        fused = 0 if result.ignored else result.associated + result.created + result.untracked
        assert fused + result.skipped == len(outlines)
        for view in tracker.tracks(0.1 * i, region=(-5, -5, 5, 5)):
            assert 0.0 <= view.confidence <= 1.0
        tracker.expire(0.1 * i)
    assert len(tracker) <= 30


def test_a_frame_older_than_the_reorder_window_joins_without_moving_the_track():
    tracker = Tracker()
    for t in ticks(3.0):
        tracker.frame('a', t, [seen(1.0, 1.0)])
    before = tracker.tracks(2.9)[0]
    result = tracker.frame('b', 1.2, [seen(1.3, 1.0)])  # 1.7 s late: past the reorder window
    after = tracker.tracks(2.9)[0]
    assert (result.associated, after.position, after.last_seen) == (1, before.position, 2.9)
    assert tracker.tracks(2.9, since=2.0)[0].seen_by == ('a',)
    assert tracker.tracks(2.9, since=0.0)[0].seen_by == ('a', 'b')


def test_a_frame_older_than_the_coast_time_is_stale_and_fuses_nothing():
    tracker = Tracker()
    for t in ticks(3.0):
        tracker.frame('a', t, [seen(1.0, 1.0)])
    result = tracker.frame('b', 0.5, [seen(3.0, 3.0), seen(1.3, 1.0)])  # 2.4 s late: an old frame
    assert (result.stale, result.skipped, result.created, len(tracker)) == (True, 2, 0, 1)
    assert tracker.newest == pytest.approx(2.9)


def test_settings_are_checked():
    with pytest.raises(ValueError, match=r'^gate: must be a positive number, got -1.0$'):
        TrackerSettings(gate=-1.0)
    with pytest.raises(ValueError, match=r'^min_overlap: must be at most 1, got 2$'):
        TrackerSettings(min_overlap=2)


def test_a_stationary_object_wider_than_one_view_keeps_every_cameras_part():
    """A shelf seen in two halves by two cameras, their frames 0.4 s apart: one track, not moving
    (the halves' centroids 0.9 m apart are no motion), and its fused outline is both halves."""
    tracker = Tracker()
    left = Observation(((0.0, 0.0), (1.2, 0.0), (1.2, 0.5), (0.0, 0.5)))
    right = Observation(((1.0, 0.0), (2.0, 0.0), (2.0, 0.5), (1.0, 0.5)))
    for step in range(8):
        tracker.frame('a', 0.8 * step, [left])
        tracker.frame('b', 0.8 * step + 0.4, [right])
    (view,) = tracker.tracks(6.0)
    assert view.stationary
    xs = [x for x, _ in view.outline]
    assert (min(xs), max(xs)) == (pytest.approx(0.0, abs=0.01), pytest.approx(2.0, abs=0.01))


def test_a_small_objects_outline_is_its_newest_view_moved_not_a_union_of_views():
    # A tag seen by two cameras 50 ms apart while it moves at 0.5 m/s: the union of both views
    # would be 2.5 cm longer and lose the tag's four corners (its heading).
    tracker = Tracker()
    for t in ticks(2.0):
        tracker.frame('a', t, [seen(0.5 * t, 1.0, size=0.2, label='7')])
        tracker.frame('b', t + 0.05, [seen(0.5 * (t + 0.05) + 0.02, 1.0, size=0.2, label='7')])
    (view,) = tracker.tracks(2.0)
    assert len(view.outline) == 4
    newest = square(0.5 * 2.0 + 0.02, 1.0, size=0.2)  # b's view at 1.95 s, moved 50 ms along
    assert sorted(view.outline) == [pytest.approx(p, abs=0.01) for p in sorted(newest)]


# -- heights ----------------------------------------------------------------------------------------


def test_a_tracks_height_is_the_highest_top_its_cameras_measured_lately():
    tracker = Tracker()
    box = square(1.0, 1.0)
    tracker.frame('a', 0.0, [Observation(box, height=0.95)])
    tracker.frame('b', 0.0, [Observation(box, height=1.0)])  # the other camera sees more of the top
    tracker.frame('c', 0.1, [Observation(box)])  # an algorithm that measures no height
    (view,) = tracker.tracks(0.1)
    assert view.height == pytest.approx(1.0)
    for t in ticks(3.0, start=0.2):  # only c for longer than the coast time: b's top is forgotten
        tracker.frame('c', t, [Observation(box)])
    assert [v.height for v in tracker.tracks(3.2)] == [0.0]


@pytest.mark.parametrize('height', [math.nan, math.inf, -1.0, 'high'])
def test_a_height_that_is_not_a_number_of_metres_counts_as_unmeasured(height):
    tracker = Tracker()
    tracker.frame('a', 0.0, [Observation(square(1.0, 1.0), height=height)])
    assert [v.height for v in tracker.tracks(0.0)] == [0.0]


def test_pieces_of_one_object_keep_the_highest_top():
    tracker = Tracker()
    for t in ticks(1.0):  # a shelf, one camera seeing it whole
        tracker.frame('a', t, [Observation(square(2.0, 1.0, 2.0), height=0.4)])
    # The next frame splits it in two pieces, the second higher (a box standing on it).
    halves = [Observation(square(1.5, 1.0, 1.0), height=0.4), Observation(square(2.5, 1.0, 1.0), height=1.2)]
    result = tracker.frame('a', 1.0, halves)
    assert result.created == 0
    assert [v.height for v in tracker.tracks(1.0)] == [pytest.approx(1.2)]


def test_a_track_has_the_room_under_it_that_a_camera_saw():
    """One camera sees a shelf's top only (clearance 0, unknown), another sees floor under it: the
    track has that one's clearance; a view of it merged with something higher proves nothing."""
    tracker = Tracker()
    shelf = square(2.0, 1.0, 1.0)
    tracker.frame('a', 0.0, [Observation(shelf, height=0.45)])
    tracker.frame('b', 0.0, [Observation(shelf, height=0.46, clearance=0.33)])
    (view,) = tracker.tracks(0.0)
    assert (view.height, view.clearance) == (pytest.approx(0.46), pytest.approx(0.33))
    tracker.frame('c', 0.1, [Observation(square(2.0, 1.0, 1.2), height=1.0)])
    assert [v.clearance for v in tracker.tracks(0.1)] == [0.0]


def test_pieces_of_one_object_keep_the_lowest_underside():
    tracker = Tracker()
    for t in ticks(1.0):
        tracker.frame('a', t, [Observation(square(2.0, 1.0, 2.0), height=0.4, clearance=0.3)])
    halves = [
        Observation(square(1.5, 1.0, 1.0), height=0.4, clearance=0.3),
        Observation(square(2.5, 1.0, 1.0), height=0.4, clearance=math.nan),  # not a number: 0
    ]
    tracker.frame('a', 1.0, halves)
    assert [v.clearance for v in tracker.tracks(1.0)] == [0.0]
