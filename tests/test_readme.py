"""The README's Python example runs as written (on the shipped wedge checkpoint)."""

import re
from pathlib import Path

import torch

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_example_runs(monkeypatch):
    text = README.read_text()
    block = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    monkeypatch.chdir(README.parent)
    namespace: dict = {}
    exec(compile(block, "README.md", "exec"), namespace)  # the repository's own README
    futures = namespace["futures"]
    assert futures.shape[:2] == (16, 30) and futures.shape[-1] == 3
    assert torch.isfinite(futures).all()
