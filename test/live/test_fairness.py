"""Fairness between callers (docs/design.md, "Forwarding"): while one caller floods a slow vision
system, it holds at most its fair share of that camera's forward places and is refused
RATE_LIMITED beyond it; another caller's requests to the same camera are all accepted and
forwarded."""

import threading

from drvs.common.status import ACCEPTED, BUSY, RATE_LIMITED
from drvs.msg import BoundingBox
from drvs.ros.service_client import ServiceClient
from drvs.srv import DetectObjectBoundary, DetectObjectBoundaryRequest
from drvs.testing import read_json_lines, wait_for

DETECT = '/drvs/detect_object_boundary'
COLOUR = 'colour:0,0,150,80,80,255'
FIELD_OF_VIEW = [[0, 0], [2, 0], [2, 2], [0, 2]]
POLITE_REQUESTS = 10


def request(request_id):
    return DetectObjectBoundaryRequest(
        algorithm=COLOUR,
        region_of_interest=BoundingBox(0.5, 0.5, 1.0, 1.0),
        callback_service='/robot/callback_coordinates',
        request_id=request_id,
    )


def test_a_flood_from_one_caller_leaves_room_for_another(graph, tmp_path):
    ros = graph
    # No per-caller rate limit to speak of: what refuses the flood is its share of the camera.
    server = ros.start_node(
        'nodes/drvs_server', name='drvs', params={'max_requests_per_s': 10000, 'burst': 10000}
    )
    ros.wait_for_service(DETECT, node=server)
    recorder = ros.start_node(
        'test/nodes/callback_recorder.py', name='robot', params={'output': tmp_path / 'callbacks.jsonl'}
    )
    ros.wait_for_service('/robot/callback_coordinates', node=recorder)
    output = tmp_path / 'cam.jsonl'
    ros.start_node(
        'test/nodes/fake_vision_system.py',
        name='cam',
        params={'output': output, 'field_of_view': FIELD_OF_VIEW, 'hang': 0.05},
    )
    wait_for(lambda: any(r['kind'] == 'register' for r in read_json_lines(output)), 30, 'cam registered')

    def forwarded():
        return {r['request_id'] for r in read_json_lines(output) if r['kind'] == 'forward'}

    flood_statuses = []
    stop = threading.Event()

    def flood():
        client = ServiceClient(DETECT, DetectObjectBoundary, 5.0, caller_id='/flood')
        try:
            number = 0
            while not stop.is_set():
                flood_statuses.append(client.call(request(f'flood{number}')).status)
                number += 1
        finally:
            client.close()

    flooder = threading.Thread(target=flood)
    flooder.start()
    polite = ServiceClient(DETECT, DetectObjectBoundary, 5.0, caller_id='/polite')
    try:
        wait_for(lambda: RATE_LIMITED in flood_statuses, 30, 'the flood to reach its share')
        answers = []
        for number in range(POLITE_REQUESTS):
            answers.append(polite.call(request(f'polite{number}')))
            if answers[-1].status != ACCEPTED:
                break
            wait_for(lambda n=number: f'polite{n}' in forwarded(), 30, f'polite{number} forwarded')
    finally:
        stop.set()
        flooder.join(30)
        polite.close()
    assert [(a.status, a.vision_systems) for a in answers] == [(ACCEPTED, 1)] * POLITE_REQUESTS, [
        a.message for a in answers
    ]
    assert flood_statuses.count(RATE_LIMITED) > 0 and BUSY not in flood_statuses
    assert flood_statuses.count(ACCEPTED) > POLITE_REQUESTS  # the flood was served too, up to its share
