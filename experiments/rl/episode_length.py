"""The episode-length figure and the summary tables of a sweep (``<mode>/seed<k>/log.csv`` under
one folder, as :mod:`experiments.rl.sweep` writes them).

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

from hrn_pyg.rl.curves import SMOOTH_UPDATES, curve_metrics, read_curve, smooth, updates_to_reach
from hrn_pyg.rl.tasks import MODES
from hrn_pyg.utils.files import atomic_path, atomic_write_text
from hrn_pyg.viz import save_figure


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
    episode length of training, the updates to reach it (:func:`~hrn_pyg.rl.curves.curve_metrics`; seeds whose
    curve dropped less than :data:`~hrn_pyg.rl.curves.MIN_DROP` are counted as "no drop" and left out of the
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
