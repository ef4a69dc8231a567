"""The simulation's cameras as ROS camera feeds: a topic-fed vision system sees what a rendering one sees.

sim_camera publishes a world's cameras as images, CameraInfo and tf; a vision
system with ``_source:=topic`` consumes them like any camera's. Its outlines must
agree with the vision system that renders its own view, and, through a lens,
still lie where the objects are.
"""

import pytest
from shapely.geometry import Polygon

from drvs.sim.world_file import load_world
from drvs.testing import read_json_lines, wait_for
from drvs.testing.detect import detect

pytestmark = pytest.mark.shared_master  # see test/conftest.py

CALLBACK = '/robot/callback_coordinates'


def ask(service, algorithm, request_id, region=(0.0, 0.0, 4.0, 3.0)):
    return detect(service, algorithm, region, request_id)


def start_topic_vision_system(ros, name, camera, **params):
    """A vision system on sim_camera's feed of ``camera``, with depth; waits until it has frames."""
    node = ros.start_node(
        'nodes/vision_system',
        name=name,
        params={'source': 'topic', 'depth': True, **params},
        remap={
            'image': f'/{camera}/image_raw',
            'camera_info': f'/{camera}/camera_info',
            'depth': f'/{camera}/depth/image_raw',
        },
    )
    service = f'/{name}/detect_object_boundary'
    ros.wait_for_service(service, node=node)
    wait_for(
        lambda: ask(service, 'colour:0,0,0,1,1,1', 'warm-up').accepted,
        30,
        f'{name} to receive frames',
        on_timeout=ros.describe,
    )
    return node


def outlines(output, request_id, ros):
    (callback,) = wait_for(
        lambda: [c for c in read_json_lines(output) if c['request_id'] == request_id],
        30,
        f'the callback for {request_id}',
        on_timeout=ros.describe,
    )
    return [Polygon(points) for points in callback['objects']]


def start_recorder(ros):
    output = ros.root / 'callbacks.jsonl'
    recorder = ros.start_node('test/nodes/callback_recorder.py', name='recorder', params={'output': output})
    ros.wait_for_service(CALLBACK, node=recorder)
    return output


def test_topic_mode_outlines_agree_with_render_mode_within_2_cm(graph):
    ros, path = graph, 'test/worlds/small.yaml'
    world = load_world(path)
    ros.start_node('nodes/sim_camera', name='sim_camera', params={'world': path, 'cameras': 'vs1'})
    rendering = ros.start_node('nodes/vision_system', name='vs1', params={'world': path})
    ros.wait_for_service('/vs1/detect_object_boundary', node=rendering)
    start_topic_vision_system(ros, 'vs1_topic', 'vs1')
    output = start_recorder(ros)

    for role, name in (('obstacle', 'crate'), ('self', 'robot')):
        model = world.colour_models[role]
        ask('/vs1/detect_object_boundary', model, f'render-{role}')
        ask('/vs1_topic/detect_object_boundary', model, f'topic-{role}')
        (rendered,) = outlines(output, f'render-{role}', ros)
        (topic,) = outlines(output, f'topic-{role}', ros)
        assert topic.hausdorff_distance(rendered) <= 0.02, name
        truth = Polygon(world.objects[0].footprint() if name == 'crate' else world.robot.footprint())
        assert topic.centroid.distance(truth.centroid) <= 0.03, name  # 160x120: 3 cm a pixel


def test_a_distorted_feed_gives_outlines_within_2_cm_of_the_truth(graph):
    ros, path = graph, 'test/worlds/lens.yaml'
    world = load_world(path)
    assert world.camera('vs1').distortion  # the feed really is distorted
    ros.start_node('nodes/sim_camera', name='sim_camera', params={'world': path, 'rate': 3.0})
    start_topic_vision_system(ros, 'vs1_topic', 'vs1', frame_timeout=2.0)
    output = start_recorder(ros)
    for role, body in (('obstacle', world.objects[0]), ('station', world.station), ('self', world.robot)):
        ask('/vs1_topic/detect_object_boundary', world.colour_models[role], role)
        (outline,) = outlines(output, role, ros)
        assert outline.hausdorff_distance(Polygon(body.footprint())) <= 0.02, role


def test_a_camera_moving_on_tf_registers_its_new_field_of_view(graph):
    """small.yaml's rover rides a mount: sim_camera moves its optical frame on tf with every frame."""
    ros, path = graph, 'test/worlds/small.yaml'
    server = ros.start_node('nodes/drvs_server', name='drvs')
    ros.wait_for_service('/drvs/detect_object_boundary', node=server)
    ros.start_node('nodes/sim_camera', name='sim_camera', params={'world': path, 'cameras': 'rover'})
    node = start_topic_vision_system(ros, 'rover_topic', 'rover', depth=False, move_threshold=0.05)
    wait_for(
        lambda: node.log(tail=200).count('move /rover_topic/detect_object_boundary with field of view') >= 2,
        30,
        'the rover to register its moving field of view',
        on_timeout=node.describe,
    )
