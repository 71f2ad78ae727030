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
