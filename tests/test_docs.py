"""The documentation holds: README.md is short, every Python example in it and in docs/ runs as
written, and every image and relative link points at a file that exists."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def test_readme_is_short():
    lines = (ROOT / "README.md").read_text().count("\n")
    assert lines <= 250, f"README.md has {lines} lines; move detail to docs/"


def test_every_docs_topic_exists():
    names = {p.name for p in PAGES}
    for topic in ("models", "parallel", "controllers", "codegen", "runtime", "dynamixel"):
        assert f"{topic}.md" in names


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
@pytest.mark.slow
def test_python_examples_run(page):
    """Each page's blocks run in order in one namespace, as a reader would type them."""
    blocks = re.findall(r"```python\n(.*?)```", page.read_text(), flags=re.S)
    namespace: dict = {}
    for block in blocks:
        exec(compile(block, str(page), "exec"), namespace)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_links_and_images_exist(page):
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)  # code is not a link
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue
        path = (page.parent / target.split("#", 1)[0]).resolve()
        assert path.exists(), f"{page.name}: {target} does not exist"


def test_examples_exist_where_they_should():
    """The README's quick start and the model and kernel pages carry runnable examples."""
    for name in ("README.md", "models.md", "parallel.md", "codegen.md"):
        page = next(p for p in PAGES if p.name == name)
        assert "```python\n" in page.read_text(), name
