"""docs/api.md is what docs/make_api.py writes from the docstrings as they are."""

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_the_api_page_is_up_to_date():
    done = subprocess.run([sys.executable, str(REPO / "docs" / "make_api.py"), "--check"], cwd=REPO,
                          capture_output=True, text=True)
    assert done.returncode == 0, f"docs/api.md is out of date: run python docs/make_api.py\n{done.stdout}{done.stderr}"
