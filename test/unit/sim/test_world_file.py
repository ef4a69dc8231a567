"""World files: the loader's values, defaults, and its refusals naming file, key and expectation."""

import copy
import doctest

import pytest
import yaml

import drvs.sim.world
import drvs.sim.world_file
import drvs.sim.world_sense
from drvs.sim.world import WorldError
from drvs.sim.world_file import load_world

BASE = {
    'floor': {'size': [4.0, 3.0]},
    'robot': {'position': [0.5, 1.5], 'size': [0.3, 0.3, 0.2], 'colour': [0, 200, 0], 'speed': 0.4},
    'station': {'position': [3.5, 2.5], 'size': [0.4, 0.3, 0.1], 'colour': [0, 0, 220]},
    'objects': [
        {
            'name': 'box1',
            'kind': 'static',
            'position': [2.0, 1.0],
            'size': [0.4, 0.6, 0.5],
            'colour': [60, 60, 60],
        },
        {
            'name': 'walker',
            'kind': 'human',
            'position': [3.0, 0.5],
            'size': [0.3, 0.3, 1.7],
            'colour': [220, 0, 0],
            'waypoints': [[3.0, 0.5], [3.0, 2.5]],
            'speed': 0.3,
        },
    ],
    'vision_systems': [{'name': 'vs1', 'position': [2.0, 1.5, 3.0], 'fov_deg': 60}],
    'colour_models': {
        'self': 'colour:0,150,0,80,255,80',
        'station': 'colour:0,0,150,80,80,255',
        'obstacle': 'colour:40,40,40,90,90,90',
        'human': 'colour:150,0,0,255,80,80',
    },
}


def write(tmp_path, data):
    path = tmp_path / 'world.yaml'
    path.write_text(yaml.safe_dump(data))
    return path


def edited(world, **changes):
    """A copy of ``world`` with ``changes``: 'station.position' or 'objects.0.kind' -> value
    (None: the key removed)."""
    data = copy.deepcopy(world)
    for path, value in changes.items():
        *parents, last = path.split('.')
        node = data
        for key in parents:
            node = node[int(key)] if isinstance(node, list) else node[key]
        last = int(last) if isinstance(node, list) else last
        if value is None:
            del node[last]
        else:
            node[last] = value
    return data


def changed(path_of_key, value):
    """BASE with one key replaced (value None: removed); path_of_key like 'objects.0.size'."""
    return edited(BASE, **{path_of_key: value})


def test_a_world_loads_with_defaults(tmp_path):
    world = load_world(write(tmp_path, BASE))
    assert world.floor_size == (4.0, 3.0)
    assert world.floor_colour == (255, 255, 255)
    assert world.robot.speed == 0.4 and world.robot.size == (0.3, 0.3, 0.2)
    walker = world.objects[1]
    assert walker.moving and walker.waypoints == ((3.0, 0.5), (3.0, 2.5)) and walker.speed == 0.3
    camera = world.camera('vs1')
    assert camera.resolution == (800, 600)
    assert camera.target == (2.0, 1.5, 0.0) and camera.up == (0.0, 1.0, 0.0)
    assert not camera.moving
    assert world.colour_models['human'] == 'colour:150,0,0,255,80,80'


def test_a_camera_names_its_site_or_none_does(tmp_path):
    assert load_world(write(tmp_path, BASE)).camera('vs1').site == ''  # one site
    second = {'name': 'vs2', 'position': [1.0, 1.5, 3.0], 'fov_deg': 60, 'site': 'b'}
    data = changed('vision_systems.0.site', 'a')
    data['vision_systems'].append(second)
    world = load_world(write(tmp_path, data))
    assert [(camera.name, camera.site) for camera in world.vision_systems] == [('vs1', 'a'), ('vs2', 'b')]


@pytest.mark.parametrize(
    'sites, message',
    [
        (
            ['a', None],
            "vision_system 'vs2'.site: missing: the other vision systems name their site (a); "
            "name this one's too",
        ),
        (
            ['a', 'b-1'],
            "vision_system 'vs2'.site: expected a site name (1 to 16 letters, digits or _), got 'b-1'",
        ),
        (['a', 2], "vision_system 'vs2'.site: expected a site name (1 to 16 letters, digits or _), got 2"),
    ],
)
def test_bad_sites_are_refused(tmp_path, sites, message):
    cameras = [
        {'name': name, 'position': [x, 1.5, 3.0], 'fov_deg': 60} | ({} if site is None else {'site': site})
        for name, x, site in zip(('vs1', 'vs2'), (2.0, 1.0), sites, strict=True)
    ]
    path = write(tmp_path, changed('vision_systems', cameras))
    with pytest.raises(WorldError) as error:
        load_world(path)
    assert str(error.value) == f'{path}: {message}'


@pytest.mark.parametrize('path', ['test/worlds/small.yaml', 'test/worlds/accuracy.yaml'])
def test_the_test_worlds_load(path):
    assert load_world(path).vision_systems


def test_a_camera_lens_is_read_as_plumb_bob_coefficients(tmp_path):
    data = changed('vision_systems.0.distortion', [-0.2, 0.05, 0.001, -0.001, 0])
    camera = load_world(write(tmp_path, data)).camera('vs1')
    assert camera.distortion == (-0.2, 0.05, 0.001, -0.001, 0.0)
    assert load_world(write(tmp_path, BASE)).camera('vs1').distortion == ()  # an ideal pinhole


@pytest.mark.parametrize(
    'key, value, message',
    [
        ('floor.size', [4.0], 'floor.size: expected 2 positive numbers [x, y], got [4.0]'),
        (
            'floor.colour',
            [60, 60, 60],
            'floor.colour: [60, 60, 60] is matched by colour_models.obstacle (colour:40,40,40,90,90,90); '
            'the floor must be a colour that no colour model matches',
        ),
        ('robot.speed', 0, 'robot.speed: expected a positive number, got 0'),
        (
            'station.colour',
            [0, 0, 300],
            'station.colour: expected 3 integers 0-255 [r, g, b], got [0, 0, 300]',
        ),
        (
            'objects.0.size',
            [0.4, 0.6],
            "object 'box1'.size: expected 3 positive numbers [x, y, z], got [0.4, 0.6]",
        ),
        ('objects.0.kind', 'robot', "object 'box1'.kind: expected static or human, got 'robot'"),
        ('objects.1.loop', 'no', "human 'walker'.loop: expected true or false, got 'no'"),
        (
            'objects.0.loop',
            False,
            "object 'box1'.loop: applies to humans only: add kind: human to make it walk "
            '(keys of a static object: name, kind, position, size, yaw, colour, decoy, shiny, bottom)',
        ),
        (
            'objects.0.wait_for_robot',
            True,
            "object 'box1'.wait_for_robot: applies to humans only: add kind: human to make it walk "
            '(keys of a static object: name, kind, position, size, yaw, colour, decoy, shiny, bottom)',
        ),
        ('objects.1.speed', None, "human 'walker'.speed: missing: how fast a human walks, m/s"),
        (
            'objects.1.waypoints',
            [[3.0, 0.5]],
            "human 'walker'.waypoints: expected a list of at least 2 points [[x, y], ...], got [[3.0, 0.5]]",
        ),
        (
            'objects.1.waypoints',
            [[3.0, 0.5], [3.0, 'x']],
            "human 'walker'.waypoints[1]: expected 2 numbers [x, y], got [3.0, 'x']",
        ),
        (
            'objects.0.name',
            'walker',
            "human 'walker'.name: 'walker' is the name of object 'walker' too; names must be unique",
        ),
        (
            'objects.0.name',
            'station',
            "object 'station'.name: 'station' is reserved for the station; choose another name",
        ),
        (
            'vision_systems.0.position',
            [2.0, 1.5, 0.0],
            "vision_system 'vs1'.position: expected a camera above the floor (z > 0), got [2.0, 1.5, 0.0]",
        ),
        (
            'vision_systems.0.resolution',
            [800],
            "vision_system 'vs1'.resolution: expected 2 integers 16-4096 [width, height], got [800]",
        ),
        (
            'vision_systems.0.fov_deg',
            180,
            "vision_system 'vs1'.fov_deg: expected a vertical field of view between 1 and 170 degrees, "
            'got 180.0',
        ),
        (
            'vision_systems.0.speed',
            0.5,
            "vision_system 'vs1'.waypoints: missing: a moving mount needs both waypoints and speed",
        ),
        (
            'vision_systems.0.name',
            'vs-1',
            'vision_systems[0].name: expected a ROS node name (letters, digits, _; starting with a letter), '
            "got 'vs-1'",
        ),
        (
            'vision_systems.0.distortion',
            [-0.2, 0.05],
            "vision_system 'vs1'.distortion: expected 5 numbers [k1, k2, p1, p2, k3], got [-0.2, 0.05]",
        ),
        (
            'vision_systems.0.distortion',
            [-20.0, 0, 0, 0, 0],
            "vision_system 'vs1'.distortion: expected plumb_bob coefficients [k1, k2, p1, p2, k3], each "
            'within +-10, got [-20.0, 0.0, 0.0, 0.0, 0.0]',
        ),
        ('colour_models.human', None, 'colour_models.human: missing (roles: self, station, obstacle, human)'),
        (
            'colour_models.self',
            'colour:1,2',
            'colour_models.self: algorithm: colour PARAMS must be 6 '
            "comma-separated integers RMIN,GMIN,BMIN,RMAX,GMAX,BMAX, got 2 value(s) in '1,2'",
        ),
        (
            'lights',
            'on',
            'lights: unknown key (keys of a world file: floor, robot, station, robots, objects, '
            'vision_systems, colour_models, real_time_factor)',
        ),
        ('vision_systems', None, 'vision_systems: missing'),
        ('objects', {'box': 1}, "objects: expected a list, got {'box': 1}"),
    ],
)
def test_bad_worlds_are_refused_naming_file_entry_and_key(tmp_path, key, value, message):
    path = write(tmp_path, changed(key, value))
    with pytest.raises(WorldError) as error:
        load_world(path)
    assert str(error.value) == f'{path}: {message}'
    assert isinstance(error.value, ValueError)  # callers that catch ValueError keep working
    assert [str(problem) for problem in error.value.problems] == [message]


def test_a_missing_file_is_named(tmp_path):
    with pytest.raises(WorldError) as error:
        load_world(tmp_path / 'none.yaml')
    assert (
        str(error.value) == f'{tmp_path / "none.yaml"}: cannot read the world file: No such file or directory'
    )


@pytest.mark.parametrize(
    'text, message',
    [
        (
            'floor: [',
            "not valid YAML: line 1, column 9: expected the node content, but found '<stream end>' "
            '(while parsing a flow node at line 1, column 9)',
        ),
        (
            'floor: {size: [4, 3]}\nfloor: {size: [5, 3]}\n',
            "not valid YAML: line 2, column 1: 'floor' is given twice (while reading a mapping at line 1, "
            'column 1)',
        ),
        (
            '',
            'expected a mapping with the keys floor, robot, station, robots, objects, vision_systems, '
            'colour_models, real_time_factor, got None',
        ),
    ],
)
def test_bad_yaml_is_refused_in_one_line(tmp_path, text, message):
    path = tmp_path / 'bad.yaml'
    path.write_text(text)
    with pytest.raises(WorldError) as error:
        load_world(path)
    assert str(error.value) == f'{path}: {message}'


def test_keys_merged_from_an_anchor_may_be_overridden(tmp_path):
    data = changed('objects', None)
    text = yaml.safe_dump(data) + (
        'objects:\n'
        '- &box {name: b1, position: [1.0, 0.5], size: [0.4, 0.4, 0.5], colour: [60, 60, 60]}\n'
        '- {<<: *box, name: b2, position: [2.0, 0.5]}\n'
    )
    path = tmp_path / 'world.yaml'
    path.write_text(text)
    world = load_world(path)
    assert [(o.name, o.position, o.size) for o in world.objects] == [
        ('b1', (1.0, 0.5), (0.4, 0.4, 0.5)),
        ('b2', (2.0, 0.5), (0.4, 0.4, 0.5)),
    ]


def test_an_unknown_camera_is_named(tmp_path):
    world = load_world(write(tmp_path, BASE))
    with pytest.raises(WorldError) as error:
        world.camera('vs9')
    assert str(error.value) == f"{world.path}: vision_systems: no entry named 'vs9' (known: vs1)"


def test_doctests():
    for module in (drvs.sim.world, drvs.sim.world_file, drvs.sim.world_sense):
        assert doctest.testmod(module).failed == 0


# -- fleets: robots: ----------------------------------------------------------------------------
SHARED = {'obstacle': 'colour:40,40,40,90,90,90', 'human': 'colour:150,0,0,255,80,80'}
FLEET = {
    **{key: value for key, value in BASE.items() if key not in ('robot', 'station', 'colour_models')},
    'robots': [
        {
            'name': 'r1',
            'position': [0.5, 1.5],
            'size': [0.3, 0.3, 0.2],
            'colour': [0, 200, 0],
            'station': {'position': [3.5, 2.5], 'size': [0.4, 0.3, 0.1], 'colour': [0, 0, 220]},
            'colour_models': {'self': 'colour:0,170,0,30,230,30', 'station': 'colour:0,0,200,30,30,240'},
        },
        {
            'name': 'r2',
            'position': [0.5, 2.5],
            'size': [0.3, 0.3, 0.2],
            'colour': [0, 200, 160],
            'speed': 0.3,
            'station': {
                'name': 'dock2',
                'position': [3.5, 0.5],
                'size': [0.4, 0.3, 0.1],
                'colour': [160, 0, 220],
            },
            'colour_models': {
                'self': 'colour:0,170,130,30,230,190',
                'station': 'colour:130,0,200,190,30,240',
            },
        },
    ],
    'colour_models': {**SHARED, 'robot': 'colour:0,170,0,30,230,190'},
}
FLEET_KEYS = (
    '(keys of a robot of robots: name, position, size, yaw, colour, speed, tag, station, colour_models)'
)
FORMS = 'a world has robot: and station: (one robot) or robots: (a list of robots, each with its station)'


def test_a_fleet_loads_with_each_robot_its_station_and_its_complete_colour_models(tmp_path):
    world = load_world(write(tmp_path, FLEET))
    assert [(r.name, r.body.name, r.station.name) for r in world.robots] == [
        ('r1', 'r1', 'r1_station'),
        ('r2', 'r2', 'dock2'),
    ]
    r2 = world.fleet_robot('r2')
    assert r2.body.speed == 0.3 and r2.body.kind == 'robot' and r2.station.kind == 'station'
    assert r2.colour_models == {
        **FLEET['colour_models'],
        'self': 'colour:0,170,130,30,230,190',
        'station': 'colour:130,0,200,190,30,240',
    }
    assert (world.robot, world.station, world.colour_models) == (
        world.robots[0].body,
        world.robots[0].station,
        world.robots[0].colour_models,
    )
    assert world.real_time_factor == 1.0
    with pytest.raises(WorldError) as error:
        world.fleet_robot('robot')
    assert str(error.value) == f"{world.path}: robots: no entry named 'robot' (known: r1, r2)"


def test_the_single_form_is_a_fleet_of_one_named_robot(tmp_path):
    world = load_world(write(tmp_path, changed('real_time_factor', 0.5)))
    (robot,) = world.robots
    assert (robot.name, robot.body, robot.station) == ('robot', world.robot, world.station)
    assert robot.colour_models == BASE['colour_models'] == world.colour_models
    assert world.fleet_robot('robot') is robot
    assert world.real_time_factor == 0.5


def test_a_single_robot_may_have_a_shared_robot_model_and_a_fleet_of_one_needs_none(tmp_path):
    data = changed('colour_models.robot', 'colour:0,150,0,80,255,80')
    assert load_world(write(tmp_path, data)).colour_models['robot'] == 'colour:0,150,0,80,255,80'
    fleet = edited(FLEET, **{'colour_models.robot': None})
    fleet['robots'].pop()
    assert [robot.name for robot in load_world(write(tmp_path, fleet)).robots] == ['r1']


def fleet_changed(**changes):
    return edited(FLEET, **changes)


@pytest.mark.parametrize(
    'changes, messages',
    [
        ({'robot': BASE['robot']}, [f'robot: given with robots: too; {FORMS}']),
        ({'robots': None}, [f'robot: missing: {FORMS}']),
        ({'robots': []}, ['robots: expected a non-empty list, got []']),
        ({'robots.1': 'r2'}, ["robots[1]: expected a mapping, got 'r2'"]),
        ({'robots.1.name': None}, ['robots[1].name: missing']),
        (
            {'robots.1.name': 'r-2'},
            [
                'robots[1].name: expected a ROS node name (letters, digits, _; starting with a letter), '
                "got 'r-2'"
            ],
        ),
        (
            {'robots.1.name': 'r1'},
            ["robots 'r1'.name: 'r1' is the name of robots 'r1' too; names must be unique"],
        ),
        ({'robots.1.station': None}, ["robots 'r2'.station: missing"]),
        (
            {'robots.1.station.speed': 1},
            [
                "robots 'r2'.station.speed: does not apply: the station does not move "
                '(keys of the station: name, position, size, yaw, colour, tag)'
            ],
        ),
        (
            {'robots.1.station.position': [3.5, 5.0]},
            ["robots 'r2'.station.position: [3.5, 5.0] is outside the floor (x 0..4, y 0..3)"],
        ),
        (
            {'robots.1.colour_model': {}},
            [f"robots 'r2'.colour_model: unknown key; did you mean colour_models? {FLEET_KEYS}"],
        ),
        (
            {'robots.1.colour_models.station': None},
            ["robots 'r2'.colour_models.station: missing (roles: self, station)"],
        ),
        (
            {'robots.1.colour_models.human': 'colour:150,0,0,255,80,80'},
            [
                "robots 'r2'.colour_models.human: a shared role: put it in the top-level colour_models "
                "(a robot's own are self and station)"
            ],
        ),
        (
            {'colour_models.self': 'colour:0,170,0,30,230,30'},
            ["colour_models.self: with robots:, each robot has its own: put it in the robot's colour_models"],
        ),
        (
            {'colour_models.robot': None},
            [
                'colour_models.robot: missing: with several robots, a model that finds every robot '
                '(roles: obstacle, human, robot)'
            ],
        ),
        ({'colour_models.human': None}, ['colour_models.human: missing (roles: obstacle, human, robot)']),
        ({'real_time_factor': 0}, ['real_time_factor: expected a number in (0, 1], got 0']),
        ({'real_time_factor': 1.5}, ['real_time_factor: expected a number in (0, 1], got 1.5']),
        ({'real_time_factor': 'slow'}, ["real_time_factor: expected a number in (0, 1], got 'slow'"]),
        (
            {'vision_systems.0.name': 'r2'},
            ["vision_system 'r2'.name: 'r2' is the name of robots 'r2' too; node names must be unique"],
        ),
    ],
)
def test_bad_fleets_are_refused_naming_robot_and_key(tmp_path, changes, messages):
    path = write(tmp_path, fleet_changed(**changes))
    with pytest.raises(WorldError) as error:
        load_world(path)
    assert [str(problem) for problem in error.value.problems] == messages


def test_the_single_form_needs_both_robot_and_station(tmp_path):
    path = write(tmp_path, changed('station', None))
    with pytest.raises(WorldError) as error:
        load_world(path)
    assert str(error.value) == f'{path}: station: missing'
