"""The documentation holds together: README.md is short, and every link of README.md and the pages
under docs/ (and worlds/README.md) points at a file of this repository, and at a heading of it that
exists."""

import doctest
import re
from pathlib import Path

import pytest

import drvs.testing.doc_examples
from drvs.testing.harness import REPO

README_MAX_LINES = 200
PAGES = sorted([REPO / 'README.md', REPO / 'worlds' / 'README.md', *(REPO / 'docs').rglob('*.md')])
LINK = re.compile(r'!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(([^)\s]+)(?:\s+"[^"]*")?\)')
OUTSIDE = re.compile(r'^[a-z][a-z0-9+.-]*:|^//|^www\.', re.I)


def without_code_blocks(text: str) -> str:
    return re.sub(r'^( *)(```|~~~).*?^\1\2', '', text, flags=re.S | re.M)


def prose(text: str) -> str:
    """``text`` without fenced code blocks and inline code, where a ``[x](y)`` is not a link."""
    return re.sub(r'`[^`\n]*`', '', without_code_blocks(text))


def links(page: Path) -> list[str]:
    return LINK.findall(prose(page.read_text()))


def anchor(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens.

    >>> anchor('How it asks: `~requests`')
    'how-it-asks-requests'
    """
    text = heading.strip().lower().replace('`', '')
    text = re.sub(r'[^\w\- ]', '', text)
    return text.replace(' ', '-')


def anchors(page: Path) -> set[str]:
    """Every heading's anchor on ``page`` (a repeated heading gets -1, -2, ... as on GitHub)."""
    seen: dict[str, int] = {}
    result = set()
    for heading in re.findall(r'^#{1,6} +(.+?) *#*$', without_code_blocks(page.read_text()), re.M):
        base = anchor(heading)
        count = seen.get(base, 0)
        seen[base] = count + 1
        result.add(base if count == 0 else f'{base}-{count}')
    return result


def test_there_are_pages_and_links_to_check():
    names = {page.relative_to(REPO).as_posix() for page in PAGES}
    assert {'README.md', 'docs/interface.md', 'docs/architecture.md', 'docs/nodes/drvs_server.md'} <= names
    assert len(links(REPO / 'README.md')) >= 20


def test_the_readme_is_at_most_200_lines():
    lines = (REPO / 'README.md').read_text().count('\n')
    assert lines <= README_MAX_LINES, f'README.md has {lines} lines; the rest belongs in docs/'


@pytest.mark.parametrize('page', PAGES, ids=lambda page: page.relative_to(REPO).as_posix())
def test_every_link_points_into_the_repository_at_something_that_exists(page):
    problems = []
    for target in links(page):
        if OUTSIDE.match(target):
            problems.append(f'{target}: points outside the repository')
            continue
        path, _, fragment = target.partition('#')
        resolved = (page.parent / path).resolve() if path else page
        if not resolved.is_relative_to(REPO):
            problems.append(f'{target}: outside the repository')
        elif not resolved.exists():
            problems.append(f'{target}: no such file')
        elif fragment and resolved.suffix == '.md' and fragment not in anchors(resolved):
            problems.append(f'{target}: no heading #{fragment} in {resolved.relative_to(REPO)}')
    assert not problems, f'{page.relative_to(REPO)}:\n' + '\n'.join(problems)


def test_the_link_finder_sees_links_and_images_but_not_code():
    text = '[a](x.md) ![p](y.png) `[no](z.md)`\n```\n[no](w.md)\n```\n[b `c`](v.md#h)\n'
    assert LINK.findall(prose(text)) == ['x.md', 'y.png', 'v.md#h']
    assert OUTSIDE.match('https://example.org') and not OUTSIDE.match('../worlds/README.md')


def test_doctests():
    assert doctest.testmod(drvs.testing.doc_examples).failed == 0
    assert doctest.run_docstring_examples(anchor, {'anchor': anchor}) is None
