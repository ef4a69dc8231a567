"""The server's checks of a robot's request or watch that need no ROS master.

The fields (algorithm, region of interest, callback name), whether any registered vision
system runs the algorithm, and the caller's rate. Each failed check is a
:class:`~drvs.common.status.Refusal` whose message is part of the interface; the order of the
checks is in docs/nodes/drvs_server.md. No ROS here.
"""

from __future__ import annotations

from collections.abc import Sequence

from drvs.algorithms import AlgorithmError, AlgorithmSet, split_algorithm
from drvs.common.status import INVALID, RATE_LIMITED, UNSUPPORTED, Refusal
from drvs.common.validation import ValidationError, global_ros_name, region_of_interest

__all__ = [
    'MAX_ALGORITHMS_REMEMBERED',
    'AlgorithmNames',
    'check_supported',
    'rate_limited',
    'request_fields',
]

MAX_ALGORITHMS_REMEMBERED = 1024
"""Algorithm strings remembered as valid (with their NAME); callers choose them, so capped."""

Box = tuple[float, float, float, float]


class AlgorithmNames:
    """The NAME of a request's algorithm, checked in full if ``known`` has it, else its syntax only
    (the vision systems that run it check its PARAMS).

    Valid strings are remembered with their NAME, at most ``max_remembered`` (then all are
    forgotten): every request asks, and parsing costs more than the rest of the check.

    >>> from drvs.algorithms import default_algorithms
    >>> names = AlgorithmNames(default_algorithms())
    >>> names.name('colour:200,0,0,255,80,80'), names.name('someones_plugin:any params')
    ('colour', 'someones_plugin')
    """

    def __init__(self, known: AlgorithmSet, max_remembered: int = MAX_ALGORITHMS_REMEMBERED):
        if max_remembered < 1:
            raise ValueError(f'max_remembered: must be at least 1, got {max_remembered}')
        self.known = known
        self.max_remembered = int(max_remembered)
        # Valid string -> its NAME. Unlocked: a dict's get, set and clear are atomic, and a string
        # checked twice at once gives the same NAME twice.
        self._names: dict[str, str] = {}

    def __len__(self) -> int:
        return len(self._names)

    def name(self, text: str) -> str:
        """The NAME of ``text`` (``NAME[:PARAMS]``).

        :raises AlgorithmError: bad syntax; PARAMS that a known algorithm refuses.
        """
        known = self._names.get(text)
        if known is not None:
            return known
        algorithm, _ = split_algorithm(text)
        if algorithm in self.known:
            self.known.parse(text)
        if len(self._names) >= self.max_remembered:
            self._names.clear()
        self._names[text] = algorithm
        return algorithm


def request_fields(
    names: AlgorithmNames, algorithm: str, region: Box, callback_service: str
) -> tuple[str, Box]:
    """The algorithm's NAME and the region of a request or watch, its callback name checked.

    :raises Refusal: ``INVALID`` naming the field.

    >>> from drvs.algorithms import default_algorithms
    >>> names = AlgorithmNames(default_algorithms())
    >>> request_fields(names, 'colour:200,0,0,255,80,80', (0, 0, 1, 1), '/robot/callback')
    ('colour', (0.0, 0.0, 1.0, 1.0))
    """
    try:
        name = names.name(algorithm)
        box = region_of_interest(region)
        global_ros_name('callback_service', callback_service)
    except (AlgorithmError, ValidationError) as error:
        raise Refusal(INVALID, str(error)) from None
    return name, box


def check_supported(available: Sequence[str], algorithm: str) -> None:
    """Refuse an algorithm none of the ``available`` ones (those the registered vision systems
    run) is; while nobody is registered (none available) nothing is known, so nothing is refused.

    :raises Refusal: ``UNSUPPORTED``, listing the available algorithms.

    >>> check_supported([], 'colour'); check_supported(['colour', 'sift'], 'sift')
    >>> check_supported(['colour', 'sift'], 'motion')
    Traceback (most recent call last):
    ...
    drvs.common.status.Refusal: algorithm: no registered vision system runs 'motion'; available: colour, sift
    """
    if available and algorithm not in available:
        raise Refusal(
            UNSUPPORTED,
            f'algorithm: no registered vision system runs {algorithm!r}; available: {", ".join(available)}',
        )


def rate_limited(caller: str, wait: float, rate: float, burst: int) -> Refusal:
    """The refusal of a call from ``caller`` over its ``rate`` (bursts of ``burst``), ``wait``
    seconds before it may call again.

    >>> str(rate_limited('/robot', 0.02, 50.0, 100))
    'rate limited: /robot sends more than 50 requests/s (bursts of 100); retry after 0.020 s'
    """
    return Refusal(
        RATE_LIMITED,
        f'rate limited: {caller or "(no caller id)"} sends more than {rate:g} requests/s '
        f'(bursts of {burst}); retry after {wait:.3f} s',
        wait,
    )
