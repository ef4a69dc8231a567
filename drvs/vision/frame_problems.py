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

__all__ = ['FRAME_PROBLEM_HOLD', 'FrameProblems']

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

    def messages(self, now: float) -> list[str]:
        """Every recent problem's message, by algorithm name."""
        with self._lock:
            problems = sorted(self._problems.items())
        return [message for _, (message, when) in problems if now - when <= self.hold]
