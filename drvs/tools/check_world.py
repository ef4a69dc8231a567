"""``drvs_check_world FILE [FILE ...]``: check world files for sense, without ROS.

Prints ``FILE: ok`` for a file that loads, else :class:`drvs.sim.world.WorldError`'s
block (``FILE: N problems:`` and one line per problem), all on stdout; exits 0
when every file is fine, 2 otherwise (a missing file is one line, exit 2 too).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import TextIO

from drvs.sim.world import WorldError
from drvs.sim.world_file import load_world

OK, BAD = 0, 2


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog='drvs_check_world',
        description='Check world files (worlds/README.md) for every problem at once; exit 0 if all are '
        'fine, 2 otherwise.',
    )
    parser.add_argument('files', nargs='+', metavar='FILE', help='a world file (YAML)')
    return parser.parse_args(argv)


def check_files(paths: Sequence[str], out: TextIO) -> int:
    """Write each file's verdict to ``out``; :data:`OK` if all load, else :data:`BAD`."""
    code = OK
    for path in paths:
        try:
            load_world(path)
        except WorldError as error:
            print(error, file=out)
            code = BAD
        else:
            print(f'{path}: ok', file=out)
    return code


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    return check_files(args.files, sys.stdout)
