"""The learning curve of a PPO run (its ``log.csv``, one row per update): :func:`read_curve`,
:func:`smooth`, :func:`updates_to_reach` and :func:`curve_metrics`."""

from __future__ import annotations

import csv
import math
from pathlib import Path

#: trailing moving-average window (updates) of the episode-length curve for its metrics
SMOOTH_UPDATES = 10
#: fraction of the last updates whose mean is a run's final average episode length
FINAL_FRACTION = 0.1
#: a run "reached its final length" when its smoothed curve has made this part of its drop
REACHED_FRACTION = 0.9
#: a drop (steps) smaller than this counts as no learning: updates_to_final is then None
MIN_DROP = 0.5


def read_curve(path: str | Path) -> list[float]:
    """A run's average episode length per PPO update from its ``log.csv``; NaN for updates in
    which no episode ended (an empty ``mean_episode_length``)."""
    with open(path, newline="") as fh:
        return [float(r["mean_episode_length"]) if r.get("mean_episode_length") else math.nan
                for r in csv.DictReader(fh)]


def smooth(curve: list[float], window: int = SMOOTH_UPDATES) -> list[float]:
    """Trailing moving average that skips NaN (updates in which no episode ended)."""
    out = []
    for i in range(len(curve)):  # a loop over updates (a few hundred)
        part = [v for v in curve[max(0, i - window + 1):i + 1] if not math.isnan(v)]
        out.append(sum(part) / len(part) if part else math.nan)
    return out


def updates_to_reach(curve: list[float], level: float, window: int = SMOOTH_UPDATES) -> int | None:
    """First update at which the smoothed curve is at or below ``level`` (full windows only); None if
    never."""
    smoothed = smooth(curve, window)
    for i in range(min(window, len(curve)) - 1, len(curve)):
        if smoothed[i] <= level:
            return i
    return None


def curve_metrics(curve: list[float]) -> dict[str, float | int | None]:
    r"""Final average episode length and the updates taken to reach it: with :math:`\bar L` the
    smoothed curve, :math:`L_0` the mean of the first :data:`SMOOTH_UPDATES` and :math:`L_f` of the
    last :data:`FINAL_FRACTION`, the first update with :math:`\bar L \le L_f + (1 - \rho)(L_0 -
    L_f)`, :math:`\rho` = :data:`REACHED_FRACTION` (None when :math:`L_0 - L_f <` :data:`MIN_DROP`)."""
    values = [v for v in curve if not math.isnan(v)]
    if not values:
        return {"final_length": None, "start_length": None, "updates_to_final": None}
    tail = max(1, round(FINAL_FRACTION * len(curve)))
    last = [v for v in curve[-tail:] if not math.isnan(v)] or values[-1:]
    final = sum(last) / len(last)
    head = [v for v in curve[:SMOOTH_UPDATES] if not math.isnan(v)] or values[:1]
    start = sum(head) / len(head)
    reached = None
    if start - final >= MIN_DROP:
        reached = updates_to_reach(curve, final + (1 - REACHED_FRACTION) * (start - final))
    return {"final_length": final, "start_length": start, "updates_to_final": reached}
