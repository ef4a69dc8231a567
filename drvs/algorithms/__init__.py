"""The shared algorithm definitions: the ``NAME[:PARAMS]`` strings of DetectObjectBoundary.

Built in: ``colour`` (:mod:`drvs.algorithms.colour`), ``apriltag``
(:mod:`drvs.algorithms.apriltag`), ``motion`` (:mod:`drvs.algorithms.motion`), ``foreground``
(:mod:`drvs.algorithms.foreground`) and, for cameras with depth, ``elevation``
(:mod:`drvs.algorithms.elevation`).
Third-party packages add algorithms through the Python entry-point group
``drvs.algorithms``: each entry point names a class (instantiated with no
arguments) or an instance with the members of :class:`Algorithm`;
:func:`load_algorithms` finds them at start. What an algorithm is:
:mod:`drvs.algorithms.base`.

>>> parsed = parse_algorithm('colour:0,0,150,80,80,255')
>>> parsed.name, parsed.params.lower, parsed.params.upper
('colour', (0, 0, 150), (80, 80, 255))
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from importlib.metadata import EntryPoint
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

    from drvs.vision.frame import Frame

from drvs.algorithms.base import (
    MAX_LENGTH,
    NAME_PATTERN,
    Algorithm,
    AlgorithmError,
    FrameProblem,
    PixelObject,
    outlines_of_mask,
    split_algorithm,
)
from drvs.algorithms.colour import Colour, ColourModel

log = logging.getLogger('rosout.' + __name__)

ENTRY_POINT_GROUP = 'drvs.algorithms'

__all__ = [
    'BUILTIN_NAMES',
    'ENTRY_POINT_GROUP',
    'MAX_LENGTH',
    'Algorithm',
    'AlgorithmError',
    'AlgorithmSet',
    'FrameProblem',
    'Colour',
    'ColourModel',
    'Parsed',
    'PixelObject',
    'builtin_algorithms',
    'default_algorithms',
    'load_algorithms',
    'outlines_of_mask',
    'parse_algorithm',
    'split_algorithm',
]


@dataclass(frozen=True)
class Parsed:
    """An algorithm string checked by its algorithm: what to run, with which parameters."""

    algorithm: Algorithm
    params: object
    text: str

    @property
    def name(self) -> str:
        return self.algorithm.name

    def detect(self, frame: Frame) -> list[PixelObject]:
        return self.algorithm.detect(frame, self.params)


class AlgorithmSet:
    """The algorithms one process runs, by name."""

    def __init__(self, algorithms: Iterable[Algorithm]):
        self.by_name: dict[str, Algorithm] = {}
        for algorithm in algorithms:
            check_algorithm(algorithm)
            if algorithm.name in self.by_name:
                raise ValueError(f'algorithm {algorithm.name!r} is defined twice')
            self.by_name[algorithm.name] = algorithm

    def names(self) -> list[str]:
        return sorted(self.by_name)

    def __contains__(self, name: str) -> bool:
        return name in self.by_name

    def get(self, name: str) -> Algorithm | None:
        return self.by_name.get(name)

    def parse(self, text: str) -> Parsed:
        """``NAME[:PARAMS]`` checked by the named algorithm.

        :raises AlgorithmError: bad syntax, unknown NAME (the message lists the known
            ones), or PARAMS the algorithm refuses.
        """
        name, params = split_algorithm(text)
        algorithm = self.by_name.get(name)
        if algorithm is None:
            raise AlgorithmError(f'algorithm: unknown NAME {name!r}; known: {", ".join(self.names())}')
        return Parsed(algorithm, algorithm.parse(params), text)


def check_algorithm(algorithm: object) -> None:
    """Refuse an object that is not an algorithm, naming what it lacks."""
    name = getattr(algorithm, 'name', None)
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name):
        raise ValueError(f'{algorithm!r}: an algorithm needs a name (a letter, then letters, digits or _)')
    for member in ('parse', 'detect'):
        if not callable(getattr(algorithm, member, None)):
            raise ValueError(f'algorithm {name!r}: {member}() is missing')


def builtin_algorithms(
    min_area: float = 20.0,
    epsilon: float = 1.0,
    tag_height: float = 0.0,
    tag_heights: Mapping[str, float] | None = None,
    depth: bool = True,
    reference: np.ndarray | None = None,
    fixed: bool = True,
) -> list[Algorithm]:
    """Fresh instances of the built-in algorithms (``motion`` keeps state: one per camera).

    ``tag_height``: the plane tags lie on unless the request says (``h=``);
    ``tag_heights``: {label: height} known for particular tags (a world file's robot);
    ``depth``: the camera has depth, so ``elevation`` can run (False: left out, so the camera
    does not register it and the server sends it only where it can run); ``reference``: the
    camera's image of its empty floor for ``foreground`` (None: learnt from its first frames);
    ``fixed``: the camera stands still, so ``foreground`` can run (left out on a moving mount).
    """
    from drvs.algorithms.apriltag import AprilTag
    from drvs.algorithms.elevation import Elevation
    from drvs.algorithms.foreground import Foreground
    from drvs.algorithms.motion import Motion

    algorithms: list[Algorithm] = [
        Colour(min_area, epsilon),
        AprilTag(default_height=tag_height, heights=tag_heights),
        Motion(epsilon=epsilon),
    ]
    if fixed:
        algorithms.append(Foreground(reference, epsilon))
    if depth:
        algorithms.append(Elevation(min_area, epsilon))
    return algorithms


BUILTIN_NAMES = ('apriltag', 'colour', 'motion')
"""The built-ins every camera runs; what an empty ``algorithms`` registration means (a camera with
depth registers ``elevation`` by name too)."""


def plugin_algorithms(entry_points: Iterable[EntryPoint] | None = None) -> list[Algorithm]:
    """The algorithms of the installed packages' ``drvs.algorithms`` entry points.

    A plugin that fails to load, or is not an algorithm, is logged as an error
    naming it and left out: the others keep working.
    """
    if entry_points is None:
        from importlib.metadata import entry_points as installed

        entry_points = installed(group=ENTRY_POINT_GROUP)
    found = []
    for entry_point in entry_points:
        try:
            loaded = entry_point.load()
            algorithm = loaded() if isinstance(loaded, type) else loaded
            check_algorithm(algorithm)
        except Exception as error:  # a broken third-party package: named and skipped
            log.error(
                'algorithm plugin %s = %s does not load: %s: %s',
                entry_point.name,
                entry_point.value,
                type(error).__name__,
                error,
            )
            continue
        if algorithm.name != entry_point.name:
            log.warning(
                'algorithm plugin entry point %r gives an algorithm named %r; it answers to %r',
                entry_point.name,
                algorithm.name,
                algorithm.name,
            )
        found.append(algorithm)
    return found


def load_algorithms(
    min_area: float = 20.0,
    epsilon: float = 1.0,
    tag_height: float = 0.0,
    tag_heights: Mapping[str, float] | None = None,
    entry_points: Iterable[EntryPoint] | None = None,
    depth: bool = True,
    reference: np.ndarray | None = None,
    fixed: bool = True,
) -> AlgorithmSet:
    """The built-ins (see :func:`builtin_algorithms`) and every plugin installed; a plugin that
    reuses a taken name is left out."""
    algorithms = builtin_algorithms(min_area, epsilon, tag_height, tag_heights, depth, reference, fixed)
    taken = {a.name for a in algorithms}
    for plugin in plugin_algorithms(entry_points):
        if plugin.name in taken:
            log.error('algorithm plugin %r: the name is taken by another algorithm; left out', plugin.name)
            continue
        taken.add(plugin.name)
        algorithms.append(plugin)
    return AlgorithmSet(algorithms)


_DEFAULT: AlgorithmSet | None = None


def default_algorithms() -> AlgorithmSet:
    """One shared set of the built-ins and installed plugins, for parsing (not for stateful detection)."""
    global _DEFAULT
    if _DEFAULT is None:
        _DEFAULT = load_algorithms()
    return _DEFAULT


def parse_algorithm(text: str, algorithms: AlgorithmSet | None = None) -> Parsed:
    """Parse ``NAME[:PARAMS]`` with ``algorithms`` (default: the built-ins and installed plugins).

    :raises AlgorithmError: naming the problem: empty, too long, bad syntax, unknown
        NAME, or PARAMS the algorithm refuses.
    """
    return (algorithms or default_algorithms()).parse(text)
