"""Clients go back to their first server (~servers, ~server_return; docs/registry.md "Replicas"):
a vision system whose first server was not there at its start registers through the second, and
through the first once it is up."""

from drvs.testing import echo, wait_for

WORLD = 'test/worlds/small.yaml'


def registered(ros, server):
    """The vision systems the server in namespace ``server`` lists on its registry topic."""
    return [entry['service_name'] for entry in echo(ros, f'{server}/registry')['vision_systems']]


def test_a_vision_system_registers_through_its_first_server_once_that_is_up(graph):
    ros = graph
    second = ros.start_node('nodes/drvs_server', name='drvs_b', params={'lease': 2.0})
    ros.wait_for_service('/drvs_b/detect_object_boundary', node=second)
    ros.start_node('nodes/world_sim', name='world_sim', params={'world': WORLD})
    ros.start_node(
        'nodes/vision_system',
        name='vs1',
        params={'world': WORLD, 'servers': ['/drvs', '/drvs_b'], 'server_return': 1.0},
    )
    wait_for(
        lambda: registered(ros, '/drvs_b') == ['/vs1/detect_object_boundary'],
        30,
        'vs1 through /drvs_b',
        0.2,
        ros.describe,
    )

    first = ros.start_node('nodes/drvs_server', name='drvs', params={'lease': 2.0})
    ros.wait_for_service('/drvs/detect_object_boundary', node=first)
    wait_for(
        lambda: registered(ros, '/drvs') == ['/vs1/detect_object_boundary'],
        30,
        'vs1 back through /drvs',
        0.2,
        ros.describe,
    )
