"""drvs.vision.frame_feed: which frame a request gets, and when a feed is stale (manual clock)."""

import doctest
import threading
from types import SimpleNamespace

import pytest

import drvs.vision.frame_feed
from drvs.testing import wait_for
from drvs.testing.clock import ManualClock
from drvs.vision.frame_feed import FrameFeed, FrameTimeout


def frame(stamp):
    return SimpleNamespace(stamp=stamp)


def test_doctest():
    assert doctest.testmod(drvs.vision.frame_feed).failed == 0


def test_a_fresh_frame_is_used_at_once():
    clock = ManualClock(10.0)
    feed = FrameFeed(max_age=0.1, timeout=5.0, stale_after=1.0, clock=clock)
    feed.put(frame(9.95))
    assert feed.get().stamp == 9.95


def test_an_old_frame_makes_the_request_wait_for_the_next_one():
    clock = ManualClock(10.0)
    feed = FrameFeed(max_age=0.1, timeout=30.0, stale_after=1.0, clock=clock)
    feed.put(frame(9.5))  # 0.5 s old: too old
    got = []
    waiter = threading.Thread(target=lambda: got.append(feed.get()))
    waiter.start()
    wait_for(lambda: feed._changed._waiters, 10, 'the request to wait')  # noqa: SLF001 (the condition)
    assert not got
    feed.put(frame(9.0))  # the next frame, whatever its stamp (a replay without /clock)
    waiter.join(10)
    assert [f.stamp for f in got] == [9.0]


def test_a_request_gives_up_after_the_timeout_and_says_why():
    clock = ManualClock(10.0)
    feed = FrameFeed(max_age=0.1, timeout=0.05, stale_after=1.0, clock=clock)
    with pytest.raises(FrameTimeout, match=r'^no frame has arrived yet \(waited 0.05 s\)$'):
        feed.get()
    feed.put(frame(10.0))
    clock.now += 2.0
    with pytest.raises(
        FrameTimeout, match=r'^no new frame within 0.05 s \(the last one arrived 2.0 s ago\)$'
    ):
        feed.get()


def test_a_feed_is_stale_after_stale_after_seconds_without_frames_and_alive_again_with_one():
    clock = ManualClock(10.0)
    feed = FrameFeed(max_age=0.1, timeout=1.0, stale_after=2.0, clock=clock)
    assert feed.stale() and feed.age() == float('inf')  # nothing yet
    feed.put(frame(10.0))
    clock.now += 2.0
    assert not feed.stale()
    clock.now += 0.01
    assert feed.stale() and feed.age() == pytest.approx(2.01)
    feed.put(frame(12.01))
    assert not feed.stale() and feed.received == 2


def test_staleness_is_counted_from_arrival_not_from_the_stamp():
    clock = ManualClock(100.0)
    feed = FrameFeed(max_age=0.1, timeout=1.0, stale_after=2.0, clock=clock)
    feed.put(frame(3.0))  # a camera whose clock is far behind: frames still arrive
    assert not feed.stale()
