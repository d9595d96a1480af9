"""The README and docs/: every relative link points to a file (and heading) that exists, the README stays
short enough to read, and it keeps the two set-up commands CI and a newcomer run."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
PAGES = [README, *sorted((REPO / "docs").glob("*.md"))]
README_MAX_LINES = 320

# [text](target) outside code: the target up to the first space or closing parenthesis.
_LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
_FENCE = re.compile(r"^(```|~~~)")


def _unfenced(text: str) -> str:
    """The text without fenced code blocks (headings and links there are none)."""
    lines, inside = [], False
    for line in text.splitlines():
        if _FENCE.match(line.strip()):
            inside = not inside
            continue
        lines.append("" if inside else line)
    return "\n".join(lines)


def _prose(text: str) -> str:
    """The text without code blocks and inline code spans (links there are not links)."""
    return re.sub(r"`[^`]*`", "", _unfenced(text))


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, markup and punctuation dropped, spaces to hyphens."""
    text = re.sub(r"`", "", heading.strip().lower())
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)  # a link keeps its text
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading anchor of a Markdown file, with GitHub's -1, -2 ... for repeated ones."""
    seen: dict[str, int] = {}
    out = set()
    for line in _unfenced(path.read_text()).splitlines():
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        base = slug(m.group(1))
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def broken_links(path: Path) -> list[str]:
    """The relative links of ``path`` whose file or anchor does not exist (external links are not checked)."""
    problems = []
    for target in _LINK.findall(_prose(path.read_text())):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto: ...
            continue
        file_part, _, anchor = target.partition("#")
        dest = (path.parent / file_part).resolve() if file_part else path
        if not dest.exists():
            problems.append(f"{target} (no such file)")
            continue
        if anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            problems.append(f"{target} (no heading with that anchor in {dest.name})")
    return problems


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_resolves(page: Path) -> None:
    assert broken_links(page) == []


def test_the_link_check_finds_a_missing_file_and_a_missing_anchor(tmp_path: Path) -> None:
    (tmp_path / "other.md").write_text("# A `code` heading: with punctuation\n\n## Twice\n\n## Twice\n")
    page = tmp_path / "page.md"
    page.write_text("[ok](other.md#a-code-heading-with-punctuation) [ok](other.md#twice-1) [ok](#here)\n"
                    "[file](missing.md) [anchor](other.md#nowhere) [web](https://example.org/x.md)\n"
                    "`[not a link](missing2.md)`\n```\n[in code](missing3.md)\n```\n# Here\n")
    assert broken_links(page) == ["missing.md (no such file)",
                                  "other.md#nowhere (no heading with that anchor in other.md)"]


def test_readme_is_short_and_keeps_the_two_setup_commands() -> None:
    text = README.read_text()
    assert len(text.splitlines()) <= README_MAX_LINES, "README.md is for a first read: move detail into docs/"
    for command in ("./scripts/demo.sh", "./scripts/test.sh"):
        assert command in text and (REPO / command).exists(), command
    assert "bash scripts/test.sh" in (REPO / ".ci" / "run").read_text()  # CI runs the README's test command


def test_readme_first_screen_says_the_units() -> None:
    """Within the first screen: VO units by default, metres only with an established metric source."""
    first_screen = "\n".join(README.read_text().splitlines()[:40])
    for words in ("VO units", "scale_source", "ground_plane", "wheel_odometry", "metres", "`units`"):
        assert words in first_screen, words
