"""Registers a rospy node again after the ROS master restarts (ros/ros_comm#185).

:class:`MasterWatch` polls the master and, when
:class:`drvs.common.master_restart.MasterRestartDetector` says so, registers every
publication, subscription and service of this process again, as rospy does at
``init_node``. Why and how: docs/design.md ("rospy facts the design rests on").
"""

from __future__ import annotations

import http.client
import logging
import threading
import xmlrpc.client
from dataclasses import dataclass

import rosgraph
import rospy
import rospy.core
from rospy.impl.registration import get_service_manager, get_topic_manager

from drvs.common.master_restart import MasterRestartDetector, Verdict
from drvs.ros.service_client import TimeoutTransport

logger = logging.getLogger('rosout.' + __name__)

__all__ = ['MasterWatch', 'RegistrationError', 'Registered']

_NO_ANSWER = (OSError, xmlrpc.client.Error, http.client.HTTPException)


class RegistrationError(Exception):
    """Registering again did not complete; the message says what failed."""


@dataclass(frozen=True)
class Registered:
    """What one re-registration registered."""

    publications: int
    subscriptions: int
    services: int


class MasterWatch:
    """Watches the ROS master from a daemon thread and registers this node again after a restart.

    :param period: seconds between polls of the master.
    :param timeout: seconds one XML-RPC call (poll, registration, publisherUpdate) may take.
    :param lock_timeout: seconds to wait for rospy's topic and service managers' locks.
    :param master_uri: the master to watch (default: this node's, from ROS_MASTER_URI or ``__master:=``).

    The constructor does no I/O; :meth:`start` (after ``rospy.init_node``) starts the thread.
    """

    def __init__(
        self,
        period: float = 1.0,
        timeout: float = 2.0,
        lock_timeout: float = 5.0,
        master_uri: str | None = None,
    ):
        for name, value in (('period', period), ('timeout', timeout), ('lock_timeout', lock_timeout)):
            if not value > 0:
                raise ValueError(f'{name}: must be positive, got {value}')
        self.period = float(period)
        self.timeout = float(timeout)
        self.lock_timeout = float(lock_timeout)
        self.master_uri = master_uri
        self.detector: MasterRestartDetector | None = None
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._caller_id = ''
        self._node_uri = ''

    # -- lifecycle -----------------------------------------------------------------------------
    def start(self) -> MasterWatch:
        """Start watching (call after ``rospy.init_node``); returns ``self``."""
        if self._thread is not None:
            raise RuntimeError('MasterWatch.start: already started')
        node_uri = rospy.core.get_node_uri()
        if not node_uri:
            raise RuntimeError('MasterWatch.start: call rospy.init_node first')
        self._node_uri = node_uri
        self._caller_id = rospy.get_name()
        self.master_uri = self.master_uri or rosgraph.get_master_uri()
        self.detector = MasterRestartDetector(node_uri)
        self._thread = threading.Thread(target=self._run, name='master_watch', daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop watching and wait (bounded) for the thread to end."""
        self._stopping.set()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(self.timeout + self.lock_timeout + self.period)

    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # -- the thread ----------------------------------------------------------------------------
    def _run(self) -> None:
        while not self._stopping.is_set() and not rospy.core.is_shutdown_requested():
            try:
                self.poll()
            except Exception:  # the watch is what keeps the node reachable: log and go on
                logger.exception('master watch: unexpected error (watching on)')
            self._stopping.wait(self.period)

    def poll(self) -> Verdict:
        """Ask the master once and act on the answer; return the detector's verdict."""
        pid, registered_uri = self._ask_master()
        decision = self.detector.observe(pid, registered_uri)
        verdict = decision.verdict
        if verdict is Verdict.SILENT:
            logger.warning('master at %s does not answer; watching for its return', self.master_uri)
        elif verdict is Verdict.BACK:
            logger.info(
                'master at %s answers again after %.1f s (same pid %s)',
                self.master_uri,
                decision.silent_for,
                decision.new_pid,
            )
        elif verdict is Verdict.NAME_TAKEN:
            logger.warning(
                'master at %s lists node %s at %s, not here (%s): not registering again',
                self.master_uri,
                self._caller_id,
                decision.other_uri,
                self._node_uri,
            )
        elif verdict is Verdict.REGISTER:
            if rospy.core.is_shutdown_requested() or self._stopping.is_set():
                return Verdict.NONE
            try:
                done = self.register_all()
            except RegistrationError as error:
                self.detector.registration_failed()
                logger.error('master at %s: %s; trying again in %g s', self.master_uri, error, self.period)
                return verdict
            except Exception:
                self.detector.registration_failed()
                raise
            self.detector.registered(decision.new_pid)
            counts = (
                f'registered again {done.publications} publications, '
                f'{done.subscriptions} subscriptions, {done.services} services'
            )
            if decision.old_pid is not None and decision.old_pid != decision.new_pid:
                logger.info(
                    'master at %s restarted (pid %s -> %s): %s',
                    self.master_uri,
                    decision.old_pid,
                    decision.new_pid,
                    counts,
                )
            else:
                logger.info(
                    'master at %s (pid %s): %s: %s',
                    self.master_uri,
                    decision.new_pid,
                    decision.reason,
                    counts,
                )
        return verdict

    def _proxy(self, uri: str) -> xmlrpc.client.ServerProxy:
        return xmlrpc.client.ServerProxy(uri, transport=TimeoutTransport(self.timeout))

    def _ask_master(self) -> tuple[int | None, str | None]:
        """(the master's pid or None if it did not answer, the URI it has for this node or None)."""
        try:
            with self._proxy(self.master_uri) as master:
                multi = xmlrpc.client.MultiCall(master)
                multi.getPid(self._caller_id)
                multi.lookupNode(self._caller_id, self._caller_id)
                (pid_code, _, pid), (node_code, _, node_uri) = tuple(multi())
        except _NO_ANSWER:
            return None, None
        if pid_code != 1:
            return None, None
        return int(pid), (node_uri if node_code == 1 else None)

    # -- registering ---------------------------------------------------------------------------
    def register_all(self) -> Registered:
        """Register every publication, subscription and service of this process with the master.

        :raises RegistrationError: rospy's locks were busy, the master did not answer,
            or it refused a registration.
        """
        topics, services = get_topic_manager(), get_service_manager()
        if not topics.lock.acquire(timeout=self.lock_timeout):
            raise RegistrationError(f'rospy topic manager busy for {self.lock_timeout:g} s')
        try:
            if not services.lock.acquire(timeout=self.lock_timeout):
                raise RegistrationError(f'rospy service manager busy for {self.lock_timeout:g} s')
            try:
                publications = topics.get_publications()
                subscriptions = topics.get_subscriptions()
                provided = services.get_services()
                publishers = self._register(publications, subscriptions, provided)
            finally:
                services.lock.release()
        finally:
            topics.lock.release()
        # Outside the locks: our own XML-RPC server queues the connections for rospy's RegManager.
        failed = []
        for topic, uris in publishers.items():
            error = self._publisher_update(topic, uris) if uris else ''
            if error:
                failed.append(error)
        if failed:
            raise RegistrationError('; '.join(failed))
        return Registered(len(publications), len(subscriptions), len(provided))

    def _register(self, publications, subscriptions, provided) -> dict[str, list[str]]:
        """One multicall registering everything; returns each subscription's current publishers."""
        calls = []
        try:
            with self._proxy(self.master_uri) as master:
                multi = xmlrpc.client.MultiCall(master)
                for topic, topic_type in publications:
                    multi.registerPublisher(self._caller_id, topic, topic_type, self._node_uri)
                    calls.append(('publication', topic))
                for topic, topic_type in subscriptions:
                    multi.registerSubscriber(self._caller_id, topic, topic_type, self._node_uri)
                    calls.append(('subscription', topic))
                for service, service_uri in provided:
                    multi.registerService(self._caller_id, service, service_uri, self._node_uri)
                    calls.append(('service', service))
                results = tuple(multi()) if calls else ()
        except _NO_ANSWER as error:
            raise RegistrationError(f'registering {len(calls)} names failed: {error}') from None
        publishers = {}
        refused = []
        for (kind, name), (code, message, value) in zip(calls, results, strict=True):
            if code != 1:
                refused.append(f'{kind} {name}: {message}')
            elif kind == 'subscription':
                publishers[name] = list(value)
        if refused:
            raise RegistrationError('the master refused ' + '; '.join(refused))
        return publishers

    def _publisher_update(self, topic: str, uris: list[str]) -> str:
        """Tell this node's own XML-RPC API the publishers of ``topic``; return an error or ''."""
        try:
            with self._proxy(self._node_uri) as node:
                code, message, _ = node.publisherUpdate(self._caller_id, topic, uris)
        except _NO_ANSWER as error:
            return f'publisherUpdate of {topic} on this node failed: {error}'
        return '' if code == 1 else f'publisherUpdate of {topic} on this node refused: {message}'


def watch_master(period: float = 1.0) -> MasterWatch:
    """Start a :class:`MasterWatch` for this node (after ``init_node``), stopped at shutdown."""
    watch = MasterWatch(period=period).start()
    rospy.on_shutdown(watch.stop)
    return watch
