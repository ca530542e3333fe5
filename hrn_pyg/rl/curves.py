"""Learning curves of PPO runs: reading, smoothing, metrics, the episode-length figure and the
summary tables.

Every function here reads what :mod:`hrn_pyg.rl.ppo` writes (``<mode>/seed<k>/log.csv``, one
row per PPO update) or the per-run results it returns; nothing trains or steps an environment.

- :func:`read_curve`, :func:`smooth`, :func:`updates_to_reach` and :func:`curve_metrics`: a
  run's average episode length per update, its trailing moving average, the first update at
  which it reaches a level, and its final length and the updates taken to reach it.
- :func:`plot_episode_length`: the seed paper's Figs. 7 and 8 (median over seeds per mode,
  range shaded).
- :func:`write_summary`: ``summary.csv`` (one row per run) and ``summary.md`` (per mode over
  seeds, median [min, max]).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import torch

from hrn_pyg.rl.tasks import MODES
from hrn_pyg.utils.files import atomic_path, atomic_write_text
from hrn_pyg.viz import save_figure

#: trailing moving-average window (updates) of the episode-length curve for the summary metrics
#: and the figure
SMOOTH_UPDATES = 10
#: fraction of the last updates whose mean is a run's final average episode length
FINAL_FRACTION = 0.1
#: a run "reached its final length" when its smoothed curve has made this part of its drop
REACHED_FRACTION = 0.9
#: a drop (steps) smaller than this counts as no learning: updates_to_final is then None
MIN_DROP = 0.5


def plot_episode_length(out_root: str | Path, png_path: str | Path, title: str = "",
                        window: int = SMOOTH_UPDATES) -> list[str]:
    """Average episode length against PPO updates, one line per mode found under ``out_root``.

    Reads ``<mode>/seed*/log.csv`` and smooths each seed's curve with a trailing moving average
    over ``window`` updates (1: raw); the line is the median over seeds, the shaded band their
    range (min to max), over the updates every seed has reached. Returns the modes drawn.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_root = Path(out_root)
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=110)
    drawn = []
    for mode in MODES:
        curves = [read_curve(p) for p in sorted((out_root / mode).glob("seed*/log.csv"))]
        curves = [smooth(c, window) for c in curves if c]
        if not curves:
            continue
        n = min(len(c) for c in curves)
        values = torch.tensor([c[:n] for c in curves], dtype=torch.float64)  # (seeds, updates)
        x = torch.arange(n)
        med = values.nanmedian(0).values
        lo = torch.where(values.isnan(), math.inf, values).min(0).values
        hi = torch.where(values.isnan(), -math.inf, values).max(0).values
        line, = ax.plot(x, med, lw=1.3, label=f"{mode} (n={len(curves)})")
        ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.2, lw=0)
        drawn.append(mode)
    ax.set_xlabel("PPO update")
    ax.set_ylabel("average episode length" + (f"\n({window}-update moving average)" if window > 1 else ""))
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if drawn:
        ax.legend(frameon=False, fontsize=8)
    fig.tight_layout()
    save_figure(fig, png_path)
    return drawn


def read_curve(path: str | Path) -> list[float]:
    """A run's average episode length per PPO update from its ``log.csv``; NaN for updates in
    which no episode ended (an empty ``mean_episode_length``)."""
    with open(path, newline="") as fh:
        return [float(r["mean_episode_length"]) if r.get("mean_episode_length") else math.nan
                for r in csv.DictReader(fh)]


# ---------------------------------------------------------------------------- summaries
def smooth(curve: list[float], window: int = SMOOTH_UPDATES) -> list[float]:
    """Trailing moving average that skips NaN (updates in which no episode ended)."""
    out = []
    for i in range(len(curve)):  # a loop over updates (a few hundred)
        part = [v for v in curve[max(0, i - window + 1):i + 1] if not math.isnan(v)]
        out.append(sum(part) / len(part) if part else math.nan)
    return out


def updates_to_reach(curve: list[float], level: float, window: int = SMOOTH_UPDATES) -> int | None:
    """First update at which the smoothed curve is at or below ``level``; None if never.

    Only full windows count (updates ``window - 1`` on): an average of the first one or two
    noisy updates would otherwise "reach" a level by chance.
    """
    smoothed = smooth(curve, window)
    for i in range(min(window, len(curve)) - 1, len(curve)):
        if smoothed[i] <= level:
            return i
    return None


def curve_metrics(curve: list[float]) -> dict[str, float | int | None]:
    r"""Final average episode length and the updates taken to reach it.

    With :math:`\bar L` the curve smoothed over :data:`SMOOTH_UPDATES`, :math:`L_0` the mean of
    its first :data:`SMOOTH_UPDATES` values and :math:`L_f` the mean of the last
    :data:`FINAL_FRACTION` of updates,
    ``updates_to_final`` is the first update with
    :math:`\bar L \le L_f + (1 - \rho)(L_0 - L_f)`, :math:`\rho` = :data:`REACHED_FRACTION`
    (None when :math:`L_0 - L_f <` :data:`MIN_DROP` steps: the run did not learn).
    """
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


SUMMARY_FIELDS = ["task", "mode", "seed", "updates", "start_length", "final_length",
                  "updates_to_final", "success_rate", "mean_episode_length", "model_success_rate",
                  "model_mean_length", "pybullet_success_rate", "pybullet_mean_length", "agreement",
                  "ground_truth_episodes", "seconds"]


def _stat(values: list) -> str:
    """``median [min, max]`` of the non-missing values; ``-`` if none."""
    vals = sorted(float(v) for v in values if v is not None and not math.isnan(float(v)))
    if not vals:
        return "-"
    n = len(vals)
    med = vals[n // 2] if n % 2 else 0.5 * (vals[n // 2 - 1] + vals[n // 2])
    return f"{med:.2f} [{vals[0]:.2f}, {vals[-1]:.2f}]"


def write_summary(out_root: str | Path, results: list[dict]) -> None:
    """``summary.csv`` (one row per run) and ``summary.md`` (per mode over seeds) under ``out_root``.

    Curve metrics are recomputed from each run's ``log.csv`` where it exists. The markdown
    table gives, per mode, the median over seeds with the range: the final average
    episode length of training, the updates to reach it (:func:`curve_metrics`; seeds whose
    curve dropped less than :data:`MIN_DROP` are counted as "no drop" and left out of the
    median), the updates for the smoothed curve to reach the deterministic mode's median final
    length ("never" counted the same way), and the final
    policy's success rate and mean length in the learned model and replayed in pybullet.
    """
    out_root = Path(out_root)
    rows = sorted(results, key=lambda r: (MODES.index(r["mode"]) if r["mode"] in MODES else 99,
                                          r["seed"]))
    for i, r in enumerate(rows):  # curve metrics from the logs, as they are now
        log = out_root / r["mode"] / f"seed{r['seed']}" / "log.csv"
        if log.is_file():
            rows[i] = {**r, **curve_metrics(read_curve(log))}
    with atomic_path(out_root / "summary.csv", suffix=".csv") as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=SUMMARY_FIELDS, extrasaction="ignore")
            w.writeheader()
            w.writerows(rows)
    finals = [r.get("final_length") for r in rows if r["mode"] == "deterministic"]
    level = _stat(finals).split(" ")[0]
    level_f = float(level) if level != "-" else None
    lines = [f"# {rows[0]['task'] if rows else ''} RL summary (median [min, max] over seeds)", "",
             "| mode | seeds | final avg. length | updates to final | updates to det. final"
             f" ({level}) | success (model) | length (model) | success (pybullet) |"
             " length (pybullet) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for mode in MODES:
        runs = [r for r in rows if r["mode"] == mode]
        if not runs:
            continue
        to_level = []
        for r in runs:
            log = out_root / mode / f"seed{r['seed']}" / "log.csv"
            if level_f is not None and log.is_file():
                to_level.append(updates_to_reach(read_curve(log), level_f))
        never = sum(v is None for v in to_level)
        reach = _stat(to_level) + (f" ({never} never)" if never else "")
        no_drop = sum(r.get("updates_to_final") is None for r in runs)
        flat = f" ({no_drop} no drop)" if no_drop else ""
        lines.append(
            f"| {mode} | {len(runs)} | {_stat([r.get('final_length') for r in runs])} | "
            f"{_stat([r.get('updates_to_final') for r in runs])}{flat} | {reach} | "
            f"{_stat([r.get('model_success_rate', r.get('success_rate')) for r in runs])} | "
            f"{_stat([r.get('model_mean_length', r.get('mean_episode_length')) for r in runs])} | "
            f"{_stat([r.get('pybullet_success_rate') for r in runs])} | "
            f"{_stat([r.get('pybullet_mean_length') for r in runs])} |")
    atomic_write_text(out_root / "summary.md", "\n".join(lines) + "\n")

