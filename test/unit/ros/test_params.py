"""read_params and drvs.common.settings: ~parameters read one way, ranges checked in one place, every
problem listed at once with where its value came from, unknown names warned about."""

import dataclasses
import doctest
import math
from dataclasses import dataclass

import pytest

import drvs.common.settings
import drvs.ros.params
from drvs.common.settings import (
    NON_NEGATIVE,
    POSITIVE,
    REQUIRED,
    ParamError,
    Settings,
    at_least,
    between,
    one_of,
    param,
)
from drvs.robot.params import RobotParams
from drvs.ros.params import (
    command_line_params,
    origin_note,
    private_param_names,
    read_params,
    unknown_param_warnings,
    writable_folder,
)
from drvs.server.params import ServerSettings
from drvs.sim.params import RecorderSettings, SimCameraParams, WorldSimSettings
from drvs.vision.params import VisionSystemParams


@dataclass(frozen=True)
class Plain:
    world: str
    rate: float = 5.0
    workers: int = 2
    once: bool = False
    speed: float | None = None


def reading(**given):
    return lambda name, default: given.get(name.lstrip('~'), default)


def test_defaults_fill_what_is_not_given_and_ints_become_floats():
    assert read_params(Plain, get=reading(world='w.yaml', rate=10)) == Plain('w.yaml', 10.0, 2, False, None)
    assert read_params(Plain, get=reading(world='w.yaml', speed=1)).speed == 1.0


def test_run_time_defaults_replace_the_dataclass_defaults_but_not_given_values():
    assert read_params(Plain, {'world': 'd.yaml', 'workers': 4}, get=reading()).workers == 4
    assert read_params(Plain, {'workers': 4}, get=reading(world='w', workers=3)).workers == 3


@pytest.mark.parametrize(
    'given, message',
    [
        ({}, '~world: required, not given (add _world:=VALUE to the command line)'),
        ({'world': 'w', 'rate': 'fast'}, "~rate: expected a number, got 'fast'"),
        ({'world': 'w', 'rate': True}, '~rate: expected a number, got True'),
        ({'world': 'w', 'workers': 2.5}, '~workers: expected an integer, got 2.5'),
        ({'world': 'w', 'once': 1}, '~once: expected true or false, got 1'),
        ({'world': 3}, '~world: expected a string, got 3'),
        ({'world': 'w', 'speed': 'x'}, "~speed: expected a number, got 'x'"),
    ],
)
def test_missing_and_mistyped_parameters_are_named(given, message):
    with pytest.raises(ValueError) as error:
        read_params(Plain, get=reading(**given))
    assert str(error.value) == message


# -- declared ranges, checked in one place (drvs.common.settings) ------------------------------------
@dataclass(frozen=True)
class Declared(Settings):
    world: str = param(REQUIRED, 'the world file')
    lease: float = param(
        10.0, 'a registration expires unless renewed within this time', unit='s', check=POSITIVE
    )
    period: float = param(0.2, 'minimum time between two messages', unit='s', check=NON_NEGATIVE)
    workers: int = param(8, 'threads', check=at_least(1))
    quality: int = param(90, 'JPEG quality', check=between(1, 100))
    source: str = param('render', 'where frames come from', check=one_of('render', 'topic'))
    speed: float | None = param(None, 'top speed', unit='m/s', check=POSITIVE)
    cameras: str = param('', 'cameras, comma-separated or a list', separator=',')


@pytest.mark.parametrize(
    'given, message',
    [
        ({'lease': -1}, '~lease: must be positive, got -1.0'),
        ({'lease': 0.0}, '~lease: must be positive, got 0.0'),
        ({'period': -0.5}, '~period: must not be negative, got -0.5'),
        ({'workers': 0}, '~workers: must be at least 1, got 0'),
        ({'quality': 0}, '~quality: must be 1 to 100, got 0'),
        ({'quality': 101}, '~quality: must be 1 to 100, got 101'),
        ({'source': 'x'}, "~source: must be one of render, topic, got 'x'"),
        ({'speed': -1.0}, '~speed: must be positive, got -1.0'),
        ({'lease': math.inf}, '~lease: expected a number, got inf'),
        ({'period': math.nan}, '~period: expected a number, got nan'),
        ({'workers': 2.0}, '~workers: expected an integer, got 2.0'),
        ({'world': None}, '~world: expected a string, got None'),
    ],
)
def test_every_kind_of_range_has_one_wording_whether_read_or_built(given, message):
    with pytest.raises(ValueError) as read:
        read_params(Declared, get=reading(**{'world': 'w', **given}))
    with pytest.raises(ValueError) as built:
        Declared(**{'world': 'w', **given})
    assert str(read.value) == str(built.value) == message


def test_values_in_range_pass_ints_become_floats_and_none_is_not_checked():
    built = Declared(world='w', lease=1, period=0, workers=1, quality=100, source='topic')
    assert (built.lease, built.period, built.speed) == (1.0, 0.0, None)
    assert isinstance(built.lease, float) and isinstance(built.period, float)


def test_a_list_is_joined_for_a_field_declared_with_a_separator_only():
    assert read_params(Declared, get=reading(world='w', cameras=['vs1', 'vs2'])).cameras == 'vs1,vs2'
    with pytest.raises(ValueError) as error:
        read_params(Declared, get=reading(world='w', cameras=[1, 2]))
    assert str(error.value) == '~cameras: expected a string or a list of strings, got [1, 2]'
    with pytest.raises(ValueError) as error:
        read_params(Declared, get=reading(world=['w']))
    assert str(error.value) == "~world: expected a string, got ['w']"


@pytest.mark.parametrize(
    'build, message',
    [
        (lambda: ServerSettings(lease=0), '~lease: must be positive, got 0.0'),
        (lambda: ServerSettings(workers=0), '~workers: must be at least 1, got 0'),
        (lambda: ServerSettings(callback_cache=-1), '~callback_cache: must not be negative, got -1.0'),
        (
            lambda: ServerSettings(ejection_time=20, max_ejection_time=10),
            '~max_ejection_time: must be at least ~ejection_time (20.0), got 10.0',
        ),
        (
            lambda: VisionSystemParams(camera='vs1', source='render'),
            '~world: required with ~source render (or use ~source topic and a camera topic)',
        ),
        (
            lambda: VisionSystemParams(camera='vs1', source='x'),
            "~source: must be one of render, topic, got 'x'",
        ),
        (lambda: RobotParams(world='w', roi_margin=-1), '~roi_margin: must not be negative, got -1.0'),
        (lambda: RobotParams(world='w', speed=math.inf), '~speed: expected a number, got inf'),
        (
            lambda: SimCameraParams(world='w', compression='bmp'),
            "~compression: must be one of jpeg, png, got 'bmp'",
        ),
        (lambda: WorldSimSettings(world='w', cmd_timeout=0), '~cmd_timeout: must be positive, got 0.0'),
        (
            lambda: RecorderSettings(world='w', out='o', cpu_period=-1),
            '~cpu_period: must be positive, got -1.0',
        ),
    ],
)
def test_the_nodes_settings_check_their_declared_ranges_when_built(build, message):
    with pytest.raises(ValueError) as error:
        build()
    assert str(error.value) == message


def test_the_vision_system_source_defaults_to_render_with_a_world_else_topic():
    assert VisionSystemParams(camera='vs1', world='w.yaml').source == 'render'
    assert VisionSystemParams(camera='vs1').source == 'topic'


@pytest.mark.parametrize(
    'cls',
    [ServerSettings, VisionSystemParams, RobotParams, SimCameraParams, WorldSimSettings, RecorderSettings],
)
def test_every_node_parameter_is_declared_with_a_meaning(cls):
    assert all(field.metadata.get('meaning') for field in dataclasses.fields(cls))


# -- every problem at once, where a value came from, unknown names (issue 14) -----------------
def test_every_problem_is_listed_at_once_types_and_ranges_alike():
    with pytest.raises(ParamError) as error:
        read_params(Declared, get=reading(lease='x', workers=0, quality=101))
    assert str(error.value) == (
        '~world: required, not given (add _world:=VALUE to the command line)\n'
        "~lease: expected a number, got 'x'\n"
        '~workers: must be at least 1, got 0\n'
        '~quality: must be 1 to 100, got 101'
    )
    assert error.value.names == ('world', 'lease', 'workers', 'quality')
    assert isinstance(error.value, ValueError)


def test_a_value_not_from_the_command_line_says_where_it_came_from():
    given = {'world': 'w', 'lease': -1, 'workers': 0}
    with pytest.raises(ParamError) as error:
        read_params(Declared, get=reading(**given), given={'world', 'lease'}, node='/srv')
    assert str(error.value) == (
        '~lease: must be positive, got -1.0\n~workers: must be at least 1, got 0'
        + origin_note('/srv', 'workers')
    )
    assert origin_note('/srv', 'workers') == (
        ' (from the parameter server, not from this command line: left by an earlier run, a launch file '
        'or `rosparam set`; clear it with `rosparam delete /srv/workers`)'
    )


def test_a_rule_across_fields_is_annotated_with_the_origin_too():
    with pytest.raises(ParamError) as error:
        read_params(
            ServerSettings,
            get=reading(ejection_time=20, max_ejection_time=10),
            given={'ejection_time'},
            node='/drvs',
        )
    assert str(error.value) == (
        '~max_ejection_time: must be at least ~ejection_time (20.0), got 10.0'
        + origin_note('/drvs', 'max_ejection_time')
    )


def test_command_line_params_are_read_as_rospy_reads_them_and_bad_yaml_names_the_parameter():
    argv = ['node', '_rate:=2', '__name:=n', 'topic:=other', '_cameras:=[vs1, vs2]', '_once:=yes']
    assert command_line_params(argv) == {'rate': 2, 'cameras': ['vs1', 'vs2'], 'once': True}
    with pytest.raises(ParamError) as error:
        command_line_params(['node', '_rate:=[1,'])
    assert (
        str(error.value)
        == "~rate: cannot read '[1,' as YAML (expected the node content, but found '<stream end>')"
    )


@pytest.mark.parametrize(
    'names, given, warnings',
    [
        (
            ['forward_timout', 'lease'],
            None,
            ['unknown parameter ~forward_timout (ignored): did you mean ~forward_timeout?'],
        ),
        (['zzz'], None, ['unknown parameter ~zzz (ignored): this node has no such parameter']),
        (
            ['leese'],
            set(),
            ['unknown parameter ~leese (ignored)' + origin_note('/drvs', 'leese') + ': did you mean ~lease?'],
        ),
        (['lease', 'workers'], None, []),
    ],
)
def test_unknown_private_parameters_are_warnings_with_the_nearest_name(names, given, warnings):
    assert unknown_param_warnings(ServerSettings, names, given, '/drvs') == warnings


def test_private_param_names_are_the_first_level_under_the_node():
    names = ['/drvs/lease', '/drvs/nested/key', '/drvs_other/x', '/use_sim_time', '/drvs']
    assert private_param_names('/drvs', names) == {'lease', 'nested'}


def test_a_folder_parameter_is_created_or_refused_naming_it(tmp_path):
    assert writable_folder('out', str(tmp_path / 'a' / 'b')) == tmp_path / 'a' / 'b'
    (tmp_path / 'file').write_text('')
    with pytest.raises(ParamError) as error:
        writable_folder('out', str(tmp_path / 'file' / 'sub'))
    assert str(error.value) == f'~out: cannot write to the folder {tmp_path}/file/sub: Not a directory'


@pytest.mark.parametrize('module', [drvs.common.settings, drvs.ros.params])
def test_doctests(module):
    assert doctest.testmod(module).failed == 0
