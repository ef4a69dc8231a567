"""The node pages' parameter tables (docs/nodes/NODE.md) are generated from the nodes' settings dataclasses:
they must agree."""

from dataclasses import dataclass
from pathlib import Path

import pytest

from drvs.common.settings import POSITIVE, REQUIRED, Settings, at_least, one_of, param
from drvs.ros.param_docs import NODES, block, main, page, rewritten, table

NODE_PAGES = Path(__file__).resolve().parents[2] / 'docs' / 'nodes'


@pytest.mark.parametrize('node', NODES)
def test_the_node_pages_table_is_the_one_the_code_generates(node):
    assert block(page(NODE_PAGES, node).read_text(), node) == table(
        NODES[node]
    ), f"docs/nodes/{node}.md's parameter table differs from {NODES[node].__name__}: run make docs"


@dataclass(frozen=True)
class Example(Settings):
    world: str = param(REQUIRED, 'the world file')
    lease: float = param(
        10.0, 'a registration expires unless renewed within this time', unit='s', check=POSITIVE
    )
    rate: float = param(40.0, 'requests per second', unit='/s', check=POSITIVE)
    workers: int = param(8, 'threads', check=at_least(1))
    source: str = param(
        '', 'where frames come from', check=one_of('render', 'topic'), default_text='`render`'
    )
    names: str = param('', 'names, comma-separated | a list', separator=',')
    once: bool = param(False, 'exit when done')
    topic: str = param('/poses', 'the pose topic')
    speed: float | None = param(None, 'top speed', unit='m/s')


def test_a_table_has_a_row_per_field_with_type_range_default_and_meaning():
    assert table(Example).splitlines() == [
        '| parameter | type | default | meaning |',
        '|---|---|---|---|',
        '| `~world` | str | required | the world file |',
        '| `~lease` | float > 0 | 10 s | a registration expires unless renewed within this time |',
        '| `~rate` | float > 0 | 40/s | requests per second |',
        '| `~workers` | int ≥ 1 | 8 | threads |',
        '| `~source` | `render` or `topic` | `render` | where frames come from |',
        '| `~names` | str or list of str | empty | names, comma-separated \\| a list |',
        '| `~once` | bool | false | exit when done |',
        '| `~topic` | str | `/poses` | the pose topic |',
        '| `~speed` | float | none | top speed |',
    ]


def test_a_field_declared_without_a_meaning_is_refused():
    @dataclass(frozen=True)
    class Bare:
        rate: float = 1.0

    with pytest.raises(ValueError) as error:
        table(Bare)
    assert str(error.value) == 'Bare.rate: no meaning; declare it with drvs.common.settings.param'


def test_writing_fills_every_page_and_names_a_page_without_markers(tmp_path, capsys):
    for node in NODES:
        page(tmp_path, node).write_text(
            f'# {node}\n\n<!-- params:{node}:begin -->\nold\n<!-- params:{node}:end -->\nend\n'
        )
    assert main(['--write', str(tmp_path)]) == 0
    for node, cls in NODES.items():
        written = page(tmp_path, node).read_text()
        assert written.startswith(f'# {node}\n') and written.endswith('end\n')
        assert block(written, node) == table(cls)
        assert rewritten(written, node) == written
    capsys.readouterr()
    page(tmp_path, 'drvs_server').write_text('# drvs_server\n')
    page(tmp_path, 'world_sim').unlink()
    assert main(['--write', str(tmp_path)]) == 1
    assert capsys.readouterr().err == (
        f'{tmp_path}/drvs_server.md: drvs_server: no <!-- params:drvs_server:begin --> ... '
        '<!-- params:drvs_server:end --> in the file\n'
        f'{tmp_path}/world_sim.md: No such file or directory\n'
    )
