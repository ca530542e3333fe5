"""When an object at rest falls asleep: :class:`SleepConfig`, the one switch of :mod:`hrn_pyg.sleeping`.

Its own module so that :mod:`hrn_pyg.rollout` can default to it without importing the sleeping
step (which builds on the rollout's stages). The rule and the reasons for the defaults are in
:mod:`hrn_pyg.sleeping`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any


@dataclass(frozen=True)
class SleepConfig:
    """When an object at rest falls asleep (the rule: :mod:`hrn_pyg.sleeping`).

    Attributes:
        enabled: False runs every object at every step (the plain rollout, bit for bit).
        threshold: metres per step; an object whose leaves all moved less than this in a step
            (and had no external force) was still in that step. Default 2e-3 (6 cm/s at 30 steps
            per second): above the creep of the shipped models at rest, below real motion.
        patience: consecutive still steps after which an object falls asleep (>= 1).
        start_from_history: a rollout's objects start in the state the start's own three
            positions imply (:func:`hrn_pyg.sleeping.state_from_history`: still over both steps
            of history, and not pushed or touched by a moving object, is asleep, as in the RL
            environment); False starts every movable object awake.
    """

    enabled: bool = True
    threshold: float = 2e-3
    patience: int = 10
    start_from_history: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.enabled, bool):
            raise ValueError(f"SleepConfig.enabled must be a bool, got {self.enabled!r}")
        threshold = self.threshold
        if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not (
                math.isfinite(threshold) and threshold > 0):
            raise ValueError(f"SleepConfig.threshold must be a finite number > 0 (metres per step), got {threshold!r}")
        if not isinstance(self.start_from_history, bool):
            raise ValueError(f"SleepConfig.start_from_history must be a bool, got {self.start_from_history!r}")
        patience = self.patience
        if isinstance(patience, bool) or not isinstance(patience, int) or patience < 1:
            raise ValueError(f"SleepConfig.patience must be an integer >= 1 (steps), got {patience!r}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


#: what :func:`hrn_pyg.rollout.rollout`, :func:`hrn_pyg.sampling.sample` and the RL environment
#: use unless told otherwise (``sleep=None`` runs every object at every step)
DEFAULT_SLEEP = SleepConfig()
