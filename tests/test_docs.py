"""The documentation holds to its own rules, read from the files themselves: the README stays a
ten-minute read, every relative link (and anchor) in README.md and docs/ resolves, the README's
commands table names every command the CLI registers and its "read more" list every docs page, and
no issue numbers or ISO dates (history belongs in CHANGELOG.md and git log) appear in README, docs
or the package's docstrings."""
from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from haptic_acu.cli import COMMANDS

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [README, *DOCS]
MAX_README_LINES = 250
HISTORY = re.compile(r"\bissues? #?\d+|\b\d{4}-\d{2}-\d{2}\b", re.I)
LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.M | re.S)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, markup and punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[`*_]|\[([^\]]*)\]\([^)]*\)", r"\1", heading.strip()).lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(text: str) -> set[str]:
    """Every heading's anchor in a Markdown text (a repeated heading gets -1, -2, ...)."""
    seen: dict[str, int] = {}
    out = set()
    for m in re.finditer(r"^#{1,6} +(.+?) *#*$", FENCE.sub("", text), re.M):
        s = slug(m.group(1))
        out.add(s if s not in seen else f"{s}-{seen[s]}")
        seen[s] = seen.get(s, 0) + 1
    return out


def broken_links(page: Path) -> list[str]:
    """The relative links of ``page`` whose file or anchor does not exist."""
    text = page.read_text()
    bad = []
    for target in LINK.findall(FENCE.sub("", text)):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto: ...
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            bad.append(f"{page.name}: {target} (no such file)")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest.read_text()):
            bad.append(f"{page.name}: {target} (no such heading)")
    return bad


def docstrings(path: Path):
    """(where, text) of every module, class and function docstring in ``path``."""
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            doc = ast.get_docstring(node, clean=False)
            if doc:
                yield f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', 1)}", doc


def readme_section(title: str) -> str:
    text = README.read_text()
    m = re.search(rf"^## {re.escape(title)}[^\n]*\n(.*?)(?=^## |\Z)", text, re.M | re.S)
    assert m, f"README has no '## {title}' section"
    return m.group(1)


def test_the_readme_is_a_ten_minute_read():
    n = len(README.read_text().splitlines())
    assert n <= MAX_README_LINES, f"README.md has {n} lines (at most {MAX_README_LINES}); move detail to docs/"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_relative_link_resolves(page):
    assert broken_links(page) == []


def test_the_link_checker_sees_a_broken_link_and_anchor(tmp_path):
    (tmp_path / "b.md").write_text("# Top\n\n## The `x` table (y)\n\n## Top\n")
    page = tmp_path / "a.md"
    page.write_text("[ok](b.md#the-x-table-y) [ok](b.md#top-1) [ok](https://example.org/none)\n"
                    "```\n[in code](nowhere.md)\n```\n"
                    "[gone](missing.md) [no heading](b.md#nothing) [here](#top)\n")
    assert broken_links(page) == ["a.md: missing.md (no such file)", "a.md: b.md#nothing (no such heading)",
                                  "a.md: #top (no such heading)"]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_no_issue_numbers_or_dates_in_the_docs(page):
    hits = [f"{page.name}:{i}: {line.strip()[:100]}" for i, line in enumerate(page.read_text().splitlines(), 1)
            if HISTORY.search(line)]
    assert hits == [], "history belongs in CHANGELOG.md and git log"


def test_no_issue_numbers_or_dates_in_docstrings():
    hits = [f"{where}: {HISTORY.search(doc).group(0)}"
            for pkg in ("haptic_acu", "devices", "bench") for path in sorted((ROOT / pkg).rglob("*.py"))
            for where, doc in docstrings(path) if HISTORY.search(doc)]
    assert hits == []


def test_the_history_pattern_sees_issue_numbers_and_dates():
    for text in ("as issue 12 asked", "Issues 3", "run 2026-11-30 15:33 UTC", "(issue #7)"):
        assert HISTORY.search(text), text
    for text in ("Zhang et al. 2021", "pp. 2085-2091", "eq. 10-14", "the issue's targets"):
        assert not HISTORY.search(text), text


def test_the_commands_table_names_every_command():
    table = readme_section("Commands")
    named = set(re.findall(r"^\| `haptic-acu ([a-z-]+)", table, re.M))
    assert set(COMMANDS) <= named, f"add a row to README's commands table for {sorted(set(COMMANDS) - named)}"
    assert named <= set(COMMANDS) | {"--version"}, f"commands the CLI does not have: {named - set(COMMANDS)}"


def test_the_readme_lists_every_docs_page():
    linked = {(README.parent / t.partition("#")[0]).resolve() for t in LINK.findall(readme_section("Read more"))}
    missing = [p.name for p in DOCS if p.resolve() not in linked]
    assert missing == [], f"link these from README's 'Read more': {missing}"
