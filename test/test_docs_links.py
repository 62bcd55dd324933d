"""
The repository documents itself: no pointer to a design file outside it, no dead links.

* no file tracked by git names the external design file (the repository's design lives in
  docs/ARCHITECTURE.md and docs/CONTRACTS.md);
* README.md names nothing under ``../shared`` and no ``DESIGN.md``;
* every relative markdown link (and image) in README.md and docs/*.md resolves to an existing
  path inside the repository, and every anchor (``#part``, ``FILE.md#part``) to a heading of
  that page (GitHub's slug) or an ``<a id="part">`` in it.

The checks are functions of their inputs, and each is also run on a bad example, so that a
check that can no longer fail is noticed.
"""
import os
from pathlib import Path
import re
import subprocess

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: the external design file the repository must not depend on (spelled in two parts so that
#: this file does not name it)
EXTERNAL_DESIGN = 'shared/' + 'DESIGN.md'
#: skipped when walking the tree without git (virtual environments, build and output folders)
_NOT_SOURCES = {'.git', '.venv', 'build', 'install', 'log', 'out', '__pycache__'}

_FENCE = re.compile(r'^(```|~~~).*?^\1', re.M | re.S)
_CODE_SPAN = re.compile(r'`[^`\n]*`')
_LINK = re.compile(r'!?\[[^\]\n]*\]\(\s*<?([^)\s>]+)>?(?:\s+"[^"]*")?\s*\)')
#: a link with a scheme (``https:``, ``mailto:``): not a file of the repository
_URL = re.compile(r'^[a-zA-Z][a-zA-Z0-9+.-]*:')


def tracked_files(root: Path) -> list:
    """Return the files git tracks under ``root`` (every file but build output without git)."""
    try:
        out = subprocess.run(['git', 'ls-files', '-z'], cwd=root, capture_output=True,
                             check=True, timeout=60).stdout
        return [root / p for p in out.decode().split('\0') if p]
    except (OSError, subprocess.SubprocessError):
        files = []
        for d, dirs, names in os.walk(root):
            dirs[:] = [x for x in dirs if x not in _NOT_SOURCES]
            files += [Path(d) / n for n in names]
        return files


def files_naming(files, needle: str) -> list:
    """Return the files (of ``files``) whose bytes contain ``needle``."""
    b = needle.encode()
    return [f for f in files if f.is_file() and b in f.read_bytes()]


def markdown_links(text: str) -> list:
    """Return the link targets of markdown text, outside code blocks and code spans."""
    text = _CODE_SPAN.sub('', _FENCE.sub('', text))
    return _LINK.findall(text)


def dead_links(md: Path, root: Path) -> list:
    """
    Return the relative links of ``md`` that do not resolve to a path inside ``root``.

    URLs (``scheme:``) and in-page anchors (``#...``) are not checked; a fragment or query after
    a path is ignored.
    """
    bad = []
    for target in markdown_links(md.read_text(encoding='utf-8')):
        if _URL.match(target) or target.startswith('#'):
            continue
        path = re.split(r'[#?]', target, maxsplit=1)[0]
        resolved = (md.parent / path).resolve()
        if not path or not resolved.exists() or not resolved.is_relative_to(root.resolve()):
            bad.append(target)
    return bad


def _docs() -> list:
    return [ROOT / 'README.md'] + sorted((ROOT / 'docs').glob('*.md'))


# ------------------------------------------------------------------------------ the repository
def test_no_tracked_file_names_the_external_design():
    files = tracked_files(ROOT)
    assert len(files) > 50, 'the file list is implausibly short'
    bad = files_naming(files, EXTERNAL_DESIGN)
    assert not bad, f'{EXTERNAL_DESIGN} is named by ' + ', '.join(
        str(f.relative_to(ROOT)) for f in bad) + ': point to docs/ARCHITECTURE.md or CONTRACTS.md'


def test_readme_names_nothing_outside_the_repository():
    text = (ROOT / 'README.md').read_text(encoding='utf-8')
    assert '../shared' not in text
    assert 'DESIGN.md' not in text, 'README.md names a design file: link docs/ARCHITECTURE.md'


@pytest.mark.parametrize('md', _docs(), ids=lambda p: str(p.relative_to(ROOT)))
def test_markdown_links_resolve_inside_the_repository(md):
    assert md.exists()
    assert dead_links(md, ROOT) == []


def test_docs_exist_and_are_linked_from_the_readme():
    links = markdown_links((ROOT / 'README.md').read_text(encoding='utf-8'))
    for name in ('ARCHITECTURE.md', 'CONTRACTS.md', 'PASSIVITY.md', 'BENCHMARKS.md',
                 'RELIABILITY.md', 'GUIDE.md', 'REFERENCE.md', 'CHANGELOG.md'):
        assert f'docs/{name}' in links, f'README.md does not link docs/{name}'


def slug(heading: str) -> str:
    """Return GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = _CODE_SPAN.sub(lambda m: m.group(0)[1:-1], heading.strip()).lower()
    return re.sub(r'[^\w\- ]', '', text).replace(' ', '-')


def anchors(md: Path) -> set:
    """Return the anchors a markdown page has: its headings' slugs and its ``<a id>``s."""
    text = _FENCE.sub('', md.read_text(encoding='utf-8'))
    out = {slug(h) for h in re.findall(r'^#{1,6} +(.+?) *#*$', text, re.M)}
    return out | set(re.findall(r'<a id="([^"]+)">', text))


def dead_anchors(md: Path) -> list:
    """Return the links of ``md`` whose anchor its target page (md itself for ``#x``) lacks."""
    bad = []
    for target in markdown_links(md.read_text(encoding='utf-8')):
        if _URL.match(target) or '#' not in target:
            continue
        path, part = target.split('#', 1)
        page = md if not path else (md.parent / path).resolve()
        if page.suffix == '.md' and page.exists() and part not in anchors(page):
            bad.append(target)
    return bad


@pytest.mark.parametrize('md', _docs(), ids=lambda p: str(p.relative_to(ROOT)))
def test_anchors_resolve_to_a_heading(md):
    assert dead_anchors(md) == []


# ------------------------------------------------------------------------- the checks can fail
def test_checks_find_what_they_are_for(tmp_path):
    repo = tmp_path / 'repo'
    (repo / 'docs').mkdir(parents=True)
    (repo / 'docs' / 'here.md').write_text('x')
    (tmp_path / 'outside.md').write_text('x')      # exists, but outside the repository
    md = repo / 'README.md'
    md.write_text('[ok](docs/here.md) [ok](docs/here.md#part) [web](https://example.org) '
                  '[anchor](#top) ![img](docs/missing.png) [gone](docs/GONE.md) '
                  '[out](../outside.md) `[code](docs/nope.md)`\n'
                  f'```\n[fenced](docs/nope.md)\n```\nsee ../{EXTERNAL_DESIGN}\n')
    assert dead_links(md, repo) == ['docs/missing.png', 'docs/GONE.md', '../outside.md']
    assert files_naming([md, repo / 'docs' / 'here.md'], EXTERNAL_DESIGN) == [md]
    subprocess.run(['git', 'init', '-q'], cwd=repo, check=True)
    subprocess.run(['git', 'add', 'README.md'], cwd=repo, check=True)
    assert tracked_files(repo) == [md]

    (repo / 'docs' / 'here.md').write_text('# A `part`: here\n<a id="kept"></a>\n')
    md.write_text('## Top\n[a](#top) [b](docs/here.md#a-part-here) [c](docs/here.md#kept) '
                  '[d](#bottom) [e](docs/here.md#part)\n')
    assert dead_anchors(md) == ['#bottom', 'docs/here.md#part']
