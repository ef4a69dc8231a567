"""Publishes a node's health (:mod:`drvs.common.health`) on ``/diagnostics``, once a period of
wall time, from a guarded thread. What each node reports: its page in docs/nodes/; why
wall time and what a failing health check publishes: docs/design.md ("Parameters, health").
"""

from __future__ import annotations

import logging
import threading
import traceback
from collections.abc import Callable, Sequence

import rospy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from drvs.common.guard import RESTART, LoopGuard
from drvs.common.health import Health, check_failed

logger = logging.getLogger('rosout.' + __name__)

__all__ = ['TOPIC', 'DiagnosticsPublisher', 'health_to_status', 'statuses_to_array']

TOPIC = '/diagnostics'


def health_to_status(health: Health, name: str, hardware_id: str) -> DiagnosticStatus:
    """One ``DiagnosticStatus``: ``health``'s level, message and values under ``name``."""
    return DiagnosticStatus(
        level=int(health.level),
        name=name,
        message=health.message,
        hardware_id=hardware_id,
        values=[KeyValue(key=key, value=value) for key, value in health.values],
    )


def statuses_to_array(statuses: Sequence[DiagnosticStatus], stamp: rospy.Time) -> DiagnosticArray:
    """A ``DiagnosticArray`` of ``statuses`` stamped ``stamp``."""
    array = DiagnosticArray(status=list(statuses))
    array.header.stamp = stamp
    return array


class DiagnosticsPublisher:
    """Publishes ``sample()`` on ``/diagnostics`` every ``period`` seconds, from a guarded thread.

    :param name: the status name, ``'drvs: <node name>'`` by convention (``'drvs: /cam1'``),
        so an aggregator can group DRVS nodes by the prefix.
    :param hardware_id: what the status is about (the camera, the robot, the host).
    :param sample: returns the node's health now; called on the publisher's thread,
        so it must take the node's locks for what it reads.
    :param period: seconds between statuses (1 Hz is the convention).
    :param guard: the node's :class:`drvs.common.guard.LoopGuard`; the loop runs under it with
        ``RESTART`` and ends when it stops. Without one, one is made that shuts the node
        down (``rospy.signal_shutdown``) if the loop keeps failing.

    The constructor does no I/O; :meth:`start` advertises the topic and starts the thread.
    """

    def __init__(
        self,
        name: str,
        hardware_id: str,
        sample: Callable[[], Health],
        period: float = 1.0,
        guard: LoopGuard | None = None,
    ):
        if not period > 0:
            raise ValueError(f'period: must be positive, got {period}')
        self.name = name
        self.hardware_id = hardware_id
        self.sample = sample
        self.period = float(period)
        self.guard = guard
        self._stopped = threading.Event()
        self._last_failure: str | None = None  # the failure logged last; None while checks succeed
        self._publisher: rospy.Publisher | None = None
        self._thread: threading.Thread | None = None

    def status(self) -> DiagnosticStatus:
        """The status to publish now: ``sample()``'s, or ERROR if it raised or returned no Health."""
        try:
            health = self.sample()
            if not isinstance(health, Health):
                raise TypeError(f'sample() must return a Health, got {type(health).__name__}')
        except Exception as error:
            health = check_failed(error)
            if health.message != self._last_failure:
                logger.error('%s: %s\n%s', self.name, health.message, traceback.format_exc())
                self._last_failure = health.message
        else:
            if self._last_failure is not None:
                logger.info('%s: health check works again', self.name)
                self._last_failure = None
        return health_to_status(health, self.name, self.hardware_id)

    def publish(self) -> None:
        """Sample and publish one status now (after :meth:`start`)."""
        if self._publisher is None:
            raise RuntimeError('publish: call start() first')
        self._publisher.publish(statuses_to_array([self.status()], rospy.Time.now()))

    def start(self) -> None:
        """Advertise ``/diagnostics`` and start publishing, the first status at once."""
        if self._thread is not None:
            raise RuntimeError('start: already started')
        self._publisher = rospy.Publisher(TOPIC, DiagnosticArray, queue_size=10)
        if self.guard is None:
            self.guard = LoopGuard(on_fatal=lambda reason: rospy.signal_shutdown(reason))
        self._thread = self.guard.spawn(self._loop, f'diagnostics {self.name}', RESTART)

    def stop(self) -> None:
        """Stop publishing (the thread ends within a period) and unadvertise."""
        self._stopped.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=self.period + 1.0)
        if self._publisher is not None:
            self._publisher.unregister()

    def _running(self) -> bool:
        return not (self._stopped.is_set() or self.guard.stop.is_set() or rospy.is_shutdown())

    def _loop(self) -> None:
        while self._running():
            try:
                self.publish()
            except rospy.ROSException:
                if not self._running():
                    return  # the node shut down while publishing: the topic is closed
                raise
            self._stopped.wait(self.period)
