"""Two sites on one registry database (docs/registry.md, "Sites"): server A (~site a) on master A,
server B (~site b) on master B, a vision system on master B registered through server B; a robot
on master A asks server A about what only B's camera sees and is called back, one-shot, by a
watch and fused, and so is a client of the HTTP gateway at site A. Neither master knows the
other's services: every call across goes to a rosrpc:// address."""

import json
import types
import urllib.request

import pytest

from drvs.gateway.tokens import add_token
from drvs.msg import BoundingBox
from drvs.ros.service_client import ServiceClient
from drvs.sim.world_file import load_world
from drvs.srv import DetectObjectBoundary, WatchObjectBoundary
from drvs.testing import RosHarness, echo, free_port, read_json_lines, wait_for

WORLD = 'test/worlds/small.yaml'
CALLBACK = '/robot/callback_coordinates'
CAMERA = '/vs1/detect_object_boundary'


@pytest.fixture(scope='module')
def sites(postgres, tmp_path_factory):
    """Both sites, started once for the module's tests (each asks with its own request ids)."""
    postgres.empty()
    folder = tmp_path_factory.mktemp('sites')
    output, token = folder / 'callbacks.jsonl', add_token(folder / 'tokens.json', 'robot')
    url = f'http://127.0.0.1:{free_port()}'
    a = RosHarness()
    try:
        b = RosHarness()
    except BaseException:  # the first master stopped too
        a.close()
        raise
    clients = []
    try:
        server = {'registry': postgres.dsn, 'unavailable_retry_after': 0.5}
        server_a = a.start_node('nodes/drvs_server', name='drvs', params={**server, 'site': 'a'})
        server_b = b.start_node('nodes/drvs_server', name='drvs', params={**server, 'site': 'b'})
        recorder = a.start_node('test/nodes/callback_recorder.py', name='robot', params={'output': output})
        camera = b.start_node('nodes/vision_system', name='vs1', params={'world': WORLD})
        gateway = a.start_node(
            'nodes/drvs_gateway',
            name='gateway',
            params={
                'bind': url.removeprefix('http://'),
                'rosbridge_bind': 'none',
                'tokens': folder / 'tokens.json',
                'request_timeout': 5.0,
            },
        )
        b.wait_for_service(CAMERA, node=camera)
        a.wait_for_service('/drvs/detect_object_boundary', node=server_a)
        b.wait_for_service('/drvs/detect_object_boundary', node=server_b)
        a.wait_for_service(CALLBACK, node=recorder)

        def describe():
            return a.describe() + '\n' + b.describe()

        detect = ServiceClient('/drvs/detect_object_boundary', DetectObjectBoundary, 10.0, a.master.uri)
        watch = ServiceClient('/drvs/watch_object_boundary', WatchObjectBoundary, 10.0, a.master.uri)
        clients += [detect, watch]
        world = load_world(WORLD)
        region = BoundingBox(0.0, 0.0, *world.floor_size)

        def ask(request_id, fused=False):
            return detect.call(
                DetectObjectBoundary._request_class(
                    algorithm=world.colour_models['obstacle'],
                    region_of_interest=region,
                    callback_service=CALLBACK,
                    request_id=request_id,
                    fused=fused,
                )
            )

        # Server A matches B's camera once it has followed the change log.
        wait_for(lambda: ask('probe').vision_systems == 1, 60, "server A matching B's camera", 0.2, describe)

        def http(path, body):
            request = urllib.request.Request(
                url + path,
                data=json.dumps(body).encode(),
                method='POST',
                headers={'Authorization': f'Bearer {token}', 'Content-Type': 'application/json'},
            )
            with urllib.request.urlopen(request, timeout=20) as response:
                return json.loads(response.read())

        a.wait_for_service('/gateway/callback_coordinates', node=gateway)
        yield types.SimpleNamespace(
            a=a,
            b=b,
            ask=ask,
            watch=watch,
            http=http,
            region=region,
            world=world,
            output=output,
            describe=describe,
        )
    finally:
        for client in clients:
            client.close()
        b.close()
        a.close()


def callbacks(sites, request_id):
    return [r for r in read_json_lines(sites.output) if r['request_id'] == request_id]


def test_neither_master_knows_the_other_sites_services(sites):
    assert sites.a.master.lookup_service(CAMERA) is None
    assert sites.b.master.lookup_service(CALLBACK) is None
    assert sites.b.master.lookup_service(CAMERA) is not None


def test_a_one_shot_request_at_site_a_is_answered_by_the_camera_of_site_b(sites):
    answer = sites.ask('one-shot')
    assert (answer.accepted, answer.vision_systems) == (True, 1), answer.message
    [callback] = wait_for(lambda: callbacks(sites, 'one-shot'), 30, 'the callback', 0.1, sites.describe)
    assert callback['vision_system'] == CAMERA and callback['objects'] and not callback['fused']


def test_a_watch_at_site_a_is_served_by_the_camera_of_site_b_and_ends_when_cancelled(sites):
    def watch(duration):
        return sites.watch.call(
            WatchObjectBoundary._request_class(
                algorithm=sites.world.colour_models['obstacle'],
                region_of_interest=sites.region,
                callback_service=CALLBACK,
                request_id='watch',
                period=0.2,
                duration=duration,
            )
        )

    answer = watch(30.0)
    assert (answer.accepted, answer.vision_systems) == (True, 1), answer.message
    wait_for(lambda: len(callbacks(sites, 'watch')) >= 3, 30, 'three callbacks', 0.1, sites.describe)
    assert {c['vision_system'] for c in callbacks(sites, 'watch')} == {CAMERA}
    assert watch(0.0).accepted
    # The withdrawal reached the camera at its address and named the watch as it stands there.
    wait_for(lambda: echo(sites.b, '/vs1/stats')['watches'] == 0, 20, 'the camera to drop the watch')


def test_a_fused_request_at_site_a_is_fused_by_server_a_from_the_camera_of_site_b(sites):
    answer = sites.ask('fused', fused=True)
    assert (answer.accepted, answer.vision_systems) == (True, 1), answer.message
    [callback] = wait_for(lambda: callbacks(sites, 'fused'), 30, 'the fused callback', 0.1, sites.describe)
    assert callback['fused'] and callback['answered'] == [CAMERA] and callback['objects'], callback
    assert callback['vision_system'] == '/drvs'


def test_a_client_of_the_gateway_at_site_a_is_answered_by_the_camera_of_site_b(sites):
    width, height = sites.world.floor_size
    answer = sites.http(
        '/v1/detect',
        {
            'algorithm': sites.world.colour_models['obstacle'],
            'region': {'min_x': 0, 'min_y': 0, 'max_x': width, 'max_y': height},
            'wait': 5,
        },
    )
    assert (answer['status'], answer['vision_systems']) == ('ACCEPTED', 1), answer
    [callback] = answer['callbacks']
    assert callback['vision_system'] == CAMERA and callback['objects'], callback
