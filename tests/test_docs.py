"""The README and docs/ stay readable and true: the README is a ten-minute read (at most
300 lines), no page speaks of the project's own history, and every relative link (file
and #anchor) resolves."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
#: words from the project's history a reader cannot see
HISTORY = re.compile(r"issue \d|previous session|the review\b|worktree|helper \d|(?-i:(?<![/\w])DESIGN\.md)", re.I)


def slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    s = re.sub(r"[^\w\- ]", "", heading.strip().lstrip("#").strip().lower())
    return s.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    out, fenced = set(), False
    for line in page.read_text().splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and re.match(r"#{1,6} ", line):
            out.add(slug(line))
    return out


def links(page: Path) -> list[tuple[int, str]]:
    """(line, target) of every Markdown link and image outside code blocks."""
    out, fenced = [], False
    for n, line in enumerate(page.read_text().splitlines(), 1):
        if line.startswith("```"):
            fenced = not fenced
            continue
        if not fenced:
            code_free = re.sub(r"`[^`]*`", "", line)
            out += [(n, m.group(1)) for m in re.finditer(r"\]\(([^)\s]+)\)", code_free)]
    return out


def test_the_readme_is_a_ten_minute_read():
    n = len((ROOT / "README.md").read_text().splitlines())
    assert n <= 300, f"README.md has {n} lines: move reference and results to docs/"


def test_no_page_speaks_of_the_projects_history():
    found = [f"{p.relative_to(ROOT)}:{n}: {line.strip()[:100]}" for p in PAGES
             for n, line in enumerate(p.read_text().splitlines(), 1) if HISTORY.search(line)]
    assert not found, "\n".join(found)


def test_every_relative_link_resolves():
    broken = []
    for page in PAGES:
        for n, target in links(page):
            if re.match(r"[a-z]+:", target):
                continue
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            where = f"{page.relative_to(ROOT)}:{n}: {target}"
            if not dest.exists():
                broken.append(f"{where} (no such file)")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                broken.append(f"{where} (no such heading in {dest.name})")
    assert not broken, "\n".join(broken)
