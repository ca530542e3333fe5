"""Training steps that fill a wall budget, from a calibration run's ``metrics.csv``.

The step rate is read after the first five rows (start-up); the answer is 85 % of the budget at
that rate, rounded down to a multiple of ``round_to`` and at least ``minimum``.

Usage: ``python benchmarks/device/steps_for_budget.py calib/<job>/metrics.csv BUDGET_S MINIMUM ROUND_TO``.
"""

from __future__ import annotations

import csv
import sys

#: rows of a run's metrics.csv that are start-up, not the steady rate
START_ROWS = 5
#: the share of the budget the steps are planned for (the rest: evaluations, checkpoints, exit)
BUDGET_SHARE = 0.85


def steps_for_budget(seconds: list[float], budget_s: float, minimum: int, round_to: int) -> int:
    """Steps of ``budget_s`` seconds at the rate ``seconds`` (cumulative, a row per step) shows."""
    rate = (len(seconds) - START_ROWS - 1) / (seconds[-1] - seconds[START_ROWS]) if len(seconds) > 8 else 1.0
    return max(minimum, int(BUDGET_SHARE * budget_s * rate) // round_to * round_to)


if __name__ == "__main__":
    path, budget, minimum, round_to = sys.argv[1], float(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
    with open(path) as f:
        times = [float(row["seconds"]) for row in csv.DictReader(f)]
    print(steps_for_budget(times, budget, minimum, round_to))
