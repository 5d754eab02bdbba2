"""The tutorials in docs/tutorials run as written: every ```python block of a page, in order, in one namespace,
in a temporary working folder (issue 19 item 6). A failing `assert` in a page fails its test."""

import os
import re

import pytest

TUTORIALS = os.path.join(os.path.dirname(__file__), "..", "docs", "tutorials")
BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)


def python_blocks(path: str) -> list[str]:
    with open(path, encoding="utf-8") as fh:
        return BLOCK.findall(fh.read())


SLOW = "<!-- test: slow -->"  # a page with this line runs with the slow tests only (`make test-all`)


def _pages():
    pages = []
    for page in sorted(p for p in os.listdir(TUTORIALS) if p.endswith(".md")):
        with open(os.path.join(TUTORIALS, page), encoding="utf-8") as fh:
            slow = SLOW in fh.read()
        pages.append(pytest.param(page, marks=pytest.mark.slow) if slow else page)
    return pages


@pytest.mark.parametrize("page", _pages())
def test_tutorial_runs(page, tmp_path, monkeypatch):
    blocks = python_blocks(os.path.join(TUTORIALS, page))
    assert blocks, f"{page} has no python block"
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": f"tutorial_{page}"}
    for k, code in enumerate(blocks, start=1):
        exec(compile(code, f"{page} block {k}", "exec"), namespace)  # noqa: S102 (our own docs)
