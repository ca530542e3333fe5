"""Every relative link in the README and ``docs/*.md`` points at a file that exists, and every
``#anchor`` into a Markdown page names one of its headings (GitHub's heading slugs)."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"```.*?```", re.S)
HEADING = re.compile(r"^#{1,6} (.+)$", re.M)
LINK = re.compile(r"\]\(([^)\s]+)\)")


def heading_slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def page_anchors(page: Path) -> set[str]:
    """The anchors of a page's headings; a repeated heading gets ``-1``, ``-2``, ... appended."""
    anchors, seen = set(), {}
    for heading in HEADING.findall(FENCE.sub("", page.read_text())):
        slug = heading_slug(heading)
        count = seen.get(slug, 0)
        seen[slug] = count + 1
        anchors.add(slug if count == 0 else f"{slug}-{count}")
    return anchors


def relative_links(page: Path) -> list[str]:
    """The links of a page outside code blocks that are not web addresses."""
    links = LINK.findall(FENCE.sub("", page.read_text()))
    return [link for link in links if not re.match(r"[a-z]+:", link)]


def test_heading_slug_follows_github():
    assert heading_slug("The verdict: tower_aside, 10 seeds per mode") == "the-verdict-tower_aside-10-seeds-per-mode"
    assert heading_slug("Fig. 9: learned policies") == "fig-9-learned-policies"
    assert heading_slug("Spread sized to the goal: cube_push_hold") == "spread-sized-to-the-goal-cube_push_hold"


def test_a_missing_file_and_a_wrong_anchor_are_caught(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("# Title\n\n## A section\n\n```\n# not a heading\n[x](gone.md)\n```\n"
                    "[ok](#a-section) [self](page.md#title) [bad](#not-a-heading) [gone](gone.md) "
                    "[web](https://example.org/x)\n")
    assert page_anchors(page) == {"title", "a-section"}
    assert broken_links(page) == ["#not-a-heading (no such heading)", "gone.md (no such file)"]


def broken_links(page: Path) -> list[str]:
    """The relative links of ``page`` whose file is missing or whose anchor names no heading."""
    broken = []
    for link in relative_links(page):
        path, _, anchor = link.partition("#")
        target = (page.parent / path).resolve() if path else page
        if not target.exists():
            broken.append(f"{link} (no such file)")
        elif anchor and target.suffix == ".md" and anchor not in page_anchors(target):
            broken.append(f"{link} (no such heading)")
    return broken


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_relative_links_resolve(page):
    broken = broken_links(page)
    assert not broken, f"{page.name}: " + ", ".join(broken)
