"""Schedules that change a number over training: sequence length, dropout rate, learning rate."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class LinearSchedule:
    r"""A value moved linearly from ``start`` to ``end`` over ``steps`` updates, then held (dropout
    annealing):

    .. math::
        v(u) = v_0 + (v_1 - v_0) \min(u / U, 1)
    """

    start: float
    end: float
    steps: int

    def __post_init__(self) -> None:
        if self.steps < 0:
            raise ValueError(f"steps must be >= 0, got {self.steps}")

    def __call__(self, update: int) -> float:
        if self.steps == 0:
            return self.end
        frac = min(max(update, 0) / self.steps, 1.0)
        return self.start + (self.end - self.start) * frac


@dataclass(frozen=True)
class SequenceLengthSchedule:
    """Recurrent unroll length grown in equal stages from ``start`` to ``end`` over the first
    ``grow_until * total_steps`` steps (stage ``s`` unrolls ``start + s``), then ``end`` (the seed
    paper: 4 to 6 steps train well when reached gradually)."""

    start: int = 1
    end: int = 6
    total_steps: int = 1000
    grow_until: float = 0.6

    def __post_init__(self) -> None:
        if not 1 <= self.start <= self.end:
            raise ValueError(f"need 1 <= start <= end, got start={self.start}, end={self.end}")
        if not 0.0 < self.grow_until <= 1.0:
            raise ValueError(f"grow_until must be in (0, 1], got {self.grow_until}")

    def __call__(self, step: int) -> int:
        stages = self.end - self.start + 1
        horizon = max(1, int(self.grow_until * self.total_steps))
        stage = min(stages - 1, max(step, 0) * stages // horizon)
        return self.start + stage


def cosine_lr_factor(step: int, total_steps: int, warmup: int = 0, floor: float = 0.05) -> float:
    """Multiplier for the base learning rate: linear warm-up, then cosine decay to ``floor``."""
    if warmup > 0 and step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total_steps - warmup))
    return floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * progress))
