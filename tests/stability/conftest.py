"""The numerical-stability suite: hard cases that must stay finite (see docs/performance.md).

The fast cases run in every ``make test``; the long ones (1000-step rollouts of every pybullet
scene, trained-checkpoint rollouts, 10x impacts on real scenes) run only with ``HRN_SLOW=1``
(``make test-slow``).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from toy_scene import one_thread  # noqa: E402,F401  (autouse fixture for every stability test)
