"""``drvs_token``: the gateway's tokens file, by hand: ``add`` prints a new token once (the file
keeps its salted hash), ``list`` shows names and rights, ``remove`` takes one out. The rules:
docs/gateway.md ("Tokens").
"""

from __future__ import annotations

import argparse
import sys

from drvs.gateway.tokens import ANY, OPERATIONS, TokenFileError, add_token, read_entries, remove_token

__all__ = ['main']


def _names(text: str) -> list[str]:
    return [name.strip() for name in text.split(',') if name.strip()]


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog='drvs_token', description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest='command', required=True)
    add = commands.add_parser('add', help='add a token and print it (once: the file keeps only its hash)')
    add.add_argument('name', help="who holds it (shown in the gateway's messages)")
    add.add_argument(
        '--ops',
        type=_names,
        default=list(OPERATIONS),
        metavar='OP,...',
        help=f'what it may do, of {", ".join(OPERATIONS)} (default: all)',
    )
    add.add_argument(
        '--algorithms',
        type=_names,
        default=[ANY],
        metavar='NAME,...',
        help='the algorithm names it may ask for, e.g. colour,apriltag (default: any)',
    )
    for command in (add, commands.add_parser('list', help='the names and rights of the tokens')):
        command.add_argument('--file', required=True, help='the tokens file (made by the first add)')
    remove = commands.add_parser('remove', help='remove the token NAME')
    remove.add_argument('name')
    remove.add_argument('--file', required=True)
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    """0 done; 1 ``remove`` found no such token; 2 bad options or an unusable file."""
    args = parse_args(argv)
    try:
        if args.command == 'add':
            print(add_token(args.file, args.name, args.ops, args.algorithms))
            print(
                f'drvs_token: added {args.name!r} to {args.file}; keep the token: it is not shown again',
                file=sys.stderr,
            )
        elif args.command == 'list':
            for entry in read_entries(args.file):
                ops, algorithms = ','.join(entry['ops']), ','.join(entry['algorithms'])
                print(f'{entry["name"]}\tops {ops}\talgorithms {algorithms}')
        elif not remove_token(args.file, args.name):
            print(f'drvs_token: {args.file} has no token named {args.name!r}', file=sys.stderr)
            return 1
    except (ValueError, TokenFileError, OSError) as error:
        print(f'drvs_token: {error}', file=sys.stderr)
        return 2
    return 0
