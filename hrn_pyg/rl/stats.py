"""Statistics that decide between RL modes: updates to reach a fixed episode length, final
length and pybullet success per mode, with bootstrap 95 % intervals over seeds.

A handful of seeds per mode is what a sweep affords, so every number here is a median over
seeds with a percentile-bootstrap interval (resampling seeds with replacement), and the
comparison of a mode with the deterministic baseline is the bootstrap interval of the
difference of their medians (the two groups resampled independently).

**Censoring.** A run that never reaches a level within its updates took *more* than its update
count; it enters as :math:`+\\infty`, which keeps the order right for a median. An interval
whose bound is infinite is reported as such ("> n updates"): the sweep cannot bound it.

**Levels.** The fixed lengths are fractions of the task's step limit chosen before any sweep
was run (:data:`REFERENCE_FRACTIONS`: three quarters and half of it), not read off the curves,
so that they cannot be picked to favour a mode.

Nothing here trains or steps an environment: it reads ``<mode>/seed<k>/log.csv`` through
:mod:`hrn_pyg.rl.curves` and the per-run results ``hrn-pyg rl`` writes to ``summary.json``.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from hrn_pyg.rl.curves import curve_metrics, read_curve, updates_to_reach
from hrn_pyg.rl.tasks import MODES
from hrn_pyg.utils.files import atomic_write_json, atomic_write_text

#: fixed episode lengths, as fractions of the task's step limit, whose first crossing by the
#: smoothed curve measures learning speed
REFERENCE_FRACTIONS = (0.75, 0.5)
#: bootstrap resamples and interval level
RESAMPLES = 10_000
LEVEL = 0.95


def median(values: torch.Tensor, dim: int = -1) -> torch.Tensor:
    """Median along ``dim`` with the even-count convention (mean of the two middle values);
    :math:`+\\infty` entries sort last, so a median of mostly censored values is infinite."""
    ordered = values.sort(dim=dim).values
    n = values.shape[dim]
    lo = ordered.narrow(dim, (n - 1) // 2, 1)
    hi = ordered.narrow(dim, n // 2, 1)
    both_inf = torch.isinf(lo) & torch.isinf(hi) & (lo == hi)
    mid = torch.where(both_inf, lo, 0.5 * (lo + hi))
    return mid.squeeze(dim)


def _resampled_medians(values: torch.Tensor, resamples: int, generator: torch.Generator) -> torch.Tensor:
    """Medians of ``resamples`` bootstrap resamples of ``values`` (``[n]``), ``[resamples]``."""
    n = values.numel()
    index = torch.randint(n, (resamples, n), generator=generator)
    return median(values[index], dim=1)


def _interval(medians: torch.Tensor, level: float) -> tuple[float, float]:
    """Percentile interval of bootstrap medians (NaN-free, may hold infinities)."""
    ordered = medians.sort().values
    r = ordered.numel()
    lo_i = int(math.floor((1 - level) / 2 * (r - 1)))
    hi_i = int(math.ceil((1 + level) / 2 * (r - 1)))
    return float(ordered[lo_i]), float(ordered[hi_i])


def bootstrap_median(values: list[float], resamples: int = RESAMPLES, level: float = LEVEL,
                     seed: int = 0) -> dict[str, float | int]:
    """Median of ``values`` over seeds and its percentile-bootstrap interval.

    Args:
        values: one value per seed; ``math.inf`` for a censored run (never reached); NaN is
            not allowed (a missing value is not a censored one).
        resamples, level, seed: bootstrap size, interval level and generator seed (the result
            is deterministic for a given seed).

    Returns:
        ``{"median", "low", "high", "n"}``.
    """
    if not values:
        raise ValueError("bootstrap_median needs at least one value")
    x = torch.tensor(values, dtype=torch.float64)
    if torch.isnan(x).any():
        raise ValueError("bootstrap_median got NaN; pass math.inf for a run that never reached the level")
    if not 0 < level < 1 or resamples < 1:
        raise ValueError(f"need 0 < level < 1 and resamples >= 1, got {level}, {resamples}")
    g = torch.Generator().manual_seed(seed)
    lo, hi = _interval(_resampled_medians(x, resamples, g), level)
    return {"median": float(median(x)), "low": lo, "high": hi, "n": len(values)}


def bootstrap_median_difference(a: list[float], b: list[float], resamples: int = RESAMPLES,
                                level: float = LEVEL, seed: int = 0) -> dict[str, float]:
    """median(a) - median(b) and its bootstrap interval, each group resampled on its own.

    Infinite medians make the difference infinite (or NaN for inf - inf, which is dropped from
    the interval: both censored says nothing about the difference). Returns
    ``{"difference", "low", "high"}``; an interval that excludes 0 is the evidence of a
    difference at that level.
    """
    if not a or not b:
        raise ValueError("bootstrap_median_difference needs values in both groups")
    xa = torch.tensor(a, dtype=torch.float64)
    xb = torch.tensor(b, dtype=torch.float64)
    if torch.isnan(xa).any() or torch.isnan(xb).any():
        raise ValueError("bootstrap_median_difference got NaN; pass math.inf for a censored run")
    g = torch.Generator().manual_seed(seed)
    diff = _resampled_medians(xa, resamples, g) - _resampled_medians(xb, resamples, g)
    diff = diff[~torch.isnan(diff)]
    point = float(median(xa) - median(xb))
    if diff.numel() == 0:
        return {"difference": point, "low": math.nan, "high": math.nan}
    lo, hi = _interval(diff, level)
    return {"difference": point, "low": lo, "high": hi}


def reference_levels(max_steps: int) -> list[float]:
    """The fixed episode lengths of a task with step limit ``max_steps``."""
    return [round(f * max_steps, 2) for f in REFERENCE_FRACTIONS]


def run_table(out_root: str | Path, results: list[dict], max_steps: int) -> list[dict]:
    """One row per run: updates to each reference level (inf if never), final length,
    pybullet and learned-model success, read from the logs under ``out_root``."""
    out_root = Path(out_root)
    rows = []
    for r in results:
        log = out_root / r["mode"] / f"seed{r['seed']}" / "log.csv"
        if not log.is_file():
            continue
        curve = read_curve(log)
        final = curve_metrics(curve)["final_length"]
        row = {"mode": r["mode"], "seed": r["seed"], "updates": len(curve),
               "final_length": math.nan if final is None else final,
               "pybullet_success_rate": r.get("pybullet_success_rate"),
               "model_success_rate": r.get("model_success_rate", r.get("success_rate"))}
        for level in reference_levels(max_steps):
            reached = updates_to_reach(curve, level)
            row[f"updates_to_{level:g}"] = math.inf if reached is None else reached
        rows.append(row)
    return rows


def compare_modes(rows: list[dict], max_steps: int, baseline: str = "deterministic",
                  seed: int = 0) -> dict:
    """Per mode: bootstrap median intervals of every metric in ``rows`` (:func:`run_table`),
    and for every other mode the interval of its difference from ``baseline``.

    Returns ``{"levels": [...], "modes": {mode: {metric: {...}}}, "versus_<baseline>":
    {mode: {metric: {...}}}}``; a mode's metrics include ``n`` (seeds) and ``updates`` (the
    fewest updates any of its runs reached, which bounds what "never" means).
    """
    metrics = [f"updates_to_{level:g}" for level in reference_levels(max_steps)]
    metrics += ["final_length", "pybullet_success_rate", "model_success_rate"]
    by_mode = {m: [r for r in rows if r["mode"] == m] for m in MODES}
    by_mode = {m: runs for m, runs in by_mode.items() if runs}
    out = {"levels": reference_levels(max_steps), "modes": {}, f"versus_{baseline}": {}}

    def column(runs, metric):
        return [float(r[metric]) for r in runs if r.get(metric) is not None
                and not (isinstance(r[metric], float) and math.isnan(r[metric]))]

    for mode, runs in by_mode.items():
        stats = {"n": len(runs), "updates": min(r["updates"] for r in runs)}
        for metric in metrics:
            vals = column(runs, metric)
            if vals:
                stats[metric] = bootstrap_median(vals, seed=seed)
        out["modes"][mode] = stats
        if mode != baseline and baseline in by_mode:
            diffs = {}
            for metric in metrics:
                a, b = column(runs, metric), column(by_mode[baseline], metric)
                if a and b:
                    diffs[metric] = bootstrap_median_difference(a, b, seed=seed)
            out[f"versus_{baseline}"][mode] = diffs
    return out


def _number(v: float, digits: int, signed: bool = False) -> str:
    """One bound or median: an infinite update count is "never" (+inf) for a median and "+inf"
    for a difference; NaN (undefined) is "?"."""
    if math.isinf(v):
        return ("+inf" if signed else "never") if v > 0 else "-inf"
    if math.isnan(v):
        return "?"
    return f"{v:{'+' if signed else ''}.{digits}f}"


def _fmt(stat: dict | None, digits: int = 0) -> str:
    """``median [low, high]`` of :func:`bootstrap_median`; ``-`` when there is none."""
    if not stat:
        return "-"
    return " ".join([_number(stat["median"], digits),
                     f"[{_number(stat['low'], digits)}, {_number(stat['high'], digits)}]"])


def _fmt_diff(stat: dict | None, digits: int = 0) -> str:
    """``difference [low, high]`` of :func:`bootstrap_median_difference`; "both never" when
    neither median is finite (inf - inf)."""
    if not stat:
        return "-"
    if math.isnan(stat["difference"]):
        return "both never"
    return " ".join([_number(stat["difference"], digits, signed=True),
                     f"[{_number(stat['low'], digits, True)}, {_number(stat['high'], digits, True)}]"])


def comparison_markdown(comparison: dict, task: str, baseline: str = "deterministic") -> str:
    """The comparison of :func:`compare_modes` as two markdown tables (per mode; versus the
    baseline)."""
    levels = comparison["levels"]
    ups = [f"updates_to_{level:g}" for level in levels]
    head = ("| mode | seeds | updates run | " + " | ".join(f"updates to length {lv:g}" for lv in levels)
            + " | final length | success (pybullet) | success (model) |")
    lines = [f"# {task}: modes compared (median over seeds [bootstrap {LEVEL:.0%} interval])", "",
             head, "|" + "---|" * (6 + len(levels))]
    for mode, s in comparison["modes"].items():
        lines.append(f"| {mode} | {s['n']} | {s['updates']} | "
                     + " | ".join(_fmt(s.get(u)) for u in ups)
                     + f" | {_fmt(s.get('final_length'), 2)} | {_fmt(s.get('pybullet_success_rate'), 2)}"
                     f" | {_fmt(s.get('model_success_rate'), 2)} |")
    versus = comparison.get(f"versus_{baseline}", {})
    if versus:
        lines += ["", f"Difference from `{baseline}` (median of mode minus median of {baseline}; "
                  "an interval that excludes 0 is a difference at that level):", "",
                  "| mode | " + " | ".join(f"updates to {lv:g}" for lv in levels)
                  + " | final length | success (pybullet) |",
                  "|" + "---|" * (3 + len(levels))]
        for mode, d in versus.items():
            lines.append(f"| {mode} | " + " | ".join(_fmt_diff(d.get(u)) for u in ups)
                         + f" | {_fmt_diff(d.get('final_length'), 2)} | "
                         f"{_fmt_diff(d.get('pybullet_success_rate'), 2)} |")
    return "\n".join(lines) + "\n"


def json_safe(obj):
    """``obj`` with every non-finite float replaced by None (strict JSON has no Infinity): in
    ``comparison.json`` a null update count or bound means "never reached"."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [json_safe(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def write_comparison(out_root: str | Path, results: list[dict], task: str, max_steps: int) -> dict:
    """``comparison.json`` (non-finite values as null) and ``comparison.md`` under ``out_root``
    from the runs' logs and results; returns the comparison (with its infinities)."""
    out_root = Path(out_root)
    rows = run_table(out_root, results, max_steps)
    comparison = {"task": task, **compare_modes(rows, max_steps), "runs": rows}
    atomic_write_json(out_root / "comparison.json", json_safe(comparison))
    atomic_write_text(out_root / "comparison.md", comparison_markdown(comparison, task))
    return comparison
