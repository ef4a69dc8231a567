#!/usr/bin/env python3
"""Run a node with chosen functions timed in CPU time: ``profiled.py OUT STEPS NODE [ARGS...]``.

``STEPS`` is a comma-separated list of ``module:Qualified.name`` (a function or a
method, rospy's or DRVS's). Each is replaced, before the node starts, by a wrapper
that adds the CPU time of its thread (``time.thread_time``) spent in the call,
callees included, to a tally. When the node exits (SIGINT, as the harness stops
it), ``OUT`` gets JSON ``{"module:Qualified.name": {"calls": n, "cpu_s": s}}``: the
tallies as they were when its shutdown began (rospy's threads of persistent
service connections then call ``receive_once`` in a busy loop until the process
ends, which is no request's cost). On SIGUSR1 it writes the tallies so far, in the
same form, to ``OUT.mark`` (so a bench can tell two runs apart: the second is the
final tallies less the mark).

Why not cProfile: it measures wall-clock time, so on a shared, loaded machine a
thread's wait for the CPU or for the interpreter lock counts as the function's; and
with a CPU-time timer it would read that clock twice per Python call, more than
the calls themselves. Timing a dozen chosen steps costs a microsecond each.
"""

import functools
import importlib
import json
import runpy
import signal
import sys
import threading
import time
from pathlib import Path

import rospy

_tally: dict[str, list] = {}  # step -> [calls, cpu seconds]
_lock = threading.Lock()


def timed(path: str) -> None:
    """Replace the function ``module:Qualified.name`` by one that tallies its CPU time."""
    module_name, _, qualified = path.partition(':')
    owner = importlib.import_module(module_name)
    *outer, name = qualified.split('.')
    for part in outer:
        owner = getattr(owner, part)
    original = getattr(owner, name)
    tally = _tally.setdefault(path, [0, 0.0])

    @functools.wraps(original)
    def wrapper(*args, **kwargs):
        start = time.thread_time()
        try:
            return original(*args, **kwargs)
        finally:
            spent = time.thread_time() - start
            with _lock:
                tally[0] += 1
                tally[1] += spent

    setattr(owner, name, wrapper)


def snapshot() -> dict:
    with _lock:
        return {step: {'calls': calls, 'cpu_s': seconds} for step, (calls, seconds) in _tally.items()}


def main() -> None:
    out, steps, node, *args = sys.argv[1:]
    sys.argv = [node, *args]
    sys.path.insert(0, str(Path(node).resolve().parent))
    for step in filter(None, steps.split(',')):
        timed(step)

    def mark(*_) -> None:  # on a thread: the main thread may hold _lock when the signal comes
        threading.Thread(target=lambda: Path(out + '.mark').write_text(json.dumps(snapshot()))).start()

    signal.signal(signal.SIGUSR1, mark)
    taken = []
    rospy.on_shutdown(lambda: taken.append(snapshot()))  # before the node's own hooks: they run in order
    try:
        runpy.run_path(node, run_name='__main__')
    finally:
        Path(out).write_text(json.dumps(taken[0] if taken else snapshot(), indent=1))


if __name__ == '__main__':
    main()
