"""The summary of a sweep that decides between modes: ``rl_<task>_summary.json``.

Reads every run under a sweep folder (``<mode>/seed<k>/log.csv`` and, with ``--eval-every``,
``eval.csv``; what :mod:`hrn_pyg.rl.ppo` writes) and puts together:

- per run (:func:`run_record`): the partial-hit share at update 0 (the initial policy), its mean
  over training and its mean in each tenth of the updates; the same for the near-miss share (the
  partial hits among the goal-reaching steps, :func:`~hrn_pyg.rl.env.near_miss_share`) where
  ``log.csv`` has it; frames to 50 % and 80 % success and
  the area under the success curve, in the learned model, replayed in pybullet and closed loop in
  pybullet (:mod:`hrn_pyg.rl.success_curve`); the final and the mean in-model training episode length;
- per mode and metric (:data:`METRICS`): the IQM over seeds with a stratified-bootstrap 95 %
  interval, and, for every other mode, the probability of improvement over ``deterministic``
  with its interval (:mod:`experiments.rl.stats`);
- performance profiles of the success AUC and final success in pybullet (replayed and closed
  loop) and of the final episode length, and IQM curves of success against frames (replayed,
  or in the model when nothing was replayed; closed loop) and of the in-model episode length
  against updates;
- ``checks``: whether every mode has :data:`MIN_SEEDS` seeds and whether the stochastic modes
  start with a partial-hit share of at least :data:`MIN_PARTIAL_SHARE` (over all steps, and over
  the goal-reaching steps: ``near_miss_share_enough``).

A run that never reaches a success level counts as :math:`+\\infty` frames in the statistics
and is written as ``null`` (strict JSON has no infinity).

``python -m experiments.rl.summary --task T --runs DIR [--out PATH] [--figure PNG]`` writes the summary of the
finished runs a sweep folder holds so far (of a sweep cut short too; a run under way is left out),
prints its main table (:func:`summary_markdown`) and draws its picture
(:func:`experiments.rl.summary_figure.plot_summary`).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path

from experiments.command import script_main
from experiments.rl.stats import (
    RESAMPLES,
    iqm_curve,
    performance_profile,
    probability_of_improvement,
    stratified_bootstrap,
)
from experiments.rl.summary_figure import plot_summary
from hrn_pyg.rl.curves import SMOOTH_UPDATES, curve_metrics, read_curve, smooth
from hrn_pyg.rl.success_curve import curve_summary, read_eval
from hrn_pyg.rl.tasks import MODES, TASKS, TaskConfig, get_task
from hrn_pyg.utils.checkpoint import load_checkpoint
from hrn_pyg.utils.files import atomic_write_json, json_safe

#: what the script does (its --help)
DESCRIPTION = "the statistics of a sweep's runs so far (rl_<task>_summary.json and a table)"
#: seeds per mode a summary should hold to decide anything
MIN_SEEDS = 10
#: partial-hit share at update 0 below which relaxation has (almost) nothing to act on
MIN_PARTIAL_SHARE = 0.1
#: the baseline every other mode is compared with
BASELINE = "deterministic"
#: modes whose environment is stochastic (checked for a partial-hit share)
STOCHASTIC_MODES = ("stochastic", "stochastic_annealed", "stochastic_unrelaxed")
#: per-run metrics compared between modes, and whether higher is better
METRICS = {
    "pybullet_success_auc": True,
    "pybullet_final_success": True,
    "pybullet_frames_to_50": False,
    "pybullet_frames_to_80": False,
    "closed_loop_success_auc": True,
    "closed_loop_final_success": True,
    "closed_loop_frames_to_50": False,
    "closed_loop_frames_to_80": False,
    "model_success_auc": True,
    "model_frames_to_50": False,
    "model_frames_to_80": False,
    "final_length": False,
    "mean_length": False,
}
#: parts of training over which the partial-hit share is averaged
SHARE_PARTS = 10


def _log_column(path: Path, name: str) -> list[float]:
    """One column of a run's ``log.csv`` as floats (NaN where empty)."""
    with open(path, newline="") as fh:
        return [float(r[name]) if r.get(name) not in (None, "") else math.nan for r in csv.DictReader(fh)]


def _mean(values: list[float]) -> float:
    kept = [v for v in values if not math.isnan(v)]
    return sum(kept) / len(kept) if kept else math.nan


def share_by_part(shares: list[float], parts: int = SHARE_PARTS) -> list[float]:
    """Mean partial-hit share in each of ``parts`` consecutive, near-equal blocks of updates
    (fewer blocks when there are fewer updates); NaN entries are skipped."""
    if parts < 1:
        raise ValueError(f"parts must be >= 1, got {parts}")
    n = len(shares)
    parts = min(parts, n)
    bounds = [round(i * n / parts) for i in range(parts + 1)]
    return [_mean(shares[a:b]) for a, b in zip(bounds, bounds[1:])]


def run_record(run_dir: str | Path) -> dict:
    """Everything the summary needs from one run folder (``log.csv``, optional ``eval.csv``)."""
    run_dir = Path(run_dir)
    log = run_dir / "log.csv"
    lengths = read_curve(log)
    shares = _log_column(log, "partial_hit_share")
    frames = _log_column(log, "frames")
    record = {"updates": len(lengths), "frames": frames[-1] if frames else 0.0,
              "partial_hit_share_update0": shares[0] if shares else math.nan,
              "partial_hit_share_mean": _mean(shares),
              "partial_hit_share_by_tenth": share_by_part(shares) if shares else [],
              "final_length": curve_metrics(lengths)["final_length"],
              "mean_length": _mean(lengths)}
    with open(log, newline="") as fh:
        logged_near = "near_miss_share" in (csv.DictReader(fh).fieldnames or [])
    if logged_near:  # logs written before the column existed have none
        near = _log_column(log, "near_miss_share")
        record.update(near_miss_share_update0=near[0] if near else math.nan,
                      near_miss_share_mean=_mean(near),
                      near_miss_share_by_tenth=share_by_part(near) if near else [])
    if record["final_length"] is None:
        record["final_length"] = math.nan
    if (run_dir / "eval.csv").is_file():
        curve = read_eval(run_dir / "eval.csv")
        record.update(curve_summary(curve))
        record["eval_curve"] = {k: curve[k] for k in ("frames", "model_success_rate", "pybullet_success_rate",
                                                      "closed_loop_success_rate")}
    return record


def run_finished(run_dir: str | Path) -> bool:
    """Whether a run folder holds a finished run: its ``policy.pt`` was saved after the number
    of updates its settings ask for (a run under way or cut short is not)."""
    path = Path(run_dir) / "policy.pt"
    if not path.is_file():
        return False
    ckpt = load_checkpoint(path)
    return int(ckpt["update"]) >= int(json.loads(ckpt["config"])["ppo"]["updates"])


def find_runs(out_root: str | Path, finished_only: bool = False) -> dict[str, dict[int, dict]]:
    """``{mode: {seed: run_record}}`` of every run under ``out_root`` (modes in
    :data:`~hrn_pyg.rl.tasks.MODES` order); with ``finished_only`` the finished runs only
    (:func:`run_finished`)."""
    out_root = Path(out_root)
    runs: dict[str, dict[int, dict]] = {}
    for mode in MODES:
        for log in sorted((out_root / mode).glob("seed*/log.csv")):
            if finished_only and not run_finished(log.parent):
                continue
            seed = int(log.parent.name.removeprefix("seed"))
            runs.setdefault(mode, {})[seed] = run_record(log.parent)
    return runs


def _scores(records: list[dict], metric: str) -> list[float]:
    """A metric over runs; a missing frames-to-level is not a score (NaN values are skipped)."""
    return [float(r[metric]) for r in records if r.get(metric) is not None and not math.isnan(float(r[metric]))]


def _curves(records: list[dict], key: str) -> list[list[float]] | None:
    """Per-run success (column ``key`` of ``eval.csv``) at the evaluations every run has (cut
    to the shortest); None when a run lacks it."""
    rows = [r["eval_curve"][key] for r in records if "eval_curve" in r]
    if not rows or len(rows) < len(records) or any(math.isnan(v) for row in rows for v in row):
        return None
    n = min(len(r) for r in rows)
    return [row[:n] for row in rows]


def task_summary(out_root: str | Path, task: str | TaskConfig, resamples: int = RESAMPLES,
                 seed: int = 0, curve_points: int = 100, finished_only: bool = False) -> dict:
    """The summary of every run under ``out_root`` (module docstring), or of its finished runs
    only; non-finite values kept (:func:`write_task_summary` writes them as null)."""
    task = get_task(task)
    runs = find_runs(out_root, finished_only)
    if not runs:
        raise FileNotFoundError(f"no runs (<mode>/seed<k>/log.csv) under {out_root}")
    boot = {"resamples": resamples, "seed": seed}
    out: dict = {"task": task.name, "max_steps": task.max_steps, "baseline": BASELINE,
                 "min_seeds": MIN_SEEDS, "modes": {}, "statistics": {}, "versus_" + BASELINE: {},
                 "performance_profiles": {}, "iqm_curves": {}}
    for mode, by_seed in runs.items():
        records = list(by_seed.values())
        shares0 = _scores(records, "partial_hit_share_update0")
        out["modes"][mode] = {
            "seeds": sorted(by_seed), "n": len(records),
            "partial_hit_share_update0": stratified_bootstrap(shares0, **boot) if shares0 else None,
            "partial_hit_share_mean": (stratified_bootstrap(s, **boot)
                                       if (s := _scores(records, "partial_hit_share_mean")) else None),
            "near_miss_share_update0": (stratified_bootstrap(s, **boot)
                                        if (s := _scores(records, "near_miss_share_update0")) else None),
            "near_miss_share_mean": (stratified_bootstrap(s, **boot)
                                     if (s := _scores(records, "near_miss_share_mean")) else None),
            "runs": [{"seed": s, **{k: v for k, v in r.items() if k != "eval_curve"}}
                     for s, r in by_seed.items()]}
        stats = {}
        for metric in METRICS:
            values = _scores(records, metric)
            if values:
                stats[metric] = stratified_bootstrap(values, **boot)
        out["statistics"][mode] = stats
        success = _curves(records, "pybullet_success_rate") or _curves(records, "model_success_rate")
        curves: dict = {}
        if success:
            frames = records[0]["eval_curve"]["frames"][:len(success[0])]
            judge = "pybullet" if _curves(records, "pybullet_success_rate") else "model"
            curves["success"] = {"judge": judge, "frames": frames, **iqm_curve(success, **boot)}
        if closed := _curves(records, "closed_loop_success_rate"):
            frames = records[0]["eval_curve"]["frames"][:len(closed[0])]
            curves["closed_loop_success"] = {"judge": "closed_loop", "frames": frames, **iqm_curve(closed, **boot)}
        lengths = [smooth(read_curve(Path(out_root) / mode / f"seed{s}" / "log.csv"), SMOOTH_UPDATES)
                   for s in by_seed]
        n = min(len(c) for c in lengths)
        stride = max(1, math.ceil(n / curve_points))
        picked = list(range(0, n, stride))
        table = [[c[i] for i in picked] for c in lengths]
        if n and not any(math.isnan(v) for row in table for v in row):
            curves["episode_length"] = {"update": picked, "window": SMOOTH_UPDATES, **iqm_curve(table, **boot)}
        out["iqm_curves"][mode] = curves
    if BASELINE in runs:
        base = list(runs[BASELINE].values())
        for mode, by_seed in runs.items():
            if mode == BASELINE:
                continue
            records, versus = list(by_seed.values()), {}
            for metric, higher in METRICS.items():
                a, b = _scores(records, metric), _scores(base, metric)
                if a and b:
                    versus[metric] = probability_of_improvement(a, b, higher_is_better=higher, **boot)
            out["versus_" + BASELINE][mode] = versus
    profiles = {"pybullet_success_auc": ([i / 20 for i in range(21)], True),
                "pybullet_final_success": ([i / 20 for i in range(21)], True),
                "closed_loop_success_auc": ([i / 20 for i in range(21)], True),
                "closed_loop_final_success": ([i / 20 for i in range(21)], True),
                "final_length": ([float(t) for t in range(1, task.max_steps + 1)], False)}
    for metric, (taus, higher) in profiles.items():
        per_mode = {mode: performance_profile(v, taus, higher, **boot) for mode, by_seed in runs.items()
                    if (v := _scores(list(by_seed.values()), metric))}
        if per_mode:
            out["performance_profiles"][metric] = {"higher_is_better": higher, "modes": per_mode}
    out["checks"] = summary_checks(out)
    return out


def summary_checks(summary: dict) -> dict:
    """Whether the summary can decide: seeds per mode against :data:`MIN_SEEDS`, and the IQM
    partial-hit share at update 0 of each stochastic mode against :data:`MIN_PARTIAL_SHARE`, over
    all steps and over the goal-reaching (near-miss) steps. Under relaxation an episode ends at
    its ``hold_steps``-th goal-reaching step in a row, so the share over all steps is capped near
    ``hold_steps`` over the episode length; the near-miss share is not capped."""
    modes = summary["modes"]
    seeds = {m: s["n"] for m, s in modes.items()}
    share = {m: (s["partial_hit_share_update0"] or {}).get("value") for m, s in modes.items()
             if m in STOCHASTIC_MODES}
    near = {m: (s.get("near_miss_share_update0") or {}).get("value") for m, s in modes.items()
            if m in STOCHASTIC_MODES}
    return {"seeds_per_mode": seeds, "enough_seeds": all(n >= MIN_SEEDS for n in seeds.values()),
            "all_modes_present": all(m in modes for m in MODES),
            "partial_hit_share_update0": share, "near_miss_share_update0": near,
            "partial_hit_share_enough": all(v is not None and v >= MIN_PARTIAL_SHARE for v in share.values())
            if share else False,
            "near_miss_share_enough": all(v is not None and v >= MIN_PARTIAL_SHARE for v in near.values())
            if near else False}


def write_task_summary(out_root: str | Path, task: str | TaskConfig, path: str | Path | None = None,
                       **kwargs) -> dict:
    """Write :func:`task_summary` as JSON (infinities as null) to ``path`` (default
    ``<out_root>/rl_<task>_summary.json``, atomically); returns the summary as computed."""
    task = get_task(task)
    summary = task_summary(out_root, task, **kwargs)
    path = Path(path) if path is not None else Path(out_root) / f"rl_{task.name}_summary.json"
    atomic_write_json(path, json_safe(summary))
    return summary


#: the metrics of :func:`summary_markdown`: (key, column title, digits)
TABLE_METRICS = (("closed_loop_success_auc", "closed-loop success AUC", 2),
                 ("closed_loop_final_success", "closed-loop final success", 2),
                 ("model_success_auc", "in-model success AUC", 2),
                 ("final_length", "final in-model length", 1))


def _interval(stat: dict | None, digits: int) -> str:
    """``value [low, high]``; ``-`` when there is none, ``never`` for an infinite value."""
    if not stat:
        return "-"

    def one(v: float | None) -> str:
        return "never" if v is None or math.isinf(v) else f"{v:.{digits}f}"

    return f"{one(stat['value'])} [{one(stat['low'])}, {one(stat['high'])}]"


def summary_markdown(summary: dict) -> str:
    """Two markdown tables of a :func:`task_summary`: per mode the IQM of :data:`TABLE_METRICS`
    with its 95 % interval and the near-miss share at update 0; per stochastic or noisy mode the
    probability of improvement over the baseline."""
    titles = " | ".join(t for _, t, _ in TABLE_METRICS)
    lines = [f"{summary['task']}: IQM over seeds [95 % stratified-bootstrap interval]", "",
             f"| mode | seeds | {titles} | near-miss share, update 0 |",
             "|---|---:|" + "---|" * (len(TABLE_METRICS) + 1)]
    for mode, info in summary["modes"].items():
        stats = summary["statistics"].get(mode, {})
        cells = " | ".join(_interval(stats.get(k), d) for k, _, d in TABLE_METRICS)
        lines.append(f"| {mode} | {info['n']} | {cells} | {_interval(info.get('near_miss_share_update0'), 2)} |")
    versus = summary.get("versus_" + summary["baseline"], {})
    if versus:
        lines += ["", f"probability of improvement over {summary['baseline']} [95 % interval]", "",
                  f"| mode | {titles} |", "|---|" + "---|" * len(TABLE_METRICS)]
        for mode, poi in versus.items():
            lines.append(f"| {mode} | " + " | ".join(_interval(poi.get(k), 2) for k, _, _ in TABLE_METRICS) + " |")
    return "\n".join(lines) + "\n"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--task", choices=sorted(TASKS), required=True, help="the task of the sweep")
    parser.add_argument("--runs", required=True, help="a sweep folder (<mode>/seed<k>/log.csv)")
    parser.add_argument("--out", default=None, help="the summary to write (default: RUNS/rl_<task>_summary.json)")
    parser.add_argument("--resamples", type=int, default=RESAMPLES, help="bootstrap resamples")
    parser.add_argument("--figure", default=None,
                        help="also draw the summary's four panels to this picture (experiments.rl.summary_figure)")


def run(args: argparse.Namespace) -> int:
    if args.resamples < 1:
        raise ValueError(f"--resamples must be >= 1, got {args.resamples}")
    out = Path(args.out) if args.out else Path(args.runs) / f"rl_{args.task}_summary.json"
    summary = write_task_summary(args.runs, args.task, out, resamples=args.resamples, finished_only=True)
    print(summary_markdown(summary), end="")
    if args.figure:
        plot_summary(json.loads(out.read_text()), args.figure)
        print(f"drew {args.figure}")
    checks = summary["checks"]
    print(f"seeds per mode {checks['seeds_per_mode']} (enough: {checks['enough_seeds']}); "
          f"near-miss share at update 0 enough: {checks['near_miss_share_enough']}; wrote {out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    return script_main("python -m experiments.rl.summary", DESCRIPTION, add_arguments, run, argv)


if __name__ == "__main__":
    sys.exit(main())
