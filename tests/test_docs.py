"""The docs are self-contained: every relative link and anchor in README.md and docs/*.md
resolves (the file exists; an `#anchor` matches a heading of the target by GitHub's slug
rules), and nothing points outside the repository (../shared, DESIGN.md)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").glob("*.md")])
_LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)|!\[[^\]]*\]\(([^)\s]+)\)")
_FENCE = re.compile(r"^(```|~~~)")


def _prose(text: str, keep_code: bool = False) -> list[str]:
    """The lines outside fenced code blocks, with inline code removed (kept: a heading's
    anchor has its code's text, as GitHub makes it)."""
    lines, fenced = [], False
    for line in text.splitlines():
        if _FENCE.match(line.lstrip()):
            fenced = not fenced
            continue
        lines.append("" if fenced else line if keep_code else re.sub(r"`[^`]*`", "", line))
    return lines


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, markup and punctuation other than `-` and
    `_` removed, spaces to `-`."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link keeps its text
    text = text.strip().lower().replace("`", "")
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for line in _prose(page.read_text(encoding="utf-8"), keep_code=True):
        match = re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not match:
            continue
        base = slug(match.group(1))
        count = seen.get(base, 0)
        seen[base] = count + 1
        out.add(base if count == 0 else f"{base}-{count}")  # GitHub numbers repeats
    return out


def links(page: Path) -> list[tuple[int, str]]:
    found = []
    for number, line in enumerate(_prose(page.read_text(encoding="utf-8")), 1):
        for match in _LINK.finditer(line):
            found.append((number, match.group(1) or match.group(2)))
    return found


def broken(page: Path, root: Path = ROOT) -> list[str]:
    """Every link of `page` that does not resolve inside `root`, as FILE:LINE: what."""
    problems = []
    for line, target in links(page):
        where = f"{page.relative_to(root)}:{line}: {target}"
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        if "DESIGN.md" in target or "shared/" in target:
            problems.append(f"{where}: points outside the repository")
            continue
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            problems.append(f"{where}: no such file")
        elif not file.resolve().is_relative_to(root):
            problems.append(f"{where}: leaves the repository")
        elif anchor and file.suffix == ".md" and anchor not in anchors(file):
            problems.append(f"{where}: no heading with anchor #{anchor} in {file.name}")
    return problems


def test_pages_are_found() -> None:
    assert ROOT / "docs" / "design.md" in PAGES and len(PAGES) > 10


@pytest.mark.parametrize("page", PAGES, ids=[p.name for p in PAGES])
def test_every_relative_link_and_anchor_resolves(page: Path) -> None:
    problems = broken(page)
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("page", PAGES, ids=[p.name for p in PAGES])
def test_no_reference_outside_the_repository(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    assert "DESIGN.md" not in text and "../shared" not in text, page.name


def test_the_checker_finds_what_is_broken(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    (tmp_path / "other.md").write_text("# Other page\n\n## 3. Scan (one round)\n")
    page.write_text("# Title\n\n[ok](other.md#3-scan-one-round) [self](#title)\n"
                    "[gone](missing.md) [bad](other.md#nope) [out](../shared/DESIGN.md)\n"
                    "```\n[in code](nowhere.md)\n```\n")
    problems = broken(page, tmp_path)
    assert [p.split(": ", 1)[1] for p in problems] == [
        "missing.md: no such file", "other.md#nope: no heading with anchor #nope in other.md",
        "../shared/DESIGN.md: points outside the repository"]


def test_slug_follows_github() -> None:
    assert slug("3. Scan semantics (one firing round)") == "3-scan-semantics-one-firing-round"
    assert slug("Write policy (`CommConfig.modbus_writes`, `softplc run --modbus-writes MODE`)"
                ) == "write-policy-commconfigmodbus_writes-softplc-run---modbus-writes-mode"
    assert slug("mbpoll examples (`-0` = 0-based addresses)") == \
        "mbpoll-examples--0--0-based-addresses"
