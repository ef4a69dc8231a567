"""One JSON line per reliability test, for the report that ``scripts/reliability_report.py`` writes.

:func:`record` and :class:`Trial` (which writes ``failed`` with the error if its block
raised) append a line to the file named by ``DRVS_RELIABILITY_LOG``, if set;
:func:`sample_resources` reads a process's memory, threads and open files from ``/proc``.
What a line holds: docs/reliability.md ("The suites' figures")::

    with Trial('fault', request.node.name, 'kill -9 a vision system') as trial:
        ...
        trial['recovery_seconds'] = 1.7
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass

__all__ = ['ENV_VARIABLE', 'OUTCOMES', 'SUITES', 'Resources', 'Trial', 'record', 'sample_resources']

ENV_VARIABLE = 'DRVS_RELIABILITY_LOG'
SUITES = ('fault', 'load', 'hostile', 'master')
"""The suites the report knows (another name is reported under its own heading)."""
OUTCOMES = ('survived', 'held', 'failed')
"""``survived``: a fault test passed; ``held``: a load or input test passed; ``failed``: it did not."""


def record(suite: str, test: str, **fields) -> dict | None:
    """Append ``{"suite": suite, "test": test, **fields}`` as one line to ``$DRVS_RELIABILITY_LOG``.

    Returns the line's dict, or None when the variable is unset or empty (nothing written).
    Floats are rounded to 3 decimals. The line is written with one ``write`` to a
    file opened for appending, so lines of concurrent writers do not interleave.

    :raises ValueError: ``suite`` or ``test`` is empty, or a field is not a finite
        number, string, bool, None, or a list or dict of those.
    """
    path = os.environ.get(ENV_VARIABLE)
    if not path:
        return None
    for field, value in (('suite', suite), ('test', test)):
        if not isinstance(value, str) or not value:
            raise ValueError(f'{field}: must be a non-empty string, got {value!r}')
    line = {'suite': suite, 'test': test}
    for field, value in fields.items():
        line[field] = _plain(field, value)
    data = (json.dumps(line, allow_nan=False) + '\n').encode()
    descriptor = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(descriptor, data)
    finally:
        os.close(descriptor)
    return line


def _plain(field: str, value):
    if value is None or isinstance(value, bool | str | int):
        return value
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f'{field}: must be a finite number, got {value}')
        return round(value, 3)
    if isinstance(value, list | tuple):
        return [_plain(field, item) for item in value]
    if isinstance(value, dict):
        return {str(key): _plain(f'{field}.{key}', item) for key, item in value.items()}
    raise ValueError(f'{field}: cannot be written as JSON: {type(value).__name__} {value!r}')


class Trial:
    """Collects a test's numbers and :func:`record` s them when the ``with`` block ends.

    :param suite: one of :data:`SUITES`.
    :param test: the test's id (``request.node.name``).
    :param what: the fault or load, in words.
    :param outcome: the outcome if the block completes (``survived`` or ``held``);
        an exception makes it ``failed``, with the exception's first line as ``error``.

    ``duration_seconds`` is added. Numbers are set like a dict: ``trial['lost'] = 0``.
    An exception is never swallowed. Call ``pytest.skip`` before the block, not in it.
    """

    def __init__(self, suite: str, test: str, what: str, outcome: str = 'survived'):
        if outcome not in OUTCOMES:
            raise ValueError(f'outcome: must be one of {", ".join(OUTCOMES)}, got {outcome!r}')
        self.suite = suite
        self.test = test
        self.what = what
        self.outcome = outcome
        self.numbers: dict[str, object] = {}
        self._started = 0.0

    def __setitem__(self, key: str, value) -> None:
        self.numbers[key] = value

    def __getitem__(self, key: str):
        return self.numbers[key]

    def update(self, **numbers) -> None:
        self.numbers.update(numbers)

    def __enter__(self) -> Trial:
        self._started = time.monotonic()
        return self

    def __exit__(self, exc_type, exc, traceback) -> bool:
        if exc_type is not None and issubclass(exc_type, KeyboardInterrupt | SystemExit | GeneratorExit):
            return False
        fields = {'what': self.what, 'outcome': self.outcome if exc_type is None else 'failed'}
        fields.update(self.numbers)
        fields['duration_seconds'] = time.monotonic() - self._started
        if exc_type is not None:
            text = str(exc).strip().splitlines()
            fields['error'] = f'{exc_type.__name__}: {text[0] if text else ""}'[:300]
        record(self.suite, self.test, **fields)
        return False


@dataclass(frozen=True)
class Resources:
    """What a process holds: resident memory (kB), threads, open file descriptors."""

    rss_kb: int
    threads: int
    fds: int


def sample_resources(pid: int) -> Resources:
    """Read ``VmRSS`` and ``Threads`` from ``/proc/<pid>/status`` and count ``/proc/<pid>/fd``.

    :raises ProcessLookupError: the process is gone.
    """
    try:
        with open(f'/proc/{pid}/status') as handle:
            status = dict(line.split(':', 1) for line in handle if ':' in line)
        fds = len(os.listdir(f'/proc/{pid}/fd'))
    except FileNotFoundError:
        raise ProcessLookupError(f'process {pid}: gone (no /proc/{pid})') from None
    return Resources(
        rss_kb=int(status['VmRSS'].split()[0]), threads=int(status['Threads'].split()[0]), fds=fds
    )
