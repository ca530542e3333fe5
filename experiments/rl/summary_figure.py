"""The picture of a sweep's summary (``rl_<task>_summary.json``): four panels drawn from the
JSON alone, so a committed summary can be redrawn without its run folders.

1. **Learning, judged in pybullet.** The IQM over seeds of the closed-loop pybullet success on
   the fixed evaluation scenes against environment frames, one line per mode, its 95 %
   stratified-bootstrap band shaded (``iqm_curves.<mode>.closed_loop_success``; the replayed or
   in-model curve, ``success``, when a sweep has no closed-loop evaluation).
2. **Learning, in the model.** The IQM of the smoothed in-model training episode length against
   PPO updates (``iqm_curves.<mode>.episode_length``); lower is faster.
3. **Performance profile.** For every threshold :math:`\\tau`, the fraction of runs whose
   closed-loop success AUC exceeds :math:`\\tau` (``performance_profiles``), with its band.
4. **Probability of improvement** of each mode over the baseline (deterministic) on the
   closed-loop success AUC, a dot and its 95 % interval per mode; 0.5 (no difference) is marked.

:func:`plot_summary` draws them; ``python -m experiments.rl.summary ... --figure PATH`` writes the picture
beside the JSON.
"""

from __future__ import annotations

import os
from typing import Any

from hrn_pyg.rl.tasks import MODES
from hrn_pyg.viz import pyplot, save_figure

#: one colour per mode, the same in every panel (matplotlib's tab10 order)
MODE_COLORS = {mode: f"C{i}" for i, mode in enumerate(MODES)}
#: the per-run score of panels 3 and 4
SCORE = "closed_loop_success_auc"


def _success_curve(curves: dict[str, Any]) -> tuple[dict[str, Any] | None, str]:
    """The success curve a mode's panel 1 draws, and what judged it."""
    if "closed_loop_success" in curves:
        return curves["closed_loop_success"], "closed loop in pybullet"
    if "success" in curves:
        return curves["success"], curves["success"].get("judge", "model")
    return None, ""


def _changing_span(profile: dict[str, Any], pad: int = 1) -> tuple[float, float] | None:
    """The thresholds over which some mode's profile falls from 1 to 0, widened by ``pad``
    thresholds each side (the rest of the axis is flat); None when there is no profile."""
    if not profile:
        return None
    taus = next(iter(profile.values()))["tau"]
    moving = [i for i in range(len(taus)) if any(0 < p["fraction"][i] < 1 for p in profile.values())]
    if not moving:
        return None
    lo, hi = max(moving[0] - 1 - pad, 0), min(moving[-1] + 1 + pad, len(taus) - 1)
    return taus[lo], taus[hi]


def plot_summary(summary: dict[str, Any], path: str | os.PathLike, title: str | None = None) -> None:
    """Draw the four panels of a :func:`~experiments.rl.summary.task_summary` (as loaded from its
    JSON: nulls for infinities are fine) to ``path`` (atomically, format from the suffix)."""
    for key in ("task", "modes", "iqm_curves", "performance_profiles", "baseline"):
        if key not in summary:
            raise ValueError(f"not a sweep summary: no {key!r} key")
    plt = pyplot()
    fig, axes = plt.subplots(1, 4, figsize=(19, 4.2))
    modes = [m for m in MODES if m in summary["modes"]]
    seeds = {m: summary["modes"][m]["n"] for m in modes}

    ax, judge = axes[0], ""
    for mode in modes:
        curve, judge = _success_curve(summary["iqm_curves"].get(mode, {}))
        if curve is None:
            continue
        frames = [f / 1000 for f in curve["frames"]]
        ax.plot(frames, curve["iqm"], color=MODE_COLORS[mode], label=f"{mode} ({seeds[mode]})")
        ax.fill_between(frames, curve["low"], curve["high"], color=MODE_COLORS[mode], alpha=0.15, lw=0)
    ax.set(xlabel="environment frames (thousands)", ylabel="success (IQM over seeds)",
           title=f"success, {judge}" if judge else "success", ylim=(0, 1.02))
    ax.legend(fontsize=8, loc="lower right", title="mode (seeds)", title_fontsize=8)

    ax = axes[1]
    for mode in modes:
        curve = summary["iqm_curves"].get(mode, {}).get("episode_length")
        if curve is None:
            continue
        ax.plot(curve["update"], curve["iqm"], color=MODE_COLORS[mode])
        ax.fill_between(curve["update"], curve["low"], curve["high"], color=MODE_COLORS[mode], alpha=0.15, lw=0)
    ax.set(xlabel="PPO update", ylabel="episode length, steps (IQM)", title="in-model training episode length")

    ax = axes[2]
    profile = summary["performance_profiles"].get(SCORE, {}).get("modes", {})
    for mode in modes:
        if mode not in profile:
            continue
        p = profile[mode]
        ax.step(p["tau"], p["fraction"], where="post", color=MODE_COLORS[mode])
        ax.fill_between(p["tau"], p["low"], p["high"], step="post", color=MODE_COLORS[mode], alpha=0.12, lw=0)
    ax.set(xlabel=r"closed-loop success AUC $\tau$", ylabel=r"fraction of runs with score > $\tau$",
           title="performance profile", ylim=(0, 1.02))
    if (span := _changing_span(profile)) is not None:
        ax.set_xlim(*span)

    ax = axes[3]
    versus = summary.get("versus_" + summary["baseline"], {})
    shown = [m for m in modes if SCORE in versus.get(m, {})]
    for row, mode in enumerate(shown):
        poi = versus[mode][SCORE]
        ax.plot([poi["low"], poi["high"]], [row, row], color=MODE_COLORS[mode], lw=6, alpha=0.35,
                solid_capstyle="butt")
        ax.plot([poi["value"]], [row], "o", color=MODE_COLORS[mode])
    ax.axvline(0.5, color="0.4", ls="--", lw=1)
    ax.set_yticks(range(len(shown)), shown, fontsize=8)
    ax.set(xlim=(0, 1), ylim=(-0.6, max(len(shown), 1) - 0.4), xlabel=f"P(mode > {summary['baseline']})",
           title="probability of improvement, closed-loop AUC")
    ax.invert_yaxis()

    fig.suptitle(title if title is not None else
                 f"{summary['task']}: IQM over seeds with 95 % stratified-bootstrap intervals")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
