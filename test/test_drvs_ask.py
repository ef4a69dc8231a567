"""drvs_ask: one question to DRVS from a terminal, with the vision systems' outlines printed."""

import pytest

from drvs.testing import RosHarness, wait_for

WORLD = 'test/worlds/small.yaml'
STATION = 'colour:0,0,150,80,80,255'


@pytest.fixture
def drvs(ros: RosHarness):
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
    return ros


def test_drvs_ask_prints_the_acknowledgement_and_the_outlines(drvs: RosHarness):
    result = drvs.run(f'drvs_ask {STATION} --roi 0 0 4 3 --wait 5')
    assert result.returncode == 0, result.stdout + result.stderr
    lines = result.stdout.splitlines()
    assert lines[0] == "accepted: True, vision_systems: 1, message: 'forwarded to 1 vision system'"
    assert lines[1].startswith('/vs2/detect_object_boundary (frame at ')
    assert lines[1].endswith('): 1 object(s)')
    # The station is a 0.4 x 0.3 box at (3.5, 2.5).
    bounds = lines[2].split()
    assert float(bounds[3].split('..')[0]) == pytest.approx(3.3, abs=0.03)
    assert float(bounds[5].split('..')[1]) == pytest.approx(2.65, abs=0.03)
    assert lines[-1] == '1 of 1 vision system(s) called back within 5.0 s'


def test_drvs_ask_refuses_a_bad_algorithm_before_asking(ros: RosHarness):
    result = ros.run("drvs_ask 'colour:1,2'")
    assert result.returncode == 2
    assert 'algorithm: colour PARAMS must be 6 comma-separated integers' in result.stderr


def test_drvs_ask_says_what_to_do_when_no_server_runs(ros: RosHarness):
    result = ros.run(f'drvs_ask {STATION} --timeout 1')
    assert result.returncode == 2
    assert 'is DRVS running?' in result.stderr


def test_drvs_ask_stops_at_once_on_an_invalid_request(drvs: RosHarness):
    result = drvs.run(f'drvs_ask {STATION} --roi 2 0 1 1 --timeout 30')
    assert result.returncode == 2, result.stdout + result.stderr
    assert result.stdout.splitlines()[0] == (
        "accepted: False, vision_systems: 0, message: 'region_of_interest: min_x 2 is greater than max_x 1'"
    )
    assert 'refused (INVALID)' in result.stderr
    assert 'retrying' not in result.stderr


def test_drvs_ask_retries_while_rate_limited(ros: RosHarness):
    server = ros.start_node('nodes/drvs_server', name='drvs', params={'max_requests_per_s': 0.2, 'burst': 1})
    ros.wait_for_service('/drvs/detect_object_boundary', node=server)
    # Two asks from one caller id: the second, within 5 s, is refused, then retried until served.
    ask = f'drvs_ask {STATION} --wait 0 --timeout 30 __name:=asker'
    result = ros.run(f'{ask}; {ask}', timeout=90)
    assert 'RATE_LIMITED, retrying: rate limited: /asker' in result.stderr, result.stdout + result.stderr
    assert result.stdout.count("message: 'no vision system covers the region of interest'") == 2
