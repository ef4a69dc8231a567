"""A run's report regenerated from its bag (``drvs_report``), without a ROS master.

``scripts/run_scenario.sh --record`` leaves ``run.bag``: every topic the scenario
recorder reads and the recorder's own drvs/RecorderSample messages. :func:`read_bag`
feeds them, in recorded order, to the :class:`drvs.ros.recorder.RunRecorder` the
live recorder uses, up to the recorder's final sample, so :func:`regenerate`
writes the ``summary.json`` the live recorder wrote, and its ``trace.json`` and
``run.png``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import rosbag

from drvs.msg import RecorderSample
from drvs.ros.recorder import RunRecorder
from drvs.sim.report import write_report
from drvs.sim.world import WorldError
from drvs.sim.world_file import load_world


class BagReportError(Exception):
    """The bag cannot give a report: missing, unreadable, not a recorded run, or its world is gone."""


def read_bag(path: str | Path) -> RunRecorder:
    """The recorder fed the run in the bag at ``path``.

    :raises BagReportError: naming the bag (or the world file) and the problem.
    """
    path = Path(path)
    if not path.exists():
        raise BagReportError(f'{path}: no such file')
    if not path.is_file():
        raise BagReportError(f'{path}: not a file')
    try:
        bag = rosbag.Bag(str(path))
    except rosbag.ROSBagUnindexedException:
        message = 'not indexed (its recording did not stop cleanly): rosbag reindex it'
        raise BagReportError(f'{path}: {message}') from None
    except (rosbag.ROSBagException, OSError) as error:
        raise BagReportError(f'{path}: not a readable bag: {error}') from None
    with bag:
        topics = bag.get_type_and_topic_info().topics
        samples = sorted(name for name, info in topics.items() if info.msg_type == RecorderSample._type)
        if not samples:
            raise BagReportError(
                f'{path}: no {RecorderSample._type} messages: not a run recorded by run_scenario.sh --record'
            )
        first = next(bag.read_messages(topics=samples)).message
        try:
            world = load_world(first.world)
        except WorldError as error:
            raise BagReportError(f'{path}: the world of the run: {error}') from None
        recorder = RunRecorder(world)
        handlers = {name: recorder.on_sample for name in samples}
        for name, (message_type, handler) in recorder.topics().items():
            if name not in topics:
                continue
            if topics[name].msg_type != message_type._type:
                raise BagReportError(
                    f'{path}: {name}: expected {message_type._type}, got {topics[name].msg_type}'
                )
            handlers[name] = handler
        for name, msg, _ in bag.read_messages(topics=list(handlers)):
            handlers[name](msg)
            if recorder.closed:
                break
    return recorder


def regenerate(path: str | Path, out: str | Path) -> dict:
    """Write ``summary.json``, ``trace.json`` and ``run.png`` of the bag's run into ``out``.

    :returns: the summary.
    :raises BagReportError: as :func:`read_bag`, or when ``out`` cannot be written.
    """
    recorder = read_bag(path)
    try:
        return write_report(recorder.record, out)
    except OSError as error:
        raise BagReportError(f'{out}: cannot write the report: {error.strerror}') from None


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog='drvs_report',
        description='Regenerate summary.json, trace.json and run.png of a run from its bag '
        '(scripts/run_scenario.sh --record); no ROS master needed.',
    )
    parser.add_argument('bag', type=Path, help="the run's bag, e.g. out/localisation/run.bag")
    parser.add_argument('--out', type=Path, help="folder for the report (default: the bag's folder)")
    return parser.parse_args(argv)


def report(args: argparse.Namespace) -> int:
    """``drvs_report``: 0 with the report written, 2 with one line on stderr saying why not."""
    out = args.out if args.out is not None else args.bag.parent
    try:
        regenerate(args.bag, out)
    except BagReportError as error:
        print(f'drvs_report: {error}', file=sys.stderr)
        return 2
    print(f'drvs_report: wrote {out / "summary.json"}, {out / "trace.json"} and {out / "run.png"}')
    return 0
