"""The README's and docs/'s links to other Markdown files lead somewhere: the file exists, and a #fragment names one
of its headings (as GitHub makes heading anchors)."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"\]\(([^)\s]*?\.md)?(?:#([^)\s]+))?\)")
FENCED = re.compile(r"^```.*?^```", re.MULTILINE | re.DOTALL)  # code blocks: no headings or links in them


def prose(page: Path) -> str:
    """A page's text without its fenced code blocks."""
    return FENCED.sub("", page.read_text(encoding="utf-8"))


def anchor(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation but hyphens dropped, spaces made hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    return {anchor(line.lstrip("#")) for line in prose(page).splitlines() if line.startswith("#")}


def test_the_anchor_of_a_heading_is_githubs():
    assert anchor(" Coarse to fine at 256 px (2026-11-29; an option, not the default)") == (
        "coarse-to-fine-at-256-px-2026-11-29-an-option-not-the-default"
    )


def test_a_comment_in_a_code_block_is_no_heading(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("# Title\n\n```bash\n# make the scene\ntacsplat sim-capture --out S\n```\n")
    assert anchors(page) == {"title"}


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_markdown_link_leads_to_a_file_and_heading(page):
    broken = []
    for match in LINK.finditer(prose(page)):
        target, fragment = match.group(1), match.group(2)
        if (target is None and fragment is None) or "://" in (target or ""):
            continue  # a link to something other than a Markdown page of this repository
        file = page if target is None else (page.parent / target).resolve()
        if not file.is_file():
            broken.append(f"{match.group(0)}: no file {file}")
        elif fragment is not None and fragment not in anchors(file):
            broken.append(f"{match.group(0)}: no heading #{fragment} in {file.name}")
    assert not broken, "\n".join(broken)


def test_the_readme_is_a_guide_of_at_most_250_lines():
    """The README stays a user's guide (what it is, the two commands, a tour, a rig, the formats): details go to
    docs/ and are linked."""
    assert len((ROOT / "README.md").read_text(encoding="utf-8").splitlines()) <= 250
