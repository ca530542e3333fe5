"""Every script under examples/ runs in its fast mode, so none of them rots."""

import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = sorted((Path(__file__).resolve().parents[1] / "examples").glob("*.py"))


@pytest.mark.parametrize("script", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_example_runs_fast(script):
    proc = subprocess.run([sys.executable, str(script), "--fast"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip(), "an example should say what it did"


def test_there_are_examples():
    assert len(EXAMPLES) >= 2
