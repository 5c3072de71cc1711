"""The documentation's relative links and images resolve: every `[text](path)` and
`![alt](path)` in README.md and docs/**/*.md names a file that exists, and every `#anchor`
names a heading of the page it points to. The README's set-up commands are the ones CI runs."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").rglob("*.md")])
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
TORCH_CPU = "pip install -c constraints.txt --no-deps torch --index-url https://download.pytorch.org/whl/cpu"
SETUP = [f'{TORCH_CPU} && pip install -c constraints.txt ".[all]" && mvtex demo --out mvtex-demo',
         f'{TORCH_CPU} && pip install -c constraints.txt ".[test]" && pytest -q']


def prose(text: str) -> str:
    """The text without fenced code blocks and inline code (links there are not links)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[`*_]", "", heading.strip().lower())
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    headings = re.findall(r"^#{1,6}\s+(.+?)\s*$", re.sub(r"^```.*?^```", "", page.read_text(), flags=re.S | re.M),
                          flags=re.M)
    return {slug(h) for h in headings}


def links(page: Path) -> list[str]:
    return [t for t in LINK.findall(prose(page.read_text())) if not re.match(r"^[a-z][a-z0-9+.-]*:", t)]


def test_pages_are_found():
    names = {p.relative_to(ROOT).as_posix() for p in PAGES}
    assert {"README.md", "docs/cli.md", "docs/formats.md", "docs/results/accuracy.md"} <= names


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_and_images_resolve(page):
    broken = []
    for target in links(page):
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            broken.append(f"{target}: no such file")
        elif anchor and file.suffix == ".md" and anchor not in anchors(file):
            broken.append(f"{target}: no heading #{anchor} in {file.relative_to(ROOT)}")
    assert not broken, f"{page.relative_to(ROOT)}: " + "; ".join(broken)


def test_link_check_sees_links_images_and_anchors():
    """The checker itself: it finds links and images, skips code and URLs, and slugs as GitHub does."""
    text = "![a](x.png) [b](y.md#two-words) `[c](no.md)` [d](https://e.org)\n```\n[f](no.md)\n```\n"
    assert LINK.findall(prose(text)) == ["x.png", "y.md#two-words", "https://e.org"]
    assert slug("`mvtex calibrate`") == "mvtex-calibrate"
    assert slug("COLMAP's pixel convention") == "colmaps-pixel-convention"
    assert slug("Parallel runs: workers, Dask, threads") == "parallel-runs-workers-dask-threads"


def test_readme_starts_with_the_setup_commands_ci_runs():
    readme = (ROOT / "README.md").read_text()
    first_block = re.search(r"^```bash\n(.*?)^```", readme, flags=re.S | re.M).group(1)
    assert first_block.splitlines() == SETUP
    ci = (ROOT / ".ci" / "run").read_text()
    assert SETUP[1].replace("pip install ", "pip install -q ") in ci.splitlines()
