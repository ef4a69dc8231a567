"""The shell examples of a documentation page, for tests that run them as written.

A page's ```` ```sh ```` blocks hold commands; the ``# ...`` lines under a command are its
documented output, in which numbers and ``...`` may differ from what it prints.
"""

from __future__ import annotations

import re
from pathlib import Path

__all__ = ['commands', 'output_pattern', 'shell_blocks']

NUMBER = r'-?\d+(?:\.\d+)?'


def shell_blocks(page: Path | str, indented: bool = False) -> list[str]:
    """The ```sh blocks of a Markdown page, in order; with ``indented``, also those inside list items
    (their indentation removed)."""
    text = Path(page).read_text()
    if not indented:
        return re.findall(r'^```sh\n(.*?)^```', text, re.S | re.M)
    blocks = []
    for indent, body in re.findall(r'^( *)```sh\n(.*?)^\1```', text, re.S | re.M):
        blocks.append(''.join(line.removeprefix(indent) for line in body.splitlines(keepends=True)))
    return blocks


def commands(block: str) -> list[tuple[str, list[str]]]:
    """(command, documented output lines) per command of a block; continuation lines joined.

    >>> commands('ls -l \\\\\\n  /tmp  # the folder\\n# total 0\\n')
    [('ls -l   /tmp', ['total 0'])]
    """
    result: list[tuple[str, list[str]]] = []
    pending = ''
    for line in block.splitlines():
        if line.startswith('# ') and not pending:
            if result:
                result[-1][1].append(line[2:])
            continue
        code = line.split('  #', 1)[0].rstrip()  # a trailing comment explains, it is not output
        if not code:
            continue
        pending += code.removesuffix('\\')  # a backslash-newline joins lines, as in bash
        if not code.endswith('\\') and pending.count('"') % 2 == 0:
            result.append((pending, []))
            pending = ''
        elif not code.endswith('\\'):
            pending += '\n'  # inside a quoted argument that spans lines
    return result


def output_pattern(documented: str) -> re.Pattern:
    """``documented`` as a regex: numbers match any number, ``...`` anything, the rest literally.

    >>> bool(output_pattern('x 5.694..6.095, (1.5, ...)').fullmatch('x 5.7..6.1, (1.25, 2, 3)'))
    True
    """
    parts = re.split(rf'(\.\.\.|{NUMBER})', documented)
    regex = ''.join(
        '.*' if part == '...' else NUMBER if re.fullmatch(NUMBER, part) else re.escape(part) for part in parts
    )
    return re.compile(regex)
