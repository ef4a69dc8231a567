"""read_params: every node reads its ~parameters into its settings dataclass the same way."""

from dataclasses import dataclass

import pytest

from drvs.ros.params import read_params


@dataclass(frozen=True)
class Settings:
    world: str
    rate: float = 5.0
    workers: int = 2
    once: bool = False
    speed: float | None = None


def reading(**given):
    return lambda name, default: given.get(name.lstrip('~'), default)


def test_defaults_fill_what_is_not_given_and_ints_become_floats():
    assert read_params(Settings, get=reading(world='w.yaml', rate=10)) == Settings(
        'w.yaml', 10.0, 2, False, None
    )
    assert read_params(Settings, get=reading(world='w.yaml', speed=1)).speed == 1.0


def test_run_time_defaults_replace_the_dataclass_defaults_but_not_given_values():
    assert read_params(Settings, {'world': 'd.yaml', 'workers': 4}, get=reading()).workers == 4
    assert read_params(Settings, {'workers': 4}, get=reading(world='w', workers=3)).workers == 3


@pytest.mark.parametrize(
    'given, message',
    [
        ({}, '~world: missing'),
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
        read_params(Settings, get=reading(**given))
    assert str(error.value) == message
