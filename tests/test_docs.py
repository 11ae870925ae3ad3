"""The shelves around the code: every relative link in the README, docs/ and experiments/
resolves (to a file, and to a heading where it names one); docs/ stays a short shelf without
raw data; every experiment has its one-page README and a line in the index."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCED = re.compile(r"```.*?```", re.S)
CODE = re.compile(r"```.*?```|`[^`\n]*`", re.S)


def _pages() -> list[Path]:
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    return pages + sorted((ROOT / "experiments").rglob("*.md"))


def _anchors(page: Path) -> set[str]:
    """GitHub's heading anchors: lower case, punctuation dropped, spaces to hyphens."""
    anchors = set()
    for line in FENCED.sub("", page.read_text()).splitlines():
        if line.startswith("#"):
            text = line.lstrip("#").strip().lower()
            anchors.add(re.sub(r"[^\w\- ]", "", text).replace(" ", "-"))
    return anchors


def _links(page: Path):
    for target in LINK.findall(CODE.sub("", page.read_text())):
        if not re.match(r"[a-z]+:", target):  # http:, https:, mailto:
            yield target


def test_every_relative_link_resolves():
    broken, checked = [], 0
    for page in _pages():
        for target in _links(page):
            path, _, anchor = target.partition("#")
            resolved = (page.parent / path).resolve() if path else page
            checked += 1
            if not resolved.exists():
                broken.append(f"{page.relative_to(ROOT)}: {target}")
            elif anchor and resolved.suffix == ".md" and anchor not in _anchors(resolved):
                broken.append(f"{page.relative_to(ROOT)}: {target} (no such heading)")
    assert checked > 100
    assert not broken, "\n".join(broken)


def test_the_link_check_sees_a_broken_link_and_a_missing_heading(tmp_path):
    page = tmp_path / "page.md"
    page.write_text(
        "# A `title`\n\n[ok](#a-title) [gone](missing.md) [bad](#no-title)\n`[code](x.md)`\n"
    )
    targets = list(_links(page))
    assert targets == ["#a-title", "missing.md", "#no-title"]
    assert _anchors(page) == {"a-title"}


def test_docs_is_a_short_shelf_without_raw_data():
    files = [p for p in (ROOT / "docs").rglob("*") if p.is_file()]
    assert len(files) <= 15, sorted(str(p.relative_to(ROOT)) for p in files)
    assert not [p for p in files if p.suffix == ".json"]
    assert len((ROOT / "docs" / "results.md").read_text().splitlines()) <= 450
    assert len((ROOT / "README.md").read_text().splitlines()) <= 250


def test_scripts_hold_user_tools_and_experiments_their_probes():
    assert not list((ROOT / "scripts").glob("probe_*"))
    folders = sorted(p for p in (ROOT / "experiments").iterdir() if p.is_dir())
    index = (ROOT / "experiments" / "README.md").read_text()
    assert len(folders) >= 20
    for folder in folders:
        readme = folder / "README.md"
        assert readme.is_file(), f"{folder.name} has no README.md"
        text = readme.read_text()
        assert len(text.splitlines()) <= 80, f"{folder.name}/README.md is over a page"
        for part in ("Question", "Command", "Commit", "Result", "Conclusion"):
            assert part in text, f"{folder.name}/README.md says no {part}"
        assert f"({folder.name}/README.md)" in index, f"the index lists no {folder.name}"
