"""World files checked for sense: impossible worlds refused with every problem named at once,
each by its entry's name and key; ``drvs_check_world`` reports them with exit 0 / 2."""

import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from test_world_file import edited

from drvs.sim.world import Problem, WorldError
from drvs.sim.world_file import load_world

REPO = Path(__file__).resolve().parents[3]
CHECK_WORLD = REPO / 'nodes' / 'drvs_check_world'
SHIPPED = sorted(REPO.glob('worlds/*.yaml')) + sorted(REPO.glob('test/worlds/*.yaml'))
# Case study 4.2: a 7 x 5.5 floor, two boxes and a human who walks into the gap between them.
OBSTACLES = yaml.safe_load((REPO / 'worlds/obstacles.yaml').read_text())
TAGS = yaml.safe_load((REPO / 'worlds/tags.yaml').read_text())
FLOOR = 'the floor (x 0..7, y 0..5.5)'
TOUCH = 'move one of them (bodies may touch, not overlap)'
WALK_THROUGH = 'or add through_obstacles: true if it should walk through'
STATIC_KEYS = '(keys of a static object: name, kind, position, size, yaw, colour, decoy, shiny, bottom)'
ROBOT_KEYS = '(keys of the robot: name, position, size, yaw, colour, speed, tag)'
UNSEEN = 'would register no field of view: move it over the floor or aim its target at it'


def problems_of(tmp_path, data) -> list[str]:
    path = tmp_path / 'world.yaml'
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(WorldError) as error:
        load_world(path)
    assert all(isinstance(problem, Problem) for problem in error.value.problems)
    return [str(problem) for problem in error.value.problems]


# Each impossible world of issue 14, and its kin, with the one problem it has.
IMPOSSIBLE = {
    'station off the floor': (
        {'station.position': [8.0, 0.8]},
        f'station.position: [8.0, 0.8] is outside {FLOOR}',
    ),
    'robot at x = -3': ({'robot.position': [-3, 2.65]}, f'robot.position: [-3.0, 2.65] is outside {FLOOR}'),
    'obstacle at x = 30.5': (
        {'objects.0.position': [30.5, 1.55]},
        f"object 'box_low'.position: [30.5, 1.55] is outside {FLOOR}",
    ),
    'robot half over the edge': (
        {'robot.position': [6.95, 2.65]},
        'robot.position: [6.95, 2.65] puts its footprint (x 6.8..7.1, y 2.5..2.8) past the edge of '
        f'{FLOOR}: move it 0.1 m further in',
    ),
    'obstacle on top of the robot': (
        {'objects.1.position': [0.9, 2.7]},
        f"object 'box_high'.position: overlaps robot: {TOUCH}",
    ),
    'station on an obstacle': (
        {'station.position': [3.3, 1.5]},
        f"object 'box_low'.position: overlaps station: {TOUCH}",
    ),
    'a human starting inside a box': (
        {'objects.2.position': [3.3, 3.3]},
        f"human 'walker'.position: overlaps object 'box_high': {TOUCH}",
    ),
    'a human waypoint inside a box': (
        {'objects.2.waypoints': [[4.3, 2.65], [3.3, 2.0]]},
        f"human 'walker'.waypoints[1]: [3.3, 2.0] puts it inside object 'box_low': move it, {WALK_THROUGH}",
    ),
    'a human walking through a box': (
        {'objects.2.waypoints': [[4.3, 2.65], [2.5, 2.65], [2.5, 1.9]], 'objects.2.loop': True},
        "human 'walker'.waypoints: its walk from [2.5, 1.9] to [4.3, 1.9] crosses object 'box_low': "
        f'reroute it, {WALK_THROUGH}',
    ),
    'a human walking off the floor': (
        {'objects.2.waypoints': [[4.3, 2.65], [4.3, 6.0]]},
        f"human 'walker'.waypoints[1]: [4.3, 6.0] is outside {FLOOR}",
    ),
    'a station colour its model does not match': (
        {'station.colour': [0, 0, 100]},
        'station.colour: [0, 0, 100] is not matched by colour_models.station (colour:0,0,150,80,80,255): '
        'the robot would not find its station; change the colour or widen the model',
    ),
    'the station model matching the robot': (
        {'colour_models.station': 'colour:0,0,0,30,255,255'},
        'robot.colour: [0, 200, 0] is matched by colour_models.station (colour:0,0,0,30,255,255) too: '
        'it would be taken for the station; change the colour or narrow the model',
    ),
    'an obstacle colour its model does not match': (
        {'objects.0.colour': [200, 200, 0]},
        "object 'box_low'.colour: [200, 200, 0] is not matched by colour_models.obstacle "
        '(colour:40,40,40,90,90,90): the robot would not see this obstacle; change the colour or widen the '
        'model (or decoy: true if that is on purpose)',
    ),
    'speed on the station': (
        {'station.speed': 0.3},
        'station.speed: does not apply: the station does not move '
        '(keys of the station: name, position, size, yaw, colour, tag)',
    ),
    'waypoints on a static object': (
        {'objects.0.waypoints': [[1.0, 1.0], [2.0, 1.0]]},
        f"object 'box_low'.waypoints: applies to humans only: add kind: human to make it walk {STATIC_KEYS}",
    ),
    'a camera that sees no floor': (
        {'vision_systems.0.position': [30.0, 2.78, 4.0]},
        f"vision_system 'vs1'.position: the camera sees none of {FLOOR} and {UNSEEN}",
    ),
    'a camera that looks at the sky': (
        {'vision_systems.1.target': [2.05, 2.05, 8.0]},
        f"vision_system 'vs2'.target: the camera sees none of {FLOOR} and {UNSEEN}",
    ),
    'a camera mount that leaves the floor behind': (
        {'vision_systems.1.waypoints': [[2.05, 2.05], [20.0, 2.05]], 'vision_systems.1.speed': 0.5},
        f"vision_system 'vs2'.waypoints[1]: from [20.0, 2.05] the camera sees none of {FLOOR} and {UNSEEN}",
    ),
    'a camera with no viewing direction': (
        {'vision_systems.0.target': [4.85, 2.78, 4.0]},
        "vision_system 'vs1'.target: equals position: the camera has no viewing direction",
    ),
    'a camera whose up is its viewing direction': (
        {'vision_systems.0.up': [0, 0, 1]},
        "vision_system 'vs1'.up: [0.0, 0.0, 1.0] does not point across the viewing direction: "
        'choose one that does',
    ),
}


@pytest.mark.parametrize('changes, problem', IMPOSSIBLE.values(), ids=IMPOSSIBLE)
def test_an_impossible_world_is_refused_naming_its_problem(tmp_path, changes, problem):
    path = tmp_path / 'world.yaml'
    path.write_text(yaml.safe_dump(edited(OBSTACLES, **changes)))
    with pytest.raises(WorldError) as error:
        load_world(path)
    assert str(error.value) == f'{path}: {problem}'  # one problem: one line


TAG_WORLDS = {
    'a station without the tag its model finds': (
        {'station.tag': None},
        'station.tag: missing: colour_models.station (apriltag:tag36h11:7) looks for a tag36h11 (id 7) tag: '
        'the robot would not find its station',
    ),
    'a station tag its model does not find': (
        {'station.tag.id': 8},
        'station.tag: tag36h11:8 is not found by colour_models.station (apriltag:tag36h11:7): '
        'the robot would not find its station; change the tag or the model',
    ),
    'a station model that finds the robot tag too': (
        {'colour_models.station': 'apriltag:tag36h11'},
        'robot.tag: tag36h11:3 is matched by colour_models.station (apriltag:tag36h11) too: '
        'it would be taken for the station; list its ids in the model',
    ),
    'an obstacle model that finds tags': (
        {'colour_models.obstacle': 'apriltag:tag36h11:9'},
        'colour_models.obstacle: finds tags, and objects carry none: the robot would not see this obstacle',
    ),
}


@pytest.mark.parametrize('changes, problem', TAG_WORLDS.values(), ids=TAG_WORLDS)
def test_an_apriltag_model_must_find_the_tag_of_its_body_only(tmp_path, changes, problem):
    assert problems_of(tmp_path, edited(TAGS, **changes)) == [problem]


def test_a_file_with_several_problems_names_them_all_in_the_order_of_the_file(tmp_path):
    names = [
        'station off the floor',
        'speed on the station',
        'a station colour its model does not match',
        'obstacle at x = 30.5',
        'robot at x = -3',
        'a camera that sees no floor',
    ]
    changes = {key: value for name in names for key, value in IMPOSSIBLE[name][0].items()}
    changes['objects.1.position'] = [-3, 2.65]  # on top of the robot, where it is now
    changes['objects.2.size'] = [0.3, 0.3]  # a type error hides no other entry's problems
    changes['robot.colur'] = [0, 200, 0]
    path = tmp_path / 'world.yaml'
    path.write_text(yaml.safe_dump(edited(OBSTACLES, **changes)))
    with pytest.raises(WorldError) as error:
        load_world(path)
    assert str(error.value).splitlines() == [
        f'{path}: 10 problems:',
        f'  robot.colur: unknown key; did you mean colour? {ROBOT_KEYS}',
        f'  robot.position: [-3.0, 2.65] is outside {FLOOR}',
        '  ' + IMPOSSIBLE['speed on the station'][1],
        f'  station.position: [8.0, 0.8] is outside {FLOOR}',
        '  ' + IMPOSSIBLE['a station colour its model does not match'][1],
        f"  object 'box_low'.position: [30.5, 1.55] is outside {FLOOR}",
        f"  object 'box_high'.position: [-3.0, 2.65] is outside {FLOOR}",
        f"  object 'box_high'.position: overlaps robot: {TOUCH}",
        "  human 'walker'.size: expected 3 positive numbers [x, y, z], got [0.3, 0.3]",
        f"  vision_system 'vs1'.position: the camera sees none of {FLOOR} and {UNSEEN}",
    ]


@pytest.mark.parametrize(
    'changes, problems',
    [
        (
            {'robot.posiiton': [0.83, 2.65], 'robot.position': None},
            [f'robot.posiiton: unknown key; did you mean position? {ROBOT_KEYS}', 'robot.position: missing'],
        ),
        (
            {'robot.tag': {'family': 'tag36h11', 'id': 3, 'sise': 0.2}},
            [
                'robot.tag.sise: unknown key; did you mean size? (keys of a tag: family, id, size)',
                'robot.tag.size: missing',
            ],
        ),
        (  # close to a key of humans only
            {'objects.0.speeed': 0.3},
            [f"object 'box_low'.speeed: unknown key; did you mean speed? {STATIC_KEYS}"],
        ),
        (
            {'vision_systems.0.fov': 60},
            [
                "vision_system 'vs1'.fov: unknown key; did you mean fov_deg? (keys of a vision system: name, "
                'position, fov_deg, resolution, target, up, waypoints, speed, distortion, depth_noise, site)'
            ],
        ),
        (
            {'colour_model': {}},
            [
                'colour_model: unknown key; did you mean colour_models? '
                '(keys of a world file: floor, robot, station, robots, objects, vision_systems, '
                'colour_models, real_time_factor)'
            ],
        ),
    ],
)
def test_a_misspelled_key_gets_a_suggestion(tmp_path, changes, problems):
    assert problems_of(tmp_path, edited(OBSTACLES, **changes)) == problems


def test_a_human_may_walk_through_boxes_and_a_decoy_may_look_like_another_role_when_the_world_says_so(
    tmp_path,
):
    path = tmp_path / 'world.yaml'
    through = {'objects.2.waypoints': [[4.3, 2.65], [2.5, 2.65], [2.5, 1.9]], 'objects.2.loop': True}
    decoy = {'objects.0.colour': [0, 0, 220]}  # coloured like the station
    problems = problems_of(tmp_path, edited(OBSTACLES, **through, **decoy))
    assert [problem.split(':')[0] for problem in problems] == [
        "object 'box_low'.colour",  # not an obstacle's colour
        "object 'box_low'.colour",  # the station's
        "human 'walker'.waypoints",  # the walk back crosses box_low
    ]
    data = edited(
        OBSTACLES, **through, **decoy, **{'objects.2.through_obstacles': True, 'objects.0.decoy': True}
    )
    path.write_text(yaml.safe_dump(data))
    world = load_world(path)
    assert world.objects[0].decoy and world.objects[2].through_obstacles
    assert not world.objects[1].decoy and not world.robot.through_obstacles  # the defaults


def test_a_human_may_walk_over_the_robot_and_the_station(tmp_path):
    # walking into the robot is a contact world_sim counts; the station is a plate, not an obstacle
    path = tmp_path / 'world.yaml'
    walk = {
        'objects.2.position': [0.83, 0.5],
        'objects.2.waypoints': [[0.83, 4.5], [5.9, 4.5], [5.9, 3.55]],  # over the robot, onto the station
    }
    path.write_text(yaml.safe_dump(edited(OBSTACLES, **walk)))
    assert load_world(path).objects[2].waypoints[2] == (5.9, 3.55)


def test_bodies_may_touch(tmp_path):
    path = tmp_path / 'world.yaml'
    # the station (0.4 wide) beside box_low (0.5 wide) and at the floor's right edge
    path.write_text(yaml.safe_dump(edited(OBSTACLES, **{'station.position': [3.75, 1.0]})))
    assert load_world(path).station.position == (3.75, 1.0)
    path.write_text(yaml.safe_dump(edited(OBSTACLES, **{'station.position': [6.8, 0.15]})))
    assert load_world(path).station.position == (6.8, 0.15)


def test_obstacle_and_human_models_may_find_each_others_bodies(tmp_path):
    # the robot plans around both alike: a red box is still an obstacle to it
    path = tmp_path / 'world.yaml'
    path.write_text(yaml.safe_dump(edited(OBSTACLES, **{'objects.0.colour': [220, 0, 0]})))
    assert load_world(path).objects[0].colour == (220, 0, 0)


# -- fleets -------------------------------------------------------------------------------------
CROSSING = yaml.safe_load((REPO / 'worlds/crossing.yaml').read_text())
CROSSING_FLOOR = 'the floor (x 0..8, y 0..5)'
TAG = {'family': 'tag36h11', 'id': 3, 'size': 0.2}
FLEET_WORLDS = {
    'a robot on another': (
        {'robots.1.position': [0.9, 1.0]},
        f"robots 'robot2'.position: overlaps robots 'robot1': {TOUCH}",
    ),
    "a station on another robot's station": (
        {'robots.1.station.position': [7.2, 4.1]},
        f"robots 'robot2'.station.position: overlaps robots 'robot1'.station: {TOUCH}",
    ),
    'a robot off the floor': (
        {'robots.0.position': [9, 1]},
        f"robots 'robot1'.position: [9.0, 1.0] is outside {CROSSING_FLOOR}",
    ),
    'a self model that finds another robot': (
        {'robots.0.colour_models.self': 'colour:0,170,0,30,230,190'},
        "robots 'robot2'.colour: [0, 200, 160] is matched by robots 'robot1'.colour_models.self "
        "(colour:0,170,0,30,230,190) too: it would be taken for robot 'robot1'; change the colour or narrow "
        'the model',
    ),
    "a station model that finds another robot's station": (
        {'robots.0.colour_models.station': 'colour:0,0,200,190,30,240'},
        "robots 'robot2'.station.colour: [160, 0, 220] is matched by robots 'robot1'.colour_models.station "
        "(colour:0,0,200,190,30,240) too: it would be taken for the station of robot 'robot1'; change the "
        'colour or narrow the model',
    ),
    'a self model that misses its robot': (
        {'robots.1.colour': [0, 200, 100]},
        "robots 'robot2'.colour: [0, 200, 100] is not matched by robots 'robot2'.colour_models.self "
        '(colour:0,170,130,30,230,190): the robot would not find itself; change the colour or widen the '
        'model',
    ),
    'a robot model that misses a robot': (
        {'colour_models.robot': 'colour:0,170,0,30,230,30'},
        "robots 'robot2'.colour: [0, 200, 160] is not matched by colour_models.robot "
        '(colour:0,170,0,30,230,30): the other robots would not see this robot; change the colour or widen '
        'the model',
    ),
    'a robot model that finds a station': (
        {'colour_models.robot': 'colour:0,0,0,30,230,240'},
        "robots 'robot1'.station.colour: [0, 0, 220] is matched by colour_models.robot "
        '(colour:0,0,0,30,230,240) too: it would be taken for a robot; change the colour or narrow the model',
    ),
    'an obstacle model that finds a robot': (
        {'colour_models.obstacle': 'colour:0,0,0,90,255,90'},
        "robots 'robot1'.colour: [0, 200, 0] is matched by colour_models.obstacle (colour:0,0,0,90,255,90) "
        'too: it would be taken for an obstacle; change the colour or narrow the model',
    ),
    'one tag on two robots': (
        {'robots.0.tag': TAG, 'robots.1.tag': TAG},
        "robots 'robot2'.tag: tag36h11:3 is also robots 'robot1'.tag; each tag (family and id) may be on one "
        'body only',
    ),
}


@pytest.mark.parametrize('changes, problem', FLEET_WORLDS.values(), ids=FLEET_WORLDS)
def test_an_impossible_fleet_is_refused_naming_robot_and_key(tmp_path, changes, problem):
    assert problems_of(tmp_path, edited(CROSSING, **changes)) == [problem]


def test_a_human_may_walk_over_every_robot_and_station_of_a_fleet(tmp_path):
    path = tmp_path / 'world.yaml'
    walk = {'objects.1.position': [0.8, 0.5], 'objects.1.waypoints': [[0.8, 4.5], [7.2, 4.5], [7.2, 0.5]]}
    path.write_text(yaml.safe_dump(edited(CROSSING, **walk)))
    assert load_world(path).objects[1].waypoints[1] == (7.2, 4.5)


@pytest.mark.parametrize('path', SHIPPED, ids=[str(p.relative_to(REPO)) for p in SHIPPED])
def test_every_shipped_world_makes_sense(path):
    assert load_world(path).vision_systems


# -- drvs_check_world --------------------------------------------------------------------------
def check_world(*paths):
    return subprocess.run(
        [sys.executable, str(CHECK_WORLD), *map(str, paths)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        env={'PATH': '/usr/bin:/bin', 'PYTHONPATH': str(REPO)},  # no ROS master needed
    )


def test_check_world_says_ok_for_good_files_and_exits_0():
    result = check_world(*SHIPPED)
    assert (result.returncode, result.stderr) == (0, '')
    assert result.stdout.splitlines() == [f'{path}: ok' for path in SHIPPED]


def test_check_world_prints_every_problem_of_each_bad_file_and_exits_2(tmp_path):
    bad = tmp_path / 'bad.yaml'
    bad.write_text(yaml.safe_dump(edited(OBSTACLES, **{'station.position': [8.0, 0.8], 'station.speed': 1})))
    broken = tmp_path / 'broken.yaml'
    broken.write_text('floor: [')
    good = REPO / 'worlds/localisation.yaml'
    result = check_world(bad, good, tmp_path / 'missing.yaml', broken)
    assert (result.returncode, result.stderr) == (2, '')
    assert result.stdout.splitlines() == [
        f'{bad}: 2 problems:',
        '  ' + IMPOSSIBLE['speed on the station'][1].replace('0.3', '1'),
        f'  station.position: [8.0, 0.8] is outside {FLOOR}',
        f'{good}: ok',
        f'{tmp_path / "missing.yaml"}: cannot read the world file: No such file or directory',
        f"{broken}: not valid YAML: line 1, column 9: expected the node content, but found '<stream end>' "
        '(while parsing a flow node at line 1, column 9)',
    ]


def test_check_world_without_files_prints_its_usage_and_exits_2():
    result = check_world()
    assert result.returncode == 2
    assert result.stderr.startswith('usage: drvs_check_world [-h] FILE [FILE ...]')
    assert 'Traceback' not in result.stderr
    result = check_world('--help')
    assert result.returncode == 0 and result.stdout.startswith('usage: drvs_check_world')


def test_check_world_refuses_a_role_the_robot_never_asks_for_with_the_nearest_one(tmp_path):
    """A typo beside the right role (``humna:`` and ``human:``) must not pass as ok."""
    typo = tmp_path / 'typo.yaml'
    typo.write_text(yaml.safe_dump(edited(OBSTACLES, **{'colour_models.humna': 'colour:150,0,0,255,80,80'})))
    result = check_world(typo)
    assert (result.returncode, result.stdout) == (
        2,
        f'{typo}: colour_models.humna: unknown role; did you mean human? '
        '(roles: self, station, obstacle, human, robot)\n',
    )


def test_a_fleets_roles_are_checked_against_the_robots_too(tmp_path):
    fleet = yaml.safe_load((REPO / 'worlds/crossing.yaml').read_text())
    fleet['colour_models']['obstacel'] = fleet['colour_models']['obstacle']
    first = fleet['robots'][0]
    first['colour_models']['slef'] = first['colour_models']['self']
    roles = '(roles: self, station, obstacle, human, robot)'
    assert sorted(problems_of(tmp_path, fleet)) == [
        f'colour_models.obstacel: unknown role; did you mean obstacle? {roles}',
        f"robots {first['name']!r}.colour_models.slef: unknown role; did you mean self? {roles}",
    ]
