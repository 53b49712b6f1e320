"""Every relative link and anchor in README.md and docs/*.md resolves.

Anchors follow GitHub's rule for headings: lower case, every character that is not a letter,
digit, underscore, hyphen or space dropped, spaces turned into hyphens, and ``-1``, ``-2``, ...
appended to repeated anchors. Links inside code (fenced blocks and inline spans) are not links.
"""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FENCE = re.compile(r'^(```|~~~).*?^\1[^\n]*$', re.MULTILINE | re.DOTALL)
INLINE_CODE = re.compile(r'(`+)(?!`).+?(?<!`)\1(?!`)', re.DOTALL)
HEADING = re.compile(r'^#{1,6}[ \t]+(.+?)[ \t]*#*[ \t]*$', re.MULTILINE)
LINK = re.compile(r'!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+"[^"]*")?\s*\)')
EXTERNAL = re.compile(r'^[a-zA-Z][a-zA-Z0-9+.-]*:')


def doc_files() -> list[Path]:
    """Return the README, every page of docs/ and the committed report."""
    docs = ROOT / 'docs'
    return [ROOT / 'README.md', *sorted(docs.glob('*.md')), *sorted(docs.glob('report/*.md'))]


def without_fences(text: str) -> str:
    """Return `text` with fenced code blocks blanked (line count kept)."""
    return FENCE.sub(lambda m: '\n' * m.group(0).count('\n'), text)


def without_code(text: str) -> str:
    """Return `text` with fenced code blocks and inline code spans blanked."""
    return INLINE_CODE.sub(lambda m: re.sub(r'[^\n]', ' ', m.group(0)), without_fences(text))


def github_anchor(heading: str) -> str:
    """Return the anchor GitHub gives a heading's text (before de-duplication)."""
    text = re.sub(r'`', '', heading).strip().lower()
    text = re.sub(r'\[([^\]]*)\]\([^)]*\)', r'\1', text)  # a link in a heading keeps its text
    text = re.sub(r'[^\w\- ]', '', text)
    return text.replace(' ', '-')


def anchors(path: Path) -> set[str]:
    """Return every heading anchor of a Markdown file, with GitHub's ``-N`` suffixes."""
    seen: dict[str, int] = {}
    out = set()
    for match in HEADING.finditer(without_fences(path.read_text(encoding='utf-8'))):
        base = github_anchor(match.group(1))
        count = seen.get(base, 0)
        seen[base] = count + 1
        out.add(base if count == 0 else f'{base}-{count}')
    return out


def links(path: Path) -> list[str]:
    """Return the targets of every Markdown link of a file that is not external."""
    text = without_code(path.read_text(encoding='utf-8'))
    return [t for t in LINK.findall(text) if not EXTERNAL.match(t)]


def test_anchor_rule_matches_github() -> None:
    assert github_anchor('`ga-ros play BAG [--rate R]`: live replay into a running ROS graph') \
        == 'ga-ros-play-bag---rate-r-live-replay-into-a-running-ros-graph'
    assert github_anchor("The paper's experiments") == 'the-papers-experiments'
    assert github_anchor('Scaling towards 100,000 poses') == 'scaling-towards-100000-poses'
    assert github_anchor('Stereo visual odometry and `vo_node`') == \
        'stereo-visual-odometry-and-vo_node'


def test_checker_finds_a_broken_link(tmp_path: Path) -> None:
    page = tmp_path / 'page.md'
    page.write_text('# Title\n\n[ok](#title) [bad](#nope) `[code](#nope)`\n', encoding='utf-8')
    assert links(page) == ['#title', '#nope']
    assert anchors(page) == {'title'}


@pytest.mark.parametrize('path', doc_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_links_resolve(path: Path) -> None:
    broken = []
    for target in links(path):
        file_part, _, anchor = target.partition('#')
        dest = (path.parent / file_part).resolve() if file_part else path
        if not dest.exists():
            broken.append(f'{target}: no such file')
        elif anchor and dest.suffix == '.md' and anchor not in anchors(dest):
            broken.append(f'{target}: no heading with this anchor in {dest.name}')
    assert not broken, f'{path.relative_to(ROOT)}:\n  ' + '\n  '.join(broken)
