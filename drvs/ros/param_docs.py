"""Generate the parameter tables of the node pages (docs/nodes/NODE.md) from the nodes' settings dataclasses.

    .venv/bin/python -m drvs.ros.param_docs                     # print every node's table
    .venv/bin/python -m drvs.ros.param_docs --write docs/nodes  # rewrite them in place (make docs)

Each node's table lies in ``docs/nodes/NODE.md`` between ``<!-- params:NODE:begin -->``
and ``<!-- params:NODE:end -->``; one row per field of its settings dataclass, as
declared with :func:`drvs.common.settings.param`. ``test/project/test_param_docs.py`` fails
when a page and the code disagree, so the parameters are documented once.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from drvs.common.settings import annotation_type
from drvs.gateway.params import GatewaySettings
from drvs.robot.params import RobotParams
from drvs.server.params import ServerSettings
from drvs.sim.params import RecorderSettings, SimCameraParams, SiteLinkSettings, WorldSimSettings
from drvs.vision.params import VisionSystemParams

NODES = {
    'drvs_server': ServerSettings,
    'vision_system': VisionSystemParams,
    'blind_robot': RobotParams,
    'world_sim': WorldSimSettings,
    'sim_camera': SimCameraParams,
    'scenario_recorder': RecorderSettings,
    'drvs_gateway': GatewaySettings,
    'drvs_site_link': SiteLinkSettings,
}
"""Node name (its page: docs/nodes/NODE.md, the table between its markers) -> its settings dataclass."""

HEADER = '| parameter | type | default | meaning |\n|---|---|---|---|'


def _type(field: dataclasses.Field) -> str:
    declared = field.metadata.get('range')
    if declared is not None and declared.short.startswith('`'):  # one of some strings
        return declared.short
    text = annotation_type(field.type)[0].__name__
    if field.metadata.get('separator'):
        text += ' or list of str'
    return f'{text} {declared.short}' if declared is not None else text


def _default(field: dataclasses.Field) -> str:
    if field.metadata.get('default_text'):
        return field.metadata['default_text']
    value = field.default
    if value is dataclasses.MISSING:
        return 'required'
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        return f'`{value}`' if value else 'empty'
    if value is None:
        return 'none'
    unit = field.metadata.get('unit', '')
    separator = '' if unit.startswith('/') or not unit else ' '
    return f'{value:g}{separator}{unit}'


def table(cls) -> str:
    """The Markdown table of the settings dataclass ``cls``.

    :raises ValueError: for a field not declared with :func:`drvs.common.settings.param` (no meaning).
    """
    rows = [HEADER]
    for field in dataclasses.fields(cls):
        meaning = field.metadata.get('meaning')
        if not meaning:
            raise ValueError(
                f'{cls.__name__}.{field.name}: no meaning; declare it with drvs.common.settings.param'
            )
        cells = (f'`~{field.name}`', _type(field), _default(field), meaning)
        rows.append('| ' + ' | '.join(cell.replace('|', '\\|') for cell in cells) + ' |')
    return '\n'.join(rows)


def markers(node: str) -> tuple[str, str]:
    return f'<!-- params:{node}:begin -->', f'<!-- params:{node}:end -->'


def block(text: str, node: str) -> str | None:
    """What ``text`` holds between ``node``'s markers (stripped), or None without them."""
    begin, end = markers(node)
    start, stop = text.find(begin), text.find(end)
    if start < 0 or stop < start:
        return None
    return text[start + len(begin) : stop].strip()


def rewritten(text: str, node: str) -> str:
    """``text`` with ``node``'s table regenerated between its markers.

    :raises ValueError: naming the node when its markers are missing.
    """
    begin, end = markers(node)
    if block(text, node) is None:
        raise ValueError(f'{node}: no {begin} ... {end} in the file')
    head, rest = text.split(begin, 1)
    tail = rest.split(end, 1)[1]
    return f'{head}{begin}\n{table(NODES[node])}\n{end}{tail}'


def page(folder: Path, node: str) -> Path:
    """The page of ``node`` in ``folder`` (docs/nodes)."""
    return folder / f'{node}.md'


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        '--write',
        type=Path,
        metavar='FOLDER',
        help='rewrite the tables of the pages FOLDER/NODE.md (docs/nodes)',
    )
    options = parser.parse_args(argv)
    if options.write is None:
        for node, cls in NODES.items():
            print(f'{node}:\n\n{table(cls)}\n')
        return 0
    status = 0
    for node in NODES:
        path = page(options.write, node)
        try:
            text = path.read_text()
            new = rewritten(text, node)
        except (OSError, ValueError) as error:
            print(f'{path}: {getattr(error, "strerror", None) or error}', file=sys.stderr)
            status = 1
            continue
        if new == text:
            print(f'{path}: parameter table up to date')
        else:
            path.write_text(new)
            print(f'{path}: parameter table rewritten')
    return status


if __name__ == '__main__':
    sys.exit(main())
