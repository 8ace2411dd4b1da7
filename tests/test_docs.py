"""The documentation stays usable: a short README, links that resolve, code that cites only the repository,
and no measured percentages in product comments (figures live in docs/, where they can be kept current)."""
from __future__ import annotations

import io
import re
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README_MAX_LINES = 250
# Written by another tool from the runs' summaries; a link to it is fine before it is generated.
GENERATED_ELSEWHERE = {ROOT / "docs" / "results.md"}
PRODUCT_DIRS = ("services", "shared", "cli", "deploy", "client")
SKIP_DIRS = {".git", ".venv", "venv", "results", "data", "build", "node_modules", "__pycache__", ".mypy_cache",
             ".pytest_cache", ".ruff_cache"}
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
ANCHOR = re.compile(r"<a\s+id=\"([^\"]+)\"")
PERCENT = re.compile(r"\d+(\.\d+)?\s?%")
# The outside design file's name, split so that a grep for it over the tree finds real citations only.
CARD_FILE = re.compile("DE" + "SIGN" + r"(\.md)?\b")
SECTION_REF = re.compile(r"docs/architecture\.md §([A-Z][A-Za-z-]*)")


def _markdown_files() -> list[Path]:
    files = [ROOT / "README.md", ROOT / "CHANGELOG.md", ROOT / "CONTRIBUTING.md"]
    return [f for f in files if f.exists()] + sorted((ROOT / "docs").glob("*.md"))


def _python_files(*tops: str) -> list[Path]:
    roots = [ROOT / t for t in tops] if tops else [ROOT]
    found: list[Path] = []
    for root in roots:
        for path in root.rglob("*.py"):
            if not SKIP_DIRS.intersection(path.relative_to(ROOT).parts):
                found.append(path)
    return sorted(found)


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(markdown: Path) -> set[str]:
    text = markdown.read_text(encoding="utf-8")
    headings = {_slug(m.group(1)) for m in re.finditer(r"^#+\s+(.+)$", text, re.MULTILINE)}
    return headings | set(ANCHOR.findall(text))


def test_readme_is_short() -> None:
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines; move details to docs/"


def test_readme_first_screen_has_quick_start_architecture_and_headline() -> None:
    first_screen = "\n".join((ROOT / "README.md").read_text(encoding="utf-8").splitlines()[:80])
    for needed in ("make demo", "make test", "## Architecture", "## Headline"):
        assert needed in first_screen, f"{needed!r} is not in the README's first 80 lines"


@pytest.mark.parametrize("markdown", _markdown_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(markdown: Path) -> None:
    broken = []
    for target in LINK.findall(markdown.read_text(encoding="utf-8")):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # https:, mailto:, ...
            continue
        path_part, _, anchor = target.partition("#")
        linked = (markdown.parent / path_part).resolve() if path_part else markdown
        if linked in GENERATED_ELSEWHERE:
            continue
        if not linked.exists():
            broken.append(f"{target} (no such file)")
        elif anchor and linked.suffix == ".md" and anchor not in _anchors(linked):
            broken.append(f"{target} (no such section)")
    assert not broken, f"{markdown.relative_to(ROOT)}: broken links: {broken}"


def test_code_cites_no_design_file_outside_the_repository() -> None:
    citing = [str(p.relative_to(ROOT)) for p in _python_files() if CARD_FILE.search(p.read_text(encoding="utf-8"))
              and p != Path(__file__).resolve()]
    assert not citing, f"these cite a design file that is not in the repository (use docs/architecture.md): {citing}"


def test_architecture_sections_cited_by_code_exist() -> None:
    anchors = _anchors(ROOT / "docs" / "architecture.md")
    missing = set()
    for path in _python_files() + _markdown_files():
        for section in SECTION_REF.findall(path.read_text(encoding="utf-8")):
            if _slug(section) not in anchors:
                missing.add(f"{path.relative_to(ROOT)}: §{section}")
    assert not missing, f"docs/architecture.md has no such section: {sorted(missing)}"


def _comments(path: Path) -> list[tuple[int, str]]:
    source = path.read_text(encoding="utf-8")
    return [(tok.start[0], tok.string) for tok in tokenize.generate_tokens(io.StringIO(source).readline)
            if tok.type == tokenize.COMMENT]


def test_product_comments_quote_no_percentages() -> None:
    """A comment says what a setting does and why; measured rates go to docs/ (they change with every run)."""
    quoting = [f"{path.relative_to(ROOT)}:{line}: {text.strip()}"
               for path in _python_files(*PRODUCT_DIRS) for line, text in _comments(path) if PERCENT.search(text)]
    assert not quoting, "percentages in product comments (point to docs/ instead):\n" + "\n".join(quoting)


def test_the_percentage_check_sees_comments_only(tmp_path: Path) -> None:
    sample = tmp_path / "sample.py"
    sample.write_text('RATE = "95%"  # a plain comment\nx = 1  # success 82.5% on val\n', encoding="utf-8")
    assert [line for line, text in _comments(sample) if PERCENT.search(text)] == [2]
