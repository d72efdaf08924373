"""Every ```python block of README.md runs as written, in order, in one namespace."""
import os
import re
import traceback

import pytest
import torch

README = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "README.md")


def python_blocks(text: str) -> list[str]:
    """The bodies of the fenced ```python blocks of a Markdown text, in order."""
    return re.findall(r"^```python[ \t]*\n(.*?)^```[ \t]*$", text, flags=re.M | re.S)


def test_readme_has_python_blocks():
    blocks = python_blocks(open(README, encoding="utf-8").read())
    assert len(blocks) >= 5


def test_readme_python_blocks_run_in_order():
    blocks = python_blocks(open(README, encoding="utf-8").read())
    torch.manual_seed(0)
    namespace: dict = {"__name__": "__readme__"}
    for i, block in enumerate(blocks):
        try:
            exec(compile(block, f"README.md python block {i}", "exec"), namespace)
        except Exception:
            pytest.fail(f"README.md python block {i} failed:\n{block}\n{traceback.format_exc()}", pytrace=False)
