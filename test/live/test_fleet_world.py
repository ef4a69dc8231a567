"""The fleet worlds (worlds/warehouse.yaml, worlds/crossing.yaml) and world_sim driving a fleet.

The worlds are checked by computation, not by eye: the cameras' fields of view cover the
floor and overlap a little, and every robot's own colour model finds exactly its robot in
the rendered view of a camera that sees it (through the vision system's own code), with
the robots placed at random in the aisles. world_sim is checked live: one ``cmd_vel`` per
robot, and the simulated time it publishes on ``/clock`` under ``/use_sim_time``.
"""

import itertools
import json

import numpy as np
import pytest
from shapely.geometry import LineString, Polygon, box
from shapely.ops import unary_union

from drvs.algorithms import parse_algorithm
from drvs.ros.node_main import NoClock, wait_for_clock
from drvs.sim.scene import Scene
from drvs.sim.world import box_footprint
from drvs.sim.world_file import load_world
from drvs.testing import wait_for
from drvs.testing.harness import echo, read_json_lines, seconds
from drvs.vision.camera import PinholeCamera
from drvs.vision.pipeline import locate_objects

pytestmark = pytest.mark.shared_master  # see test/conftest.py

WAREHOUSE, CROSSING = 'worlds/warehouse.yaml', 'worlds/crossing.yaml'
FLEETS = [WAREHOUSE, CROSSING]
INSIDE = 0.05
"""Metres: a body counts as seen by a camera when its footprint lies this far inside the view."""


def views(world) -> dict[str, Polygon]:
    """Each camera's field of view on the floor, as registered with the DRVS server."""
    return {
        camera.name: Polygon(PinholeCamera.from_config(camera).floor_footprint(world.floor_size))
        for camera in world.vision_systems
    }


def test_the_warehouse_is_a_building_with_aisles_a_fleet_and_people():
    world = load_world(WAREHOUSE)
    width, depth = world.floor_size
    assert width >= 20 and depth >= 12
    assert len(world.vision_systems) >= 30 and len(world.robots) >= 6
    assert len({robot.station.name for robot in world.robots}) == len(world.robots)
    shelves = [body for body in world.objects if body.kind == 'static']
    assert len(shelves) >= 16 and {body.colour for body in shelves} == {(90, 90, 90)}
    assert 3 <= len([body for body in world.objects if body.kind == 'human' and body.moving]) <= 4


def test_the_crossing_is_small_enough_for_every_test_run():
    world = load_world(CROSSING)
    assert len(world.robots) == 2 and 2 <= len(world.vision_systems) <= 4
    assert all(camera.resolution[0] * camera.resolution[1] <= 320 * 240 for camera in world.vision_systems)


def test_the_routes_of_the_fleet_cross():
    for path in FLEETS:
        world = load_world(path)
        routes = [(robot.name, robot.body.position, robot.station.position) for robot in world.robots]
        crossing = {name for (name, *route), (other, *other_route) in itertools.combinations(routes, 2)
                    for name in (name, other) if _cross(route, other_route)}  # fmt: skip
        assert crossing == {robot.name for robot in world.robots}, path


def _cross(a, b) -> bool:
    return LineString(a).crosses(LineString(b))


@pytest.mark.parametrize('path', FLEETS)
def test_the_cameras_cover_the_floor_and_their_views_overlap_a_little(path):
    world = load_world(path)
    seen = views(world)
    floor = box(0, 0, *world.floor_size)
    assert floor.difference(unary_union(list(seen.values()))).area < 1e-9
    for name, view in seen.items():
        others = [other for other_name, other in seen.items() if other_name != name]
        shared = [view.intersection(other).area for other in others]
        assert max(shared) > 0, f'{name} overlaps no other camera'
        assert max(shared) < 0.2 * view.area, f'{name} shares much of its view with another camera'
        assert view.difference(unary_union(others)).area > 0.5 * view.area, f'{name} sees little of its own'


def random_placement(world, rng) -> dict[str, tuple[float, float, float]]:
    """A pose for every robot, at random in the free floor (clear of objects, stations and each
    other by 5 cm); in the warehouse, in an aisle (rows of cameras are above the aisles)."""
    floor = box(0, 0, *world.floor_size)
    taken = [Polygon(body.footprint()) for body in world.objects]
    taken += [Polygon(robot.station.footprint()) for robot in world.robots]
    aisles = sorted({camera.position[1] for camera in world.vision_systems})
    poses = {}
    for robot in world.robots:
        while True:
            x = rng.uniform(0.3, world.floor_size[0] - 0.3)
            y = rng.choice(aisles) + rng.uniform(-0.75, 0.75)
            yaw = rng.uniform(-np.pi, np.pi)
            footprint = Polygon(box_footprint((x, y), robot.body.size, yaw))
            if floor.contains(footprint) and all(footprint.distance(other) > 0.05 for other in taken):
                break
        taken.append(footprint)
        poses[robot.name] = (x, y, yaw)
    return poses


@pytest.mark.parametrize('path', FLEETS)
def test_each_robot_finds_itself_and_no_other_body_in_the_view_of_every_camera_that_sees_it(path):
    world = load_world(path)
    seen = views(world)
    whole_floor = (0.0, 0.0, *world.floor_size)
    cameras = {camera.name: PinholeCamera.from_config(camera) for camera in world.vision_systems}
    robot_model = parse_algorithm(world.colour_models['robot'])
    rng = np.random.default_rng(7)
    with Scene(world) as scene:
        for _ in range(3):
            poses = random_placement(world, rng)
            scene.apply_poses(poses)
            footprints = {name: Polygon(box_footprint(pose[:2], world.fleet_robot(name).body.size, pose[2]))
                          for name, pose in poses.items()}  # fmt: skip
            frames = {}
            for robot in world.robots:
                footprint = footprints[robot.name]
                seers = [name for name, view in seen.items() if view.buffer(-INSIDE).contains(footprint)]
                assert seers, f'no camera sees {robot.name} at {poses[robot.name]}'
                own = parse_algorithm(robot.colour_models['self'])
                for name in seers:
                    frame = frames.setdefault(name, scene.render(cameras[name]))
                    (found,) = [Polygon(outline) for outline in locate_objects(frame, own, whole_floor)]
                    assert found.intersection(footprint).area > 0.6 * footprint.area, (robot.name, name)
                    assert found.centroid.distance(footprint.centroid) < 0.1, (
                        robot.name,
                        name,
                    )  # shelves hide some
            for name, frame in frames.items():  # the shared model: robots only, each one once
                outlines = [Polygon(outline) for outline in locate_objects(frame, robot_model, whole_floor)]
                assert all(any(o.intersects(fp) for fp in footprints.values()) for o in outlines), name
                for footprint in footprints.values():
                    if seen[name].buffer(-INSIDE).contains(footprint):
                        assert (
                            sum(o.intersection(footprint).area > 0.5 * footprint.area for o in outlines) == 1
                        )


@pytest.mark.parametrize('path', FLEETS)
def test_each_station_model_finds_its_station_only(path):
    world = load_world(path)
    seen = views(world)
    whole_floor = (0.0, 0.0, *world.floor_size)
    with Scene(world) as scene:
        for robot in world.robots:
            station = Polygon(robot.station.footprint())
            model = parse_algorithm(robot.colour_models['station'])
            (camera,) = [c for c in world.vision_systems if seen[c.name].buffer(-INSIDE).contains(station)][
                :1
            ]
            frame = scene.render(PinholeCamera.from_config(camera))
            (found,) = [Polygon(outline) for outline in locate_objects(frame, model, whole_floor)]
            assert found.intersection(station).area > 0.6 * station.area


# -- node_main under /use_sim_time ---------------------------------------------------------------
class FakeRospy:
    """The rospy calls wait_for_clock makes: /use_sim_time, the time, shutdown."""

    def __init__(self, sim_time, times, shutdown=False):
        self.sim_time, self.times, self.shutdown = sim_time, iter(times), shutdown

    def get_param(self, name, default):
        assert name == '/use_sim_time'
        return self.sim_time

    def get_time(self):
        return next(self.times)

    def is_shutdown(self):
        return self.shutdown


def test_a_node_waits_for_the_first_clock_under_use_sim_time_and_gives_up_naming_world_sim(monkeypatch):
    import drvs.ros.node_main as node_main

    monkeypatch.setattr(node_main, 'rospy', FakeRospy(True, [0.0, 0.0, 12.5]))
    assert wait_for_clock(5.0)
    monkeypatch.setattr(node_main, 'rospy', FakeRospy(False, []))
    assert wait_for_clock(5.0)  # real time: nothing to wait for
    monkeypatch.setattr(node_main, 'rospy', FakeRospy(True, itertools.repeat(0.0), shutdown=True))
    assert not wait_for_clock(5.0)
    monkeypatch.setattr(node_main, 'rospy', FakeRospy(True, itertools.repeat(0.0)))
    with pytest.raises(NoClock) as error:
        wait_for_clock(0.1)
    assert str(error.value) == (
        '/use_sim_time is true and no /clock came in 0.1 s: the simulated time is published by world_sim '
        '(nodes/world_sim): start it, or set /use_sim_time false for real time'
    )


# -- world_sim, live --------------------------------------------------------------------------------
def truth_of(ros) -> dict:
    return json.loads(echo(ros, '/world_sim/ground_truth')['data'])


def drive(ros, robot: str, vx: float, vy: float):
    """``rostopic pub`` of a constant command to ``/<robot>/cmd_vel`` at 10 Hz until stopped."""
    twist = f'{{linear: {{x: {vx}, y: {vy}}}}}'
    argv = ['rostopic', 'pub', '-r', '10', f'/{robot}/cmd_vel', 'geometry_msgs/Twist', twist]
    return ros.spawn(f'pub_{robot}', argv)


def test_world_sim_drives_each_robot_from_its_own_cmd_vel_and_sends_tf_for_each(ros):
    sim = ros.start_node('nodes/world_sim', name='world_sim', params={'world': CROSSING})
    wait_for(
        lambda: {'/robot1/cmd_vel', '/robot2/cmd_vel'} <= set(ros.master.subscriptions_of('/world_sim')),
        30,
        "world_sim subscribing to each robot's cmd_vel",
        on_timeout=ros.describe,
    )
    publisher = drive(ros, 'robot2', 0.3, 0.0)
    wait_for(lambda: truth_of(ros)['robots']['robot2']['travelled'] > 0.3, 60, 'robot2 driving',
             on_timeout=ros.describe)  # fmt: skip
    publisher.stop()
    truth = truth_of(ros)
    assert truth['robots']['robot1']['travelled'] == 0.0 and truth['robot']['position'] == [0.8, 1.0]
    assert truth['robots']['robot2']['position'][1] == pytest.approx(4.0)
    moving = {transform['child_frame_id'] for transform in echo(ros, '/tf')['transforms']}
    assert moving == {'robot1', 'robot2', 'walker'}  # on /tf_static: the crate and the stations
    assert sim.interrupt() == 0, sim.describe()


def test_world_sim_refuses_a_slow_world_without_use_sim_time(ros):
    sim = ros.start_node(
        'nodes/world_sim', name='world_sim', params={'world': CROSSING, 'real_time_factor': 0.5}
    )
    assert sim.process.wait(60) == 2, sim.describe()
    assert (
        'world_sim: real_time_factor 0.5 (from ~real_time_factor) runs the world on simulated time: set '
        '/use_sim_time true before starting the nodes (`rosparam set /use_sim_time true`), or run at '
        'real_time_factor 1'
    ) in sim.log()


def test_under_use_sim_time_world_sim_is_the_clock_of_every_node(ros):
    ros.master.call('setParam', '/use_sim_time', True)
    # The server starts first: node_main builds it once world_sim's first /clock has come.
    server = ros.start_node('nodes/drvs_server', name='drvs')
    output = ros.root / 'probe.jsonl'
    topics = ['/clock', '/world_sim/ground_truth']
    ros.start_node(
        'test/nodes/clock_probe.py', name='probe', params={'output': output, 'topics': json.dumps(topics)}
    )
    ros.start_node('nodes/world_sim', name='world_sim', params={'world': CROSSING, 'real_time_factor': 0.5})
    ros.wait_for_service('/drvs/detect_object_boundary', node=server, timeout=60)

    def lines(topic):
        return [line for line in read_json_lines(output) if line['topic'] == topic]

    wait_for(lambda: len(lines('/world_sim/ground_truth')) >= 20, 60, 'ground truth', on_timeout=ros.describe)
    clock = [seconds(line['data']['clock']) for line in lines('/clock')]
    assert clock == sorted(clock) and len(set(clock)) == len(clock)
    truths = [json.loads(line['data']['data']) for line in lines('/world_sim/ground_truth')]
    # Stamped with the simulated time it publishes on /clock, which started at world_sim's start
    # and runs on with the simulation: stamp - time is that start, for every step.
    for truth in truths:
        assert min(abs(truth['stamp'] - tick) for tick in clock) < 1e-6
    assert max(t['stamp'] - t['time'] for t in truths) - min(t['stamp'] - t['time'] for t in truths) < 1e-6
    # Another node's clock (rospy.get_time()) is that time: a value world_sim published.
    # (Up to the newest tick the probe wrote: rospy's own /clock subscription may be a tick ahead
    # of the probe's while the file is read.)
    times = [line['rostime'] for line in read_json_lines(output) if 0 < line['rostime'] <= clock[-1]]
    assert times and all(min(abs(time - tick) for tick in clock) < 1e-6 for time in times)
