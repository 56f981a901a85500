"""The product documentation: page limits, relative links that resolve, and no work history in product pages.

``README.md`` and ``docs/*.md`` are read as text. Links are Markdown inline links outside code; a relative link
must name an existing file, and a ``#fragment`` must name a heading of the target page (GitHub's anchors).
``docs/experiments.md`` is the history page, so only it may speak of work sessions and issue numbers.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: The most lines each page may have: the README is the entry point, results.md holds current figures only.
LINE_LIMITS = {"README.md": 150, "docs/results.md": 250}
#: The page that keeps the history of the work, exempt from the history-word check.
HISTORY_PAGE = "docs/experiments.md"
#: Words about the work rather than the product. "session" alone is a product term (teleop and Zenoh sessions), so
#: the check looks for it as a stretch of work: "this session", "last session", "work session", …
HISTORY_WORDS = re.compile(
    r"\bissue\s*#|\bissue\s+\d|\b(?:this|that|last|previous|earlier|next|same|work|working)\s+session\b",
    re.IGNORECASE,
)

FENCE = re.compile(r"^(```|~~~).*?^\1[^\n]*$", re.MULTILINE | re.DOTALL)
INLINE_CODE = re.compile(r"`+[^`\n]*`+")
LINK = re.compile(r"!?\[[^\]\n]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
HEADING = re.compile(r"^#{1,6}\s+(.*?)\s*#*\s*$", re.MULTILINE)


def doc_pages(root: Path = ROOT) -> list[Path]:
    """README.md and every Markdown page under docs/."""
    return [root / "README.md", *sorted((root / "docs").glob("*.md"))]


def without_code(text: str) -> str:
    """``text`` with fenced code blocks and inline code spans removed (links and headings there are not links)."""
    return INLINE_CODE.sub("", FENCE.sub("", text))


def heading_anchor(heading: str) -> str:
    """GitHub's anchor of a heading: link text kept, markup and punctuation dropped, lower case, spaces to hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)
    text = re.sub(r"[^\w\- ]", "", text.lower())
    return text.replace(" ", "-")


def anchors(text: str) -> set[str]:
    """Every heading anchor of a page, repeated headings numbered as GitHub numbers them (``-1``, ``-2``, …)."""
    seen: dict[str, int] = {}
    found = set()
    for match in HEADING.finditer(FENCE.sub("", text)):
        anchor = heading_anchor(match.group(1))
        count = seen.get(anchor, 0)
        seen[anchor] = count + 1
        found.add(anchor if count == 0 else f"{anchor}-{count}")
    return found


def broken_links(page: Path) -> list[str]:
    """The relative links of ``page`` whose file does not exist or whose ``#fragment`` names no heading there."""
    problems = []
    for target in LINK.findall(without_code(page.read_text(encoding="utf-8"))):
        if re.match(r"[a-z][a-z0-9+.-]*:", target, re.IGNORECASE):
            continue  # http:, https:, mailto: — not a file of this repository
        path_part, _, fragment = target.partition("#")
        linked = (page.parent / path_part).resolve() if path_part else page
        if not linked.exists():
            problems.append(f"{target}: no file {linked}")
        elif (
            fragment
            and linked.suffix == ".md"
            and fragment not in anchors(linked.read_text(encoding="utf-8"))
        ):
            problems.append(f"{target}: no heading #{fragment} in {linked.name}")
    return problems


def history_words(page: Path) -> list[str]:
    """The lines of ``page`` that speak of the work (issues, work sessions) rather than of the product."""
    return [
        f"{number}: {line.strip()}"
        for number, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1)
        if HISTORY_WORDS.search(line)
    ]


@pytest.mark.parametrize("name", sorted(LINE_LIMITS))
def test_the_page_stays_within_its_line_limit(name: str) -> None:
    lines = len((ROOT / name).read_text(encoding="utf-8").splitlines())
    assert lines <= LINE_LIMITS[name], f"{name} has {lines} lines, the limit is {LINE_LIMITS[name]}"


@pytest.mark.parametrize("page", doc_pages(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_relative_link_resolves(page: Path) -> None:
    assert broken_links(page) == []


@pytest.mark.parametrize(
    "page",
    [p for p in doc_pages() if p.relative_to(ROOT).as_posix() != HISTORY_PAGE],
    ids=lambda p: p.relative_to(ROOT).as_posix(),
)
def test_product_pages_speak_of_the_product_not_of_the_work(page: Path) -> None:
    assert history_words(page) == []


def test_the_checks_find_a_broken_link_a_missing_heading_and_a_history_word(tmp_path: Path) -> None:
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "a.md").write_text(
        "# A page\n\n## Why is 𝒲 grown? (the `cpu` preset)\n", encoding="utf-8"
    )
    page = tmp_path / "README.md"
    page.write_text(
        "[ok](docs/a.md#why-is-𝒲-grown-the-cpu-preset) [ok](#top) [web](https://example.org/x.md)\n"
        "[gone](docs/b.md) [no heading](docs/a.md#nowhere) `[in code](docs/c.md)`\n"
        "# Top\n\n```bash\n# not a heading\n```\n\nAs said in this session, see issue #12.\n",
        encoding="utf-8",
    )
    assert broken_links(page) == [
        f"docs/b.md: no file {(tmp_path / 'docs' / 'b.md').resolve()}",
        "docs/a.md#nowhere: no heading #nowhere in a.md",
    ]
    assert anchors(page.read_text(encoding="utf-8")) == {"top"}
    assert history_words(page) == ["9: As said in this session, see issue #12."]
    assert history_words(tmp_path / "docs" / "a.md") == []
