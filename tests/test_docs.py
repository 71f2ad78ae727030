"""The README is a front page and docs/ a reference: the README stays short, gives exactly the two set-up commands,
and every page it or docs/index.md names exists; every docs page is listed in the index."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")
INDEX = (ROOT / "docs" / "index.md").read_text(encoding="utf-8")


def test_readme_is_a_front_page_of_at_most_1500_words():
    words = len(README.split())
    assert words <= 1500, f"README.md has {words} words"


def test_readme_gives_exactly_two_setup_commands():
    blocks = re.findall(r"```bash\n(.*?)```", README, flags=re.S)
    assert len(blocks) == 2, blocks
    assert blocks[0].strip().endswith("i4cal demo")
    assert blocks[1].strip().endswith("pytest")


def test_every_docs_page_named_exists_and_is_indexed():
    named = set(re.findall(r"docs/([a-z_]+\.md)", README)) | set(re.findall(r"\]\(([a-z_]+\.md)\)", INDEX))
    missing = sorted(n for n in named if not (ROOT / "docs" / n).is_file())
    assert not missing, f"named but absent: {missing}"
    pages = {p.name for p in (ROOT / "docs").glob("*.md")} - {"index.md"}
    unindexed = sorted(pages - set(re.findall(r"\]\(([a-z_]+\.md)\)", INDEX)))
    assert not unindexed, f"docs pages not in docs/index.md: {unindexed}"


#: a date (YYYY-MM-DD), an issue number or a session's name: the marks of a lab notebook's narrative
NARRATIVE = re.compile(r"(?<![-\w])20\d\d-[01]\d-[0-3]\d(?![T\d])|\b[Ii]ssue #?\d+|\b\w+th session\b")


def test_no_dated_narrative_in_docs_outside_benchmarks():
    """How a thing was found belongs in docs/benchmarks.md and git history; the other pages say what is."""
    found = [
        f"{p.name}:{n}: {m.group(0)}"
        for p in sorted((ROOT / "docs").glob("*.md"))
        if p.name != "benchmarks.md"
        for n, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
        for m in [NARRATIVE.search(line)]
        if m
    ]
    assert not found, found
