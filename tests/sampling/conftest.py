"""Make the shared toy scenes of ``tests/toy_scene.py`` importable from the sampling tests."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from toy_scene import one_thread  # noqa: E402,F401  (autouse fixture for every sampling test)
