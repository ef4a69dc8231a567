"""How every DRVS node starts: find the master, ``init_node``, read the settings, build the node.

A user's mistake is one message and exit code 2 (:data:`USER_ERROR`), never a
traceback; under ``/use_sim_time`` a node is built once simulated time has begun.
What users see: docs/troubleshooting.md; the rospy facts: docs/design.md.
"""

from __future__ import annotations

import http.client
import os
import signal
import sys
import threading
import time
import xmlrpc.client
from collections.abc import Callable, Mapping
from pathlib import Path

import rosgraph
import rospy

from drvs.common.settings import ParamError
from drvs.ros.master_watch import watch_master
from drvs.ros.params import (
    command_line_params,
    origin_note,
    private_param_names,
    read_params,
    unknown_param_warnings,
)
from drvs.ros.service_client import TimeoutTransport

__all__ = [
    'CLOCK_TIMEOUT',
    'MASTER_TIMEOUT',
    'USER_ERROR',
    'NoClock',
    'NoMaster',
    'error_block',
    'master_uri',
    'node_main',
    'spin',
    'wait_for_clock',
    'wait_for_master',
]

USER_ERROR = 2
"""Exit code of a node stopped by a user's mistake (bad parameter, world file, folder, no master)."""

INTERRUPTED = 130
"""Exit code of a node stopped (Ctrl-C, SIGTERM) before it finished starting, as a shell reports it."""

MASTER_TIMEOUT = 10.0
"""Seconds a node waits for the ROS master before it gives up."""

CLOCK_TIMEOUT = 30.0
"""Seconds a node under ``/use_sim_time`` waits for the first ``/clock`` before it gives up."""

USER_ERRORS = (ValueError, OSError)
"""What ``build`` raises for a user's mistake: ValueError (ParamError, WorldError), OSError (a file)."""


class NoMaster(Exception):
    """No ROS master answered; the message says at which URI and what to do."""


def master_uri() -> str:
    """The master's URI: ``__master:=`` on the command line, else ``ROS_MASTER_URI``, else rospy's default.

    :raises NoMaster: for a malformed ``__master:=``.
    """
    try:
        return rosgraph.get_master_uri()
    except ValueError as error:
        raise NoMaster(str(error)) from None


def wait_for_master(timeout: float, uri: str | None = None) -> str:
    """Wait until the master at ``uri`` (default ``ROS_MASTER_URI``) answers; return its URI.

    :raises NoMaster: after ``timeout`` seconds, naming the URI tried and how to fix it.
    """
    unset = ''
    if uri is None:
        uri = master_uri()
        if 'ROS_MASTER_URI' not in os.environ:
            unset = "; ROS_MASTER_URI is not set, so that is rospy's default"
    deadline = time.monotonic() + timeout
    while True:
        left = deadline - time.monotonic()
        try:
            transport = TimeoutTransport(max(0.1, min(2.0, left)))
            with xmlrpc.client.ServerProxy(uri, transport=transport) as master:
                code, message, _ = master.getPid('/drvs_master_check')
            if code == 1:
                return uri
            problem = f'it answered {message!r}'
        except (OSError, http.client.HTTPException, xmlrpc.client.Error, ValueError) as error:  # a bad URI
            problem = getattr(error, 'strerror', None) or str(error)
        if time.monotonic() >= deadline:
            raise NoMaster(
                f'no ROS master at {uri} ({problem}; tried for {timeout:g} s{unset}): '
                'start one with `roscore`, or `source scripts/env.sh`, or set ROS_MASTER_URI '
                "to the running master's URI"
            )
        time.sleep(min(0.2, max(0.0, deadline - time.monotonic())))


class NoClock(Exception):
    """``/use_sim_time`` is true and no ``/clock`` came; the message says who publishes it."""


def wait_for_clock(timeout: float) -> bool:
    """With ``/use_sim_time`` true, wait until rospy has a simulated time: the first ``/clock``
    message came (``rospy.get_time() > 0``). True at once without it; False if the node was shut
    down while waiting.

    :raises NoClock: after ``timeout`` seconds of wall time, naming ``/clock`` and world_sim.
    """
    if not rospy.get_param('/use_sim_time', False):
        return True
    deadline = time.monotonic() + timeout
    while rospy.get_time() <= 0:
        if rospy.is_shutdown():
            return False
        if time.monotonic() >= deadline:
            raise NoClock(
                f'/use_sim_time is true and no /clock came in {timeout:g} s: the simulated time is '
                'published by world_sim (nodes/world_sim): start it, or set /use_sim_time false for real time'
            )
        time.sleep(0.05)
    return True


def error_block(prog: str, error: BaseException) -> str:
    """``prog: message`` for a one-line error; ``prog:`` and the lines indented for several."""
    if isinstance(error, OSError) and error.strerror:
        text = f'{error.filename}: {error.strerror}' if error.filename else error.strerror
    else:
        text = str(error) or type(error).__name__
    lines = text.splitlines()
    if len(lines) == 1:
        return f'{prog}: {lines[0]}'
    return f'{prog}:\n' + '\n'.join(f'  {line}' for line in lines)


def spin(node) -> int:
    """Start ``node`` (built on :class:`drvs.ros.node.NodeScaffold`, as ``node.node``) and serve
    until shutdown; 1 if one of its background loops failed (logged with its traceback), else 0."""
    node.start()
    rospy.spin()
    return 1 if node.node.failure else 0


def shutdown_from_a_thread(signum: int, frame) -> None:
    """SIGINT/SIGTERM handler: ``rospy.signal_shutdown`` on a new thread, not in the handler.

    rospy's own handler shuts the node down inside the signal handler. When the signal
    lands while the main thread is in a call to the master (advertising a topic, say),
    shutting down makes another master call on the same thread, which waits for the
    ServerProxy lock the interrupted call holds: the node hangs for good. From a thread,
    the shutdown waits until the interrupted call has returned.
    """
    reason = f'{signal.Signals(signum).name} received'
    threading.Thread(target=rospy.signal_shutdown, args=(reason,), name='shutdown').start()


def node_main(
    name: str,
    settings_cls,
    build: Callable,
    *,
    run: Callable[[object], int] = spin,
    defaults: Mapping[str, object] | Callable[[], Mapping[str, object]] | None = None,
    anonymous: bool = False,
    disable_signals: bool = False,
    master_timeout: float = MASTER_TIMEOUT,
    no_master_code: int = USER_ERROR,
    watch: bool = True,
    publishes_clock: bool = False,
    clock_timeout: float = CLOCK_TIMEOUT,
    prog: str | None = None,
) -> int:
    """Run a node: its exit code, :data:`USER_ERROR` after one clean message on a user's mistake.

    :param name: the node's default name (``__name:=`` replaces it).
    :param settings_cls: its settings dataclass, read with :func:`drvs.ros.params.read_params`.
    :param build: ``build(settings)``: the node, constructed; what it raises of
        :data:`USER_ERRORS` is the user's mistake.
    :param run: ``run(node)``: starts and serves the node, returns the exit code.
    :param defaults: field defaults known only once the node is up (or a function giving them).
    :param master_timeout: seconds to wait for the master; then ``no_master_code``.
    :param watch: register again after a master restart (:func:`drvs.ros.master_watch.watch_master`).
    :param publishes_clock: the node publishes ``/clock`` itself (world_sim): it does not wait for it.
    :param clock_timeout: seconds to wait for the first ``/clock`` under ``/use_sim_time``.
    :param prog: the name messages start with (default: the executable's).
    """
    prog = prog or Path(sys.argv[0]).name
    try:
        given = command_line_params()
    except ValueError as error:  # a `_name:=value` that is not YAML
        print(error_block(prog, error), file=sys.stderr)
        return USER_ERROR
    try:
        wait_for_master(master_timeout)
    except NoMaster as error:
        print(error_block(prog, error), file=sys.stderr)
        return no_master_code
    if not disable_signals:  # rospy's own handler can deadlock: ours shuts down from a thread
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, shutdown_from_a_thread)
    try:
        rospy.init_node(name, anonymous=anonymous, disable_signals=True)
    except rospy.ROSInitException as error:  # stopped (Ctrl-C, SIGTERM) while registering
        print(error_block(prog, error), file=sys.stderr)
        return INTERRUPTED
    try:
        if watch:
            watch_master()  # registers again after a master restart (ros/ros_comm#185)
        node_name = rospy.get_name()
        private = private_param_names(node_name, rospy.get_param_names())
        for warning in unknown_param_warnings(settings_cls, private, given, node_name):
            rospy.logwarn('%s: %s', prog, warning)
        try:
            settings = read_params(settings_cls, defaults() if callable(defaults) else defaults, given=given)
            if not publishes_clock and not wait_for_clock(clock_timeout):
                return INTERRUPTED  # stopped while waiting
            try:
                node = build(settings)
            except ParamError as error:  # a parameter found wrong while building: where it came from
                raise error.annotated(
                    lambda param: origin_note(node_name, param)
                    if param in private and param not in given
                    else ''
                ) from None
        except (*USER_ERRORS, NoClock) as error:
            rospy.logfatal('%s', error_block(prog, error))
            rospy.signal_shutdown('user error')
            return USER_ERROR
        return run(node)
    finally:
        rospy.signal_shutdown('done')  # nothing if it is shut down already
