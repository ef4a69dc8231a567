"""When must a node register again with the ROS master? (ros/ros_comm#185)

:class:`MasterRestartDetector` decides, from what one poll of the master saw, whether the
node must register again; the ROS glue (:mod:`drvs.ros.master_watch`) polls and
re-registers. No ROS here. The rule and why: docs/reliability.md ("Master restarts").

>>> detector = MasterRestartDetector('http://127.0.0.1:4000/', clock=lambda: 0.0)
>>> detector.observe(101, 'http://127.0.0.1:4000/').verdict  # the master init_node registered with
<Verdict.NONE: 'none'>
>>> decision = detector.observe(202, None)  # a new master process, which does not know us
>>> decision.verdict, decision.old_pid, decision.new_pid
(<Verdict.REGISTER: 'register'>, 101, 202)
>>> detector.registered(202)
>>> detector.observe(202, 'http://127.0.0.1:4000/').verdict
<Verdict.NONE: 'none'>
"""

from __future__ import annotations

import enum
import time
from collections.abc import Callable
from dataclasses import dataclass

__all__ = ['Decision', 'MasterRestartDetector', 'Verdict']


class Verdict(enum.Enum):
    NONE = 'none'  # nothing to do
    SILENT = 'silent'  # the master stopped answering (said once per outage)
    BACK = 'back'  # the same master answers again and still knows this node: nothing lost
    REGISTER = 'register'  # register everything again
    NAME_TAKEN = 'name_taken'  # the master lists this node's name under another URI (said once)


@dataclass(frozen=True)
class Decision:
    """What to do after one poll, and why."""

    verdict: Verdict
    old_pid: int | None = None  # the master the node last registered with (None: not known yet)
    new_pid: int | None = None  # the master that answered this poll (None: no answer)
    reason: str = ''
    silent_for: float = 0.0  # seconds the master had not answered before this poll
    other_uri: str = ''  # with NAME_TAKEN: the URI the master has for this node's name


class MasterRestartDetector:
    """Turns polls of the master (its pid, and the URI it has for this node) into decisions.

    :param node_uri: this node's XML-RPC URI, as it registered it.
    :param clock: monotonic seconds (injectable for tests); used for ``silent_for``.

    The caller polls, passes what it saw to :meth:`observe`, and after a
    ``REGISTER`` decision reports the outcome with :meth:`registered` or
    :meth:`registration_failed` (then the next answered poll says ``REGISTER``
    again). Not thread-safe: one watcher thread owns it.
    """

    def __init__(self, node_uri: str, clock: Callable[[], float] = time.monotonic):
        self.node_uri = node_uri
        self._clock = clock
        self._pid: int | None = None  # the master process that has this node's registrations
        self._failed = False  # the last re-registration did not complete
        self._silent_since: float | None = None
        self._taken_by: str | None = None

    @property
    def pid(self) -> int | None:
        """The pid of the master this node is registered with, as far as the detector knows."""
        return self._pid

    def observe(self, pid: int | None, registered_uri: str | None) -> Decision:
        """One poll: ``pid`` from ``getPid`` (None: no answer), ``registered_uri`` from ``lookupNode``.

        ``registered_uri`` is None when the master does not know this node's name.
        """
        now = self._clock()
        if pid is None:
            if self._silent_since is not None:
                return Decision(Verdict.NONE, self._pid)
            self._silent_since = now
            return Decision(Verdict.SILENT, self._pid, reason='the master does not answer')
        silent_for = 0.0 if self._silent_since is None else now - self._silent_since
        self._silent_since = None
        old = self._pid
        if registered_uri is not None and registered_uri != self.node_uri:
            if registered_uri == self._taken_by:
                return Decision(Verdict.NONE, old, pid, silent_for=silent_for)
            self._taken_by = registered_uri
            return Decision(
                Verdict.NAME_TAKEN,
                old,
                pid,
                reason=f'the master has this node name at {registered_uri}',
                silent_for=silent_for,
                other_uri=registered_uri,
            )
        self._taken_by = None
        if old is None:
            # First answer: init_node registered everything with this master.
            self._pid = pid
            if registered_uri is None:
                return Decision(Verdict.REGISTER, None, pid, 'the master does not know this node', silent_for)
            return Decision(Verdict.NONE, pid, pid, silent_for=silent_for)
        if pid != old:
            return Decision(Verdict.REGISTER, old, pid, 'new master process', silent_for)
        if registered_uri is None:
            return Decision(Verdict.REGISTER, old, pid, 'the master does not know this node', silent_for)
        if self._failed:
            return Decision(Verdict.REGISTER, old, pid, 'the last registration failed', silent_for)
        if silent_for > 0:
            return Decision(Verdict.BACK, old, pid, 'the same master answers again', silent_for)
        return Decision(Verdict.NONE, old, pid, silent_for=silent_for)

    def registered(self, pid: int) -> None:
        """Everything was registered again with the master whose pid is ``pid``."""
        self._pid = pid
        self._failed = False

    def registration_failed(self) -> None:
        """Registering again did not complete: the next answered poll says ``REGISTER`` again."""
        self._failed = True
