"""drvs_ask: one question to DRVS from a terminal, with the vision systems' outlines printed, and
an exit code that tells found, nothing found, no coverage, refused and no server apart (no master
and bad options: test_user_errors.py)."""

import re
from pathlib import Path

import pytest

from drvs.testing import RosHarness, wait_for
from drvs.tools.ask import (
    EXIT_CODES,
    FOUND,
    NO_MASTER,
    NO_SERVER,
    NOT_COVERED,
    NOTHING_FOUND,
    REFUSED,
    USAGE,
    format_callback,
    parse_args,
)

pytestmark = pytest.mark.shared_master  # see test/conftest.py

WORLD = 'test/worlds/small.yaml'
STATION = 'colour:0,0,150,80,80,255'


@pytest.fixture(scope='module')
def drvs():
    """The server and vs2 on a master of their own, for the tests that only ask."""
    with RosHarness() as ros:
        server = ros.start_node('nodes/drvs_server', name='drvs')
        ros.wait_for_service('/drvs/detect_object_boundary', node=server)
        camera = ros.start_node('nodes/vision_system', name='vs2', params={'world': WORLD})
        wait_for(
            lambda: 'forwarded to 1 vision system' in ros.run(f'drvs_ask {STATION} --wait 0.1').stdout,
            60,
            'vs2 to register',
            interval=0.5,
            on_timeout=ros.describe,
        )
        assert camera.running()
        yield ros


PAGE = Path(__file__).resolve().parents[2] / 'docs' / 'tutorials' / 'by-hand.md'


def test_drvs_ask_prints_the_acknowledgement_and_the_outlines(drvs: RosHarness):
    result = drvs.run(f'drvs_ask {STATION} --roi 0 0 4 3 --wait 2')  # it waits all of --wait
    assert result.returncode == FOUND, result.stdout + result.stderr
    lines = result.stdout.splitlines()
    assert lines[0] == "accepted: True, vision_systems: 1, message: 'forwarded to 1 vision system'"
    assert lines[1].startswith('/vs2/detect_object_boundary (frame at ')
    assert lines[1].endswith('): 1 object(s)')
    # The station is a 0.4 x 0.3 box at (3.5, 2.5).
    bounds = lines[2].split()
    assert float(bounds[3].split('..')[0]) == pytest.approx(3.3, abs=0.03)
    assert float(bounds[5].split('..')[1]) == pytest.approx(2.65, abs=0.03)
    assert lines[-1] == '1 of 1 vision system(s) called back within 2.0 s'


def test_drvs_ask_fused_prints_one_answer_with_a_track(drvs: RosHarness):
    result = drvs.run(f'drvs_ask --fused {STATION} --roi 0 0 4 3 --wait 5')
    assert result.returncode == FOUND, result.stdout + result.stderr
    lines = result.stdout.splitlines()
    assert lines[1].startswith('/drvs (frame at ') and lines[1].endswith('): 1 object(s)')
    assert lines[2] == '  fused: OK: 1 of 1 answered'
    assert re.fullmatch(
        r'      track #\d+, velocity \(-?0\.\d\d, -?0\.\d\d\) m/s.*seen by /vs2/detect_object_boundary',
        lines[4],
    )
    assert lines[-1] == '1 of 1 vision system(s) called back within 5.0 s'
    # Nothing there: the camera says so (fused), so the one answer comes at once, empty.
    empty = drvs.run(f'drvs_ask --fused {STATION} --roi 0 0 1 1 --wait 5')
    assert empty.returncode == NOTHING_FOUND, empty.stdout + empty.stderr
    assert '/drvs (frame at ' in empty.stdout and ': 0 object(s)' in empty.stdout


def test_drvs_ask_refuses_a_bad_algorithm_before_asking(ros: RosHarness):
    result = ros.run("drvs_ask 'colour:1,2'")
    assert result.returncode == USAGE
    assert 'algorithm: colour PARAMS must be 6 comma-separated integers' in result.stderr


def test_drvs_ask_says_what_to_do_when_no_server_runs(ros: RosHarness):
    result = ros.run(f'drvs_ask {STATION} --timeout 1')
    assert result.returncode == NO_SERVER
    assert 'is DRVS running?' in result.stderr


def test_drvs_ask_tells_nothing_found_no_coverage_and_a_refusal_apart(drvs: RosHarness):
    # vs2 sees the right half of the 4 x 3 floor; nothing there is magenta.
    nothing = drvs.run('drvs_ask colour:200,0,200,255,60,255 --roi 2 0 4 3 --wait 1')
    assert nothing.returncode == NOTHING_FOUND, nothing.stdout + nothing.stderr
    assert nothing.stdout.splitlines()[-1] == '0 of 1 vision system(s) called back within 1.0 s'
    assert nothing.stderr == (
        'drvs_ask: nothing found: 1 vision system(s) asked, none found anything within 1 s\n'
    )

    nowhere = drvs.run(f'drvs_ask {STATION} --roi 20 20 21 21')
    assert nowhere.returncode == NOT_COVERED, nowhere.stdout + nowhere.stderr
    assert nowhere.stdout == (
        "accepted: True, vision_systems: 0, message: 'no vision system covers the region of interest'\n"
    )
    assert nowhere.stderr == (
        'drvs_ask: not asked: no vision system covers the region of interest '
        '(`rostopic echo /drvs/registry` lists the fields of view)\n'
    )

    # A final refusal stops at once, with its status name.
    refused = drvs.run('drvs_ask nosuch:1 --timeout 30')
    assert refused.returncode == REFUSED, refused.stdout + refused.stderr
    message = "algorithm: no registered vision system runs 'nosuch'; available: "
    assert refused.stdout.startswith(f'accepted: False, vision_systems: 0, message: "{message}')
    assert refused.stderr.startswith(f'drvs_ask: refused (UNSUPPORTED): {message}')
    assert 'retrying' not in refused.stderr


def test_the_exit_codes_are_the_same_in_help_and_on_the_docs_page(capsys):
    with pytest.raises(SystemExit):
        parse_args(['--help'])
    help_text = capsys.readouterr().out
    for code, meaning in EXIT_CODES.items():
        assert f'  {code:<3}  {meaning}\n' in help_text + '\n'
        assert re.search(rf'^\| {code} \| \S', PAGE.read_text(), re.MULTILINE), code
    assert (FOUND, NOTHING_FOUND, USAGE, NOT_COVERED, REFUSED, NO_SERVER, NO_MASTER) == tuple(range(7))


def test_drvs_ask_retries_while_rate_limited(ros: RosHarness):
    server = ros.start_node('nodes/drvs_server', name='drvs', params={'max_requests_per_s': 0.2, 'burst': 1})
    ros.wait_for_service('/drvs/detect_object_boundary', node=server)
    # Two asks from one caller id: the second, within 5 s, is refused, then retried until served.
    ask = f'drvs_ask {STATION} --wait 0 --timeout 30 __name:=asker'
    result = ros.run(f'{ask}; {ask}', timeout=90)
    assert 'RATE_LIMITED, retrying: rate limited: /asker' in result.stderr, result.stdout + result.stderr
    assert result.stdout.count("message: 'no vision system covers the region of interest'") == 2


def test_a_measured_height_is_printed_with_the_bounds():
    from drvs.ros.conversions import points_to_detected_object
    from drvs.srv import CallbackCoordinatesRequest

    square = [(1.0, 2.0), (1.5, 2.0), (1.5, 2.5), (1.0, 2.5)]
    request = CallbackCoordinatesRequest(
        vision_system='/vs1/detect_object_boundary',
        objects=[points_to_detected_object(square, height=0.5), points_to_detected_object(square)],
    )
    lines = format_callback(request).splitlines()
    assert lines[1] == '  [0] bounds x 1.000..1.500, y 2.000..2.500, 0.500 m high'
    assert lines[3] == '  [1] bounds x 1.000..1.500, y 2.000..2.500'  # unknown: not printed
