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

**Aggregates over runs** (the second half, as ``rliable`` computes them, written here in
torch): the interquartile mean (:func:`iqm`) with stratified-bootstrap intervals
(:func:`stratified_bootstrap`), the probability that a run of one mode beats a run of another
(:func:`probability_of_improvement`), performance profiles (:func:`performance_profile`) and
IQM curves (:func:`iqm_curve`). :mod:`experiments.rl.summary` applies them to a sweep.

Nothing here trains or steps an environment: it reads ``<mode>/seed<k>/log.csv`` through
:mod:`hrn_pyg.rl.curves` and the per-run results a sweep (:mod:`experiments.rl.sweep`) writes to
``summary.json``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path

import torch

from hrn_pyg.rl.curves import curve_metrics, read_curve, updates_to_reach
from hrn_pyg.rl.tasks import MODES
from hrn_pyg.utils.files import atomic_write_json, atomic_write_text, json_safe

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


def write_comparison(out_root: str | Path, results: list[dict], task: str, max_steps: int) -> dict:
    """``comparison.json`` (non-finite values as null) and ``comparison.md`` under ``out_root``
    from the runs' logs and results; returns the comparison (with its infinities)."""
    out_root = Path(out_root)
    rows = run_table(out_root, results, max_steps)
    comparison = {"task": task, **compare_modes(rows, max_steps), "runs": rows}
    atomic_write_json(out_root / "comparison.json", json_safe(comparison))
    atomic_write_text(out_root / "comparison.md", comparison_markdown(comparison, task))
    return comparison


# ---------------------------------------------------------------------------- rliable-style
# Aggregates over runs that hold with few seeds (Agarwal et al., "Deep RL at the edge of the
# statistical precipice", 2021, and their ``rliable`` library): the interquartile mean, the
# stratified bootstrap, the probability of improvement and performance profiles. Scores are
# ``(n, T)``: ``n`` runs (seeds) of ``T`` tasks; a 1-D tensor is one task. The bootstrap draws
# runs with replacement within each task (the strata), never across tasks.


#: scores of runs: ``(n,)`` or ``(n, T)``, a tensor or nested lists
Scores = torch.Tensor | Sequence[float] | Sequence[Sequence[float]]


def _as_runs(scores: Scores, what: str) -> torch.Tensor:
    """``scores`` as a float64 ``(n, T)`` tensor; NaN (a missing score) is refused, ``+inf``
    (a censored one: never reached) is allowed."""
    x = torch.as_tensor(scores, dtype=torch.float64)
    if x.dim() == 1:
        x = x.unsqueeze(-1)
    if x.dim() != 2 or x.shape[0] < 1 or x.shape[1] < 1:
        raise ValueError(f"{what} must be (runs,) or (runs, tasks) with at least one run, got "
                         f"shape {tuple(x.shape)}")
    if torch.isnan(x).any():
        raise ValueError(f"{what} holds NaN; pass math.inf for a run that never reached a level")
    return x


def iqm(scores: torch.Tensor) -> torch.Tensor:
    r"""Interquartile mean over the last dimension: with the :math:`n` values sorted,
    :math:`\frac{1}{n - 2c}\sum_{i=c}^{n-c-1} x_{(i)}`, :math:`c = \lfloor n/4 \rfloor` (the
    25 % trimmed mean of ``scipy.stats.trim_mean``, what ``rliable`` calls IQM). A kept
    :math:`+\infty` makes it infinite. **Shapes**: ``(..., n)`` -> ``(...)``.
    """
    n = scores.shape[-1]
    if n < 1:
        raise ValueError("iqm needs at least one value")
    cut = n // 4
    return scores.sort(dim=-1).values[..., cut:n - cut].mean(-1)


def iqm_of_runs(scores: torch.Tensor) -> torch.Tensor:
    """IQM over every run of every task, ``(..., n, T)`` -> ``(...)`` (``rliable``'s
    ``aggregate_iqm``)."""
    return iqm(scores.flatten(-2))


def _resample(x: torch.Tensor, resamples: int, generator: torch.Generator) -> torch.Tensor:
    """Stratified bootstrap resamples of ``x`` ``(n, T)``: runs drawn with replacement within
    each task, ``(resamples, n, T)``."""
    n, T = x.shape
    index = torch.randint(n, (resamples, n, T), generator=generator)
    return x[index, torch.arange(T)]


def _percentile_interval(values: torch.Tensor, level: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Percentile interval along dim 0 of bootstrap statistics ``(R, ...)``; the index
    convention of :func:`_interval`."""
    ordered = values.sort(dim=0).values
    r = ordered.shape[0]
    lo_i = int(math.floor((1 - level) / 2 * (r - 1)))
    hi_i = int(math.ceil((1 + level) / 2 * (r - 1)))
    return ordered[lo_i], ordered[hi_i]


def _check_bootstrap(resamples: int, level: float) -> None:
    if not 0 < level < 1 or resamples < 1:
        raise ValueError(f"need 0 < level < 1 and resamples >= 1, got {level}, {resamples}")


def stratified_bootstrap(scores: Scores, statistic: Callable[[torch.Tensor], torch.Tensor] | None = None,
                         resamples: int = RESAMPLES, level: float = LEVEL,
                         seed: int = 0) -> dict[str, float | int]:
    """A statistic of runs and its stratified-bootstrap percentile interval.

    Args:
        scores: ``(n,)`` or ``(n, T)``, ``+inf`` for a censored run.
        statistic: ``(..., n, T) -> (...)``; None: the IQM over runs and tasks
            (:func:`iqm_of_runs`).
        resamples, level, seed: bootstrap size, interval level, generator seed (the result is
            deterministic for a given seed).

    Returns ``{"value", "low", "high", "n"}`` (``n`` runs per task).
    """
    _check_bootstrap(resamples, level)
    statistic = iqm_of_runs if statistic is None else statistic
    x = _as_runs(scores, "scores")
    g = torch.Generator().manual_seed(seed)
    lo, hi = _percentile_interval(statistic(_resample(x, resamples, g)), level)
    return {"value": float(statistic(x)), "low": float(lo), "high": float(hi), "n": x.shape[0]}


def probability_of_improvement_point(x: torch.Tensor, y: torch.Tensor,
                                     higher_is_better: bool = True) -> torch.Tensor:
    r"""Probability that a run of X beats a run of Y, averaged over tasks:

    .. math::
        P(X > Y) = \frac{1}{T}\sum_{t=1}^{T} \frac{1}{n m} \sum_{i=1}^{n}\sum_{j=1}^{m}
        \Big(\mathbb 1[x_{it} > y_{jt}] + \tfrac12 \mathbb 1[x_{it} = y_{jt}]\Big)

    (the Mann-Whitney U statistic over :math:`nm`); "beats" is ">" or, with
    ``higher_is_better=False``, "<". Two censored (infinite) runs tie.

    **Shapes**: x ``(..., n, T)``, y ``(..., m, T)`` -> ``(...)``.
    """
    a, b = x.unsqueeze(-2), y.unsqueeze(-3)                       # (..., n, 1, T), (..., 1, m, T)
    better = (a > b) if higher_is_better else (a < b)
    wins = better.double() + 0.5 * (a == b).double()              # (..., n, m, T)
    return wins.mean(dim=(-3, -2)).mean(-1)


def probability_of_improvement(x: Scores, y: Scores, higher_is_better: bool = True, resamples: int = RESAMPLES,
                               level: float = LEVEL, seed: int = 0) -> dict[str, float | int]:
    """:func:`probability_of_improvement_point` of X over Y with a bootstrap interval, X and Y
    resampled independently, each stratified by task. Returns ``{"value", "low", "high",
    "n_x", "n_y"}``; a lower bound above 0.5 says X beats Y more often than not at ``level``.
    """
    _check_bootstrap(resamples, level)
    xs, ys = _as_runs(x, "x"), _as_runs(y, "y")
    if xs.shape[1] != ys.shape[1]:
        raise ValueError(f"x and y must have the same tasks, got {xs.shape[1]} and {ys.shape[1]}")
    g = torch.Generator().manual_seed(seed)
    boot = probability_of_improvement_point(_resample(xs, resamples, g), _resample(ys, resamples, g),
                                            higher_is_better)
    lo, hi = _percentile_interval(boot, level)
    return {"value": float(probability_of_improvement_point(xs, ys, higher_is_better)),
            "low": float(lo), "high": float(hi), "n_x": xs.shape[0], "n_y": ys.shape[0]}


def performance_profile_point(scores: torch.Tensor, taus: torch.Tensor,
                              higher_is_better: bool = True) -> torch.Tensor:
    r"""Fraction of runs (over every task) whose score passes each threshold :math:`\tau`:
    :math:`\frac{1}{nT}\sum \mathbb 1[x > \tau]` (``rliable``'s run-score distribution), or
    :math:`\mathbb 1[x \le \tau]` with ``higher_is_better=False`` (e.g. the share of runs that
    reach a level within :math:`\tau` frames).

    **Shapes**: scores ``(..., n, T)``, taus ``(K,)`` -> ``(..., K)``.
    """
    flat = scores.flatten(-2).unsqueeze(-1)                       # (..., nT, 1)
    passed = (flat > taus) if higher_is_better else (flat <= taus)
    return passed.double().mean(-2)


def performance_profile(scores: Scores, taus: Sequence[float] | torch.Tensor, higher_is_better: bool = True, resamples: int = RESAMPLES,
                        level: float = LEVEL, seed: int = 0) -> dict[str, list[float]]:
    """:func:`performance_profile_point` at every ``tau`` with stratified-bootstrap intervals:
    ``{"tau", "fraction", "low", "high"}``, one entry per threshold."""
    _check_bootstrap(resamples, level)
    x = _as_runs(scores, "scores")
    t = torch.as_tensor(taus, dtype=torch.float64).reshape(-1)
    if t.numel() < 1:
        raise ValueError("performance_profile needs at least one threshold")
    g = torch.Generator().manual_seed(seed)
    lo, hi = _percentile_interval(performance_profile_point(_resample(x, resamples, g), t,
                                                            higher_is_better), level)
    return {"tau": t.tolist(), "fraction": performance_profile_point(x, t, higher_is_better).tolist(),
            "low": lo.tolist(), "high": hi.tolist()}


def iqm_curve(curves: torch.Tensor | Sequence[Sequence[float]], resamples: int = RESAMPLES, level: float = LEVEL,
              seed: int = 0) -> dict[str, list[float]]:
    """IQM over runs at every point of a curve, with stratified-bootstrap intervals (the same
    resampled runs at every point). ``curves`` ``(n, P)``: one row per run, one column per point
    (evaluation or update). Returns ``{"iqm", "low", "high"}``, ``P`` values each."""
    _check_bootstrap(resamples, level)
    x = torch.as_tensor(curves, dtype=torch.float64)
    if x.dim() != 2 or x.shape[0] < 1 or x.shape[1] < 1:
        raise ValueError(f"curves must be (runs, points), got shape {tuple(x.shape)}")
    if torch.isnan(x).any():
        raise ValueError("curves hold NaN")
    g = torch.Generator().manual_seed(seed)
    index = torch.randint(x.shape[0], (resamples, x.shape[0]), generator=g)
    boot = iqm(x[index].transpose(-1, -2))                        # (R, P)
    lo, hi = _percentile_interval(boot, level)
    return {"iqm": iqm(x.T).tolist(), "low": lo.tolist(), "high": hi.tolist()}
