"""The server's checks of a request that need no master, and the texts of its answers (no ROS)."""

import doctest

import pytest

import drvs.server.answers
import drvs.server.request_check
from drvs.algorithms import AlgorithmError, default_algorithms
from drvs.common.status import BUSY, INVALID, RATE_LIMITED, Refusal
from drvs.server.answers import SharedReplies, busy_everywhere, forwarded, sent_to_none, watch_answer
from drvs.server.request_check import AlgorithmNames, check_supported, rate_limited, request_fields
from drvs.server.watch_table import CANCELLED, NOT_STANDING, RENEWED, STARTED

RED = 'colour:200,0,0,255,80,80'


@pytest.fixture(scope='module')
def known():
    return default_algorithms()


def test_the_doctests_pass():
    assert doctest.testmod(drvs.server.request_check).failed == 0
    assert doctest.testmod(drvs.server.answers).failed == 0


def test_a_known_algorithm_is_checked_in_full_an_unknown_one_by_its_syntax(known):
    names = AlgorithmNames(known)
    assert names.name(RED) == 'colour'
    assert names.name('someones_plugin:whatever it takes') == 'someones_plugin'
    with pytest.raises(AlgorithmError, match='colour PARAMS must be 6 comma-separated integers'):
        names.name('colour:red')
    with pytest.raises(AlgorithmError, match="got '9bad'$"):
        names.name('9bad')
    assert len(names) == 2  # refused strings are not remembered


def test_remembered_strings_are_bounded(known):
    names = AlgorithmNames(known, max_remembered=2)
    for text in ('a:1', 'b:2', 'c:3'):
        names.name(text)
    assert len(names) == 1  # full: forgotten, then the new one kept
    with pytest.raises(ValueError, match='max_remembered: must be at least 1, got 0'):
        AlgorithmNames(known, max_remembered=0)


@pytest.mark.parametrize(
    ('algorithm', 'region', 'callback', 'message'),
    [
        (RED, (1, 1, 0, 0), '/robot/cb', 'region_of_interest: min_x 1 is greater than max_x 0'),
        (
            RED,
            (0, 0, 1, 1),
            'relative/cb',
            "callback_service: 'relative/cb' is not a global ROS name (it must start with /)",
        ),
        (
            '9bad',
            (0, 0, 1, 1),
            '/robot/cb',
            'algorithm: expected NAME[:PARAMS] with NAME a letter then letters, digits or _, '
            "e.g. colour:0,0,150,80,80,255, got '9bad'",
        ),
    ],
)
def test_request_fields_refuse_invalid_naming_the_field(known, algorithm, region, callback, message):
    with pytest.raises(Refusal) as refused:
        request_fields(AlgorithmNames(known), algorithm, region, callback)
    assert (refused.value.status, refused.value.message) == (INVALID, message)


def test_rate_limited_names_the_caller_or_its_absence():
    refusal = rate_limited('', 0.25, 50.0, 100)
    assert (refusal.status, refusal.retry_after) == (RATE_LIMITED, 0.25)
    assert refusal.message == (
        'rate limited: (no caller id) sends more than 50 requests/s (bursts of 100); retry after 0.250 s'
    )


def test_nothing_is_unsupported_while_nobody_is_registered():
    check_supported([], 'anything')


@pytest.mark.parametrize(
    ('change', 'serving', 'message'),
    [
        (STARTED, 0, "watch 'w' started; 0 vision systems serve it"),
        (RENEWED, 1, "watch 'w' renewed; 1 vision system serves it"),
        (STARTED, 3, "watch 'w' started; 3 vision systems serve it"),
        (CANCELLED, 0, "watch 'w' cancelled"),
        (NOT_STANDING, 0, "no watch 'w' stands: nothing to cancel"),
    ],
)
def test_watch_answers(change, serving, message):
    assert watch_answer(change, 'w', serving) == message


def test_acknowledgement_texts():
    assert forwarded(0, 2) == 'forwarded to 0 vision systems; 2 busy vision system(s) skipped'
    assert sent_to_none(False, 'sift') == 'no vision system covers the region of interest'
    busy = busy_everywhere(2, 'sift', 10, 0.5)
    assert (busy.status, busy.retry_after) == (BUSY, 0.5)
    assert busy.message == (
        "busy: all 2 vision systems that cover the region and run 'sift' have 10 forwards pending; "
        'try again later'
    )


def test_shared_replies_are_made_once_per_key_and_bounded():
    made = []

    def make():
        made.append(object())
        return made[-1]

    replies = SharedReplies(max_kept=2)
    assert replies.get(1, make) is replies.get(1, make)
    replies.get(2, make)
    replies.get(3, make)
    replies.get(3, make)
    assert (len(replies), len(made)) == (2, 4)
