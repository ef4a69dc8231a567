"""Why an algorithm cannot work on a vision system's frames now, remembered for a while.

An algorithm that meets a frame it cannot use (``elevation`` without usable depth, ``foreground``
without its reference: :class:`drvs.algorithms.FrameProblem`) says why; the vision system notes
it here, refuses that algorithm's requests with the message while it is recent, and reports it on
its diagnostics (docs/nodes/vision_system.md). A frame that works clears it.

>>> problems = FrameProblems(hold=10.0)
>>> problems.note('elevation', 'elevation: the frame has no depth image', now=100.0)
>>> problems.current('elevation', now=105.0)
'elevation: the frame has no depth image'
>>> problems.current('elevation', now=111.0) is None
True
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from drvs.algorithms import Algorithm, Parsed
from drvs.vision.frame import Frame

__all__ = ['FRAME_PROBLEM_HOLD', 'FrameProblems', 'depth_problem']

FRAME_PROBLEM_HOLD = 10.0
"""Seconds a frame problem refuses requests and shows on the diagnostics after it was last met;
then a request is tried again (and notes it again if it persists)."""


class FrameProblems:
    """The latest frame problem per algorithm name, with when it was met. Thread-safe."""

    def __init__(self, hold: float = FRAME_PROBLEM_HOLD):
        self.hold = hold
        self._lock = threading.Lock()  # guards _problems
        self._problems: dict[str, tuple[str, float]] = {}  # algorithm name -> (message, when)

    def note(self, name: str, message: str, now: float) -> None:
        with self._lock:
            self._problems[name] = (message, now)

    def clear(self, name: str) -> None:
        with self._lock:
            self._problems.pop(name, None)

    def current(self, name: str, now: float) -> str | None:
        """The problem of algorithm ``name`` met within :attr:`hold` seconds of ``now``, or None."""
        with self._lock:
            found = self._problems.get(name)
        if found is None or now - found[1] > self.hold:
            return None
        return found[0]

    def why(
        self,
        algorithm: Parsed,
        latest: Callable[[], Frame | None],
        depth: Callable[[], str | None],
        now: float,
    ) -> str | None:
        """Why ``algorithm`` cannot work on the camera's frames now: what the newest frame at hand
        (``latest()``) shows, or without one a problem met lately; None if none is known. ``depth()``:
        why the camera's depth was left out of its newest frame (:func:`depth_problem`), asked after
        ``latest()``, whose decoding finds it."""
        check = getattr(algorithm.algorithm, 'frame_problem', None)
        if getattr(type(algorithm.algorithm), 'frame_problem', None) is Algorithm.frame_problem:
            check = None  # it says of no frame that it cannot work on it: no frame to look at
        frame = latest() if check is not None else None  # decoding it notes a depth problem
        problem = depth_problem(algorithm, depth())
        if problem is None and frame is not None and check is not None:  # the newest frame says it all
            problem = check(frame)
            if problem is None:
                self.clear(algorithm.name)
            return problem
        return problem or self.current(algorithm.name, now)

    def messages(self, now: float) -> list[str]:
        """Every recent problem's message, by algorithm name."""
        with self._lock:
            problems = sorted(self._problems.items())
        return [message for _, (message, when) in problems if now - when <= self.hold]


def depth_problem(algorithm: Parsed, depth: str | None) -> str | None:
    """``depth`` (why the camera's depth was left out of its newest frame) as ``algorithm``'s
    problem, if it needs depth; else None."""
    if getattr(algorithm.algorithm, 'needs_depth', False) and depth:
        return f'{algorithm.name}: {depth}'
    return None
