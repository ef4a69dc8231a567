"""How healthy a DRVS node is, decided from plain facts: OK, WARN or ERROR, and why.

One function per node (:func:`server_health`, :func:`vision_system_health`,
:func:`robot_health`) turns what the node counts into the level, the one-line message
and the values of its ``/diagnostics`` status, unit-tested without ROS (the level
constants repeat ``diagnostic_msgs/DiagnosticStatus``'s; a test checks they agree).
What each level means for each node: the "Health" section of its page under docs/nodes/;
how rules combine: docs/design.md.

>>> server_health(2, 0, 100, {}, {}, 0, 0).message
'ok'
>>> robot_health('failed', 'no fix for 5.0 s', 6.0, 5.0, True).message
'failed: no fix for 5.0 s'
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from drvs.common import status as drvs_status

__all__ = [
    'ERROR',
    'LEVEL_NAMES',
    'OK',
    'STALE',
    'WARN',
    'Health',
    'check_failed',
    'robot_health',
    'server_health',
    'vision_system_health',
]

# diagnostic_msgs/DiagnosticStatus: byte OK=0, WARN=1, ERROR=2, STALE=3.
OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = {OK: 'OK', WARN: 'WARN', ERROR: 'ERROR', STALE: 'STALE'}

# A queue fuller than this fraction is a warning: the next burst will be refused.
NEARLY_FULL = 0.8

# Robot states (drvs.robot.controller) in which the fix and coverage no longer matter.
_FINAL_ROBOT_STATES = ('arrived', 'failed')


@dataclass
class Health:
    """One node's health: a level, one line saying what is wrong (or ``'ok'``), and the facts.

    :param level: ``OK``, ``WARN``, ``ERROR`` or ``STALE``.
    :param message: one line: every problem, worst first, or ``'ok'``.
    :param values: ``(key, value)`` pairs, both strings, in display order; units in the keys.
    """

    level: int
    message: str
    values: list[tuple[str, str]] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.level not in LEVEL_NAMES:
            raise ValueError(
                f'level: must be one of 0 (OK), 1 (WARN), 2 (ERROR), 3 (STALE), got {self.level!r}'
            )
        if not isinstance(self.message, str):
            raise TypeError(f'message: must be a str, got {type(self.message).__name__}')
        for key, value in self.values:
            if not isinstance(key, str) or not isinstance(value, str):
                raise TypeError(
                    f'values: key and value must be str, got {type(key).__name__} {key!r}: '
                    f'{type(value).__name__} {value!r}'
                )

    @property
    def level_name(self) -> str:
        """``'WARN'`` for 1."""
        return LEVEL_NAMES[self.level]


def check_failed(error: BaseException) -> Health:
    """The health of a node whose health check itself raised ``error``: ERROR, naming it.

    >>> check_failed(KeyError('queue')).message
    "health check failed: KeyError: 'queue'"
    """
    return Health(ERROR, f'health check failed: {type(error).__name__}: {error}')


def _verdict(problems: list[tuple[int, str]], values: list[tuple[str, str]]) -> Health:
    """The worst level of ``problems`` and all their texts, errors first; OK and ``'ok'`` if none."""
    if not problems:
        return Health(OK, 'ok', values)
    ordered = sorted(problems, key=lambda problem: -problem[0])  # stable: rule order within a level
    return Health(ordered[0][0], '; '.join(text for _, text in ordered), values)


def _count(number: int, noun: str) -> str:
    """``'1 vision system'``, ``'2 vision systems'``."""
    return f'{number} {noun}' if number == 1 else f'{number} {noun}s'


def _seconds(value: float | None) -> str:
    return 'none' if value is None else f'{value:.2f}'


def _yes(flag: bool) -> str:
    return 'yes' if flag else 'no'


def _refusal_names(*counts: Mapping[str, int]) -> list[str]:
    """Every refusal status name: the known ones in code order, then any other key, sorted."""
    known = [name for code, name in drvs_status.NAMES.items() if code != drvs_status.ACCEPTED]
    others = sorted({name for count in counts for name in count} - set(known))
    return known + others


def server_health(
    registered: int,
    pending_forwards: int,
    max_pending: int,
    refusals_by_status: Mapping[str, int],
    refusals_recent: Mapping[str, int],
    rate_limited_callers: int,
    ejected: int,
    watches: int = 0,
    left_out: Mapping[str, str] | None = None,
    tracks: int = 0,
    registry: str = 'memory',
    registry_problem: str | None = None,
    site: str = '',
) -> Health:
    """The server's health from its registry, its forwarding pool and its refusals.

    :param registered: vision systems registered now.
    :param pending_forwards: forwards queued or in flight now.
    :param max_pending: the forwarding pool's limit; at it, requests are refused ``BUSY``.
    :param refusals_by_status: refusals since start, by status name (``'BUSY'``: 4).
    :param refusals_recent: refusals in the last period (since the previous status).
    :param rate_limited_callers: callers currently over their share.
    :param ejected: vision systems currently ejected after failed forwards.
    :param watches: watches standing now (a value only: any number is healthy).
    :param left_out: vision systems the fusion stage leaves out (their outlines disagree with
        their neighbours'), with why.
    :param tracks: fused tracks now (a value only).
    :param registry: where the registry lives: ``memory`` or the database (a value only).
    :param registry_problem: why the registry's database is out of reach, None when it is not.
    :param site: the server's ``~site`` ('' : the only one; a value only).

    ======================================================  =======  ===============================
    rule                                                    level    message
    ======================================================  =======  ===============================
    ``pending_forwards >= max_pending``                     ERROR    forward queue full: refusing
                                                                     BUSY (P of M pending)
    ``registry_problem``                                    ERROR    registry database unreachable
                                                                     for 12 s (...): serving from ...
    ``registered == 0``                                     WARN     no vision system registered
    ``pending_forwards > 0.8 * max_pending``                WARN     forward queue N% full
                                                                     (P of M pending)
    ``BUSY`` or ``RATE_LIMITED`` refusals in the last       WARN     refused 3 BUSY, 1 RATE_LIMITED
    period                                                           in the last period
    ``ejected > 0``                                         WARN     1 vision system ejected after
                                                                     failed forwards
    ``left_out`` not empty                                  WARN     left out of fusion: /cam3/...:
                                                                     its outlines are 0.8 m from ...
    none of these                                           OK       ok
    ======================================================  =======  ===============================

    No vision system registered is a warning, not an error: the server itself
    works (a request is accepted and sent to 0 vision systems), and at start-up the
    cameras register a moment after the server. ``INVALID`` and ``UNSUPPORTED``
    refusals are the callers' mistakes, not the server's health: counted in the
    values only, like ``UNAVAILABLE``.
    """
    if max_pending <= 0:
        raise ValueError(f'max_pending: must be positive, got {max_pending}')
    problems: list[tuple[int, str]] = []
    if pending_forwards >= max_pending:
        problems.append(
            (ERROR, f'forward queue full: refusing BUSY ({pending_forwards} of {max_pending} pending)')
        )
    if registry_problem:
        problems.append((ERROR, registry_problem))
    if registered == 0:
        problems.append((WARN, 'no vision system registered'))
    if max_pending > pending_forwards > NEARLY_FULL * max_pending:
        percent = int(100 * pending_forwards / max_pending)
        problems.append(
            (WARN, f'forward queue {percent}% full ({pending_forwards} of {max_pending} pending)')
        )
    overload = [
        f'{refusals_recent[name]} {name}'
        for name in ('BUSY', 'RATE_LIMITED')
        if refusals_recent.get(name, 0) > 0
    ]
    if overload:
        problems.append((WARN, f'refused {", ".join(overload)} in the last period'))
    if ejected > 0:
        problems.append((WARN, f'{_count(ejected, "vision system")} ejected after failed forwards'))
    left_out = left_out or {}
    if left_out:
        reasons = '; '.join(f'{name}: {why}' for name, why in sorted(left_out.items()))
        problems.append((WARN, f'left out of fusion: {reasons}'))
    values = [
        ('registered vision systems', str(registered)),
        ('registry', f'{registry} (unreachable)' if registry_problem else registry),
        ('site', site or '(the only one)'),
        ('pending forwards', str(pending_forwards)),
        ('max pending forwards', str(max_pending)),
        ('rate-limited callers', str(rate_limited_callers)),
        ('ejected vision systems', str(ejected)),
        ('watches', str(watches)),
        ('fused tracks', str(tracks)),
        ('left out of fusion', ', '.join(sorted(left_out)) or 'none'),
    ]
    for name in _refusal_names(refusals_by_status, refusals_recent):
        values.append((f'refused {name} (last period)', str(refusals_recent.get(name, 0))))
        values.append((f'refused {name} (since start)', str(refusals_by_status.get(name, 0))))
    return _verdict(problems, values)


def vision_system_health(
    registered: bool,
    source: str,
    frame_age: float | None,
    stale_after: float,
    queue_length: int,
    queue_size: int,
    callback_failures_recent: int,
    callbacks_recent: int,
    registration_status: str = '',
    registration_error: str = '',
    watches: int = 0,
    frame_problems: Sequence[str] = (),
    server: str = '',
    server_moves: int = 0,
) -> Health:
    """A vision system's health from its registration, its camera feed, its queue and its callbacks.

    :param registered: whether the server holds a lease for it now.
    :param source: ``'topic'`` (a ROS camera) or ``'render'`` (renders its own frames).
    :param frame_age: seconds since the newest frame arrived; None when there is none
        yet, or for ``render`` (frames are made on demand, so they cannot go stale).
    :param stale_after: a feed whose newest frame is older than this is stale.
    :param queue_length: requests queued now.
    :param queue_size: the queue's bound (0: not bounded, never nearly full).
    :param callback_failures_recent: callbacks to robots that failed in the last period.
    :param callbacks_recent: callbacks attempted in the last period.
    :param registration_status: the status name of the last refused registration
        (``'INVALID'``, ``'UNAVAILABLE'``, ...); empty when the last one was accepted
        or got no answer.
    :param registration_error: why the last registration failed (the refusal's
        message, or why the server did not answer); empty when it succeeded.
    :param watches: standing requests (watches) it serves now; a value, no rule.
    :param frame_problems: why algorithms cannot work on the camera's frames now (an
        ``elevation`` without usable depth, a ``foreground`` without its reference), one
        message each, naming the algorithm.
    :param server: the server (registration service) it registers through now, and
        ``server_moves`` the times it moved to the next of ``~servers``; values, no rule
        (shown when ``server`` is given).

    ======================================================  =======  ===============================
    rule                                                    level    message
    ======================================================  =======  ===============================
    ``frame_age > stale_after``                             ERROR    camera feed stale: last frame
                                                                     3.2 s ago (stale after 2.0 s)
    ``source == 'topic'`` and ``frame_age is None``         ERROR    no frame yet from the camera
                                                                     topic
    ``registration_status == 'INVALID'``                    ERROR    registration refused INVALID:
                                                                     <error>
    not ``registered`` (otherwise)                          WARN     not registered: refused
                                                                     UNAVAILABLE: <error>, or
                                                                     not registered: <error>
    ``queue_length > 0.8 * queue_size``                     WARN     request queue N% full
                                                                     (L of S)
    ``callback_failures_recent > 0``                        WARN     2 of 5 callbacks failed in
                                                                     the last period
    each of ``frame_problems``                              WARN     elevation: the depth image
                                                                     has no valid pixel ...
    none of these                                           OK       ok
    ======================================================  =======  ===============================

    ``INVALID`` is an error because sending the same registration again cannot
    succeed (the field of view or the algorithms are wrong); any other reason not
    to be registered (the server is unreachable, busy, or ejected this camera for
    a while) is temporary and retried.
    """
    if not stale_after > 0:
        raise ValueError(f'stale_after: must be positive, got {stale_after}')
    problems: list[tuple[int, str]] = []
    if frame_age is not None and frame_age > stale_after:
        problems.append(
            (ERROR, f'camera feed stale: last frame {frame_age:.1f} s ago (stale after {stale_after:g} s)')
        )
    elif frame_age is None and source == 'topic':
        problems.append((ERROR, 'no frame yet from the camera topic'))
    refusal = f'refused {registration_status}' + (f': {registration_error}' if registration_error else '')
    if registration_status == 'INVALID':
        problems.append((ERROR, f'registration {refusal}'))
    elif not registered:
        if registration_status:
            problems.append((WARN, f'not registered: {refusal}'))
        else:
            problems.append(
                (WARN, f'not registered: {registration_error or "no answer from the server yet"}')
            )
    if queue_size > 0 and queue_length > NEARLY_FULL * queue_size:
        percent = int(100 * queue_length / queue_size)
        problems.append((WARN, f'request queue {percent}% full ({queue_length} of {queue_size})'))
    if callback_failures_recent > 0:
        problems.append(
            (WARN, f'{callback_failures_recent} of {callbacks_recent} callbacks failed in the last period')
        )
    problems += [(WARN, problem) for problem in frame_problems]
    values = [
        ('registered', _yes(registered)),
        ('source', source),
        ('frame age (s)', _seconds(frame_age)),
        ('stale after (s)', _seconds(stale_after)),
        ('queue length', str(queue_length)),
        ('queue size', str(queue_size)),
        ('watches', str(watches)),
        ('callbacks (last period)', str(callbacks_recent)),
        ('callback failures (last period)', str(callback_failures_recent)),
        ('last registration refusal', registration_status or 'none'),
        ('last registration error', registration_error or 'none'),
        *_server_values(server, server_moves),
    ]
    return _verdict(problems, values)


def robot_health(
    state: str,
    reason: str,
    fix_age: float | None,
    fix_timeout: float,
    coverage: bool,
    server: str = '',
    server_moves: int = 0,
) -> Health:
    """A robot's health from its controller state, the age of its newest fix and its coverage.

    :param state: the controller's state (:mod:`drvs.robot.controller`): ``localising``,
        ``moving``, ``blocked``, ``arriving``, ``arrived`` or ``failed``.
    :param reason: why it is in that state (why it failed, what blocks it); may be empty.
    :param fix_age: seconds since the newest fix of the robot; None when there is none yet.
    :param fix_timeout: seconds without a fix after which the robot fails.
    :param coverage: whether some registered vision system sees the robot.
    :param server: the server (service) it asks now, and ``server_moves`` the times it moved
        to the next of ``~servers``; values, no rule (shown when ``server`` is given).

    ======================================================  =======  ===============================
    rule                                                    level    message
    ======================================================  =======  ===============================
    ``state == 'failed'``                                   ERROR    failed: <reason>
    ``state == 'arrived'``                                  OK       ok (nothing else is checked)
    ``state == 'blocked'``                                  WARN     blocked: <reason>
    ``fix_age is None``                                     WARN     no fix yet
    ``fix_age > fix_timeout / 2``                           WARN     last fix 3.1 s ago (fails
                                                                     after 5.0 s)
    not ``coverage``                                        WARN     no vision system covers the
                                                                     robot
    none of these                                           OK       ok
    ======================================================  =======  ===============================

    A robot that arrived or failed stops asking for fixes, so in those states the
    fix age and the coverage are reported but not judged.
    """
    if not fix_timeout > 0:
        raise ValueError(f'fix_timeout: must be positive, got {fix_timeout}')
    problems: list[tuple[int, str]] = []
    if state == 'failed':
        problems.append((ERROR, f'failed: {reason}' if reason else 'failed'))
    elif state not in _FINAL_ROBOT_STATES:
        if state == 'blocked':
            problems.append((WARN, f'blocked: {reason}' if reason else 'blocked'))
        if fix_age is None:
            problems.append((WARN, 'no fix yet'))
        elif fix_age > fix_timeout / 2:
            problems.append((WARN, f'last fix {fix_age:.1f} s ago (fails after {fix_timeout:g} s)'))
        if not coverage:
            problems.append((WARN, 'no vision system covers the robot'))
    values = [
        ('state', state),
        ('reason', reason or 'none'),
        ('fix age (s)', _seconds(fix_age)),
        ('fix timeout (s)', _seconds(fix_timeout)),
        ('covered', _yes(coverage)),
        *_server_values(server, server_moves),
    ]
    return _verdict(problems, values)


def _server_values(server: str, moves: int) -> list[tuple[str, str]]:
    """The values of a client of several servers: the one in use, and its moves."""
    return [('DRVS server', server), ('server moves', str(moves))] if server else []
