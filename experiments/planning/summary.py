"""The summary of a planning sweep (:mod:`experiments.planning.sweep`): per mode, success rate,
steps to the goal and planning time per control step, with IQM over planner seeds and 95 %
stratified-bootstrap intervals, and the probability of improvement over the deterministic
planner (:mod:`experiments.rl.stats`), beside the PPO policies' closed-loop success on the
same fixed scenes where a PPO summary exists (``docs/results/rl_<task>_summary.json``).

A run is one planner seed: its scores are the means over the scenes it played. Steps count the
task's step limit for a failed episode (the convention of :mod:`hrn_pyg.rl.evaluate`).

::

    python -m experiments.planning.summary --task cube_push_stop --runs runs/planning/cube_push_stop

A sweep split over several folders by ``--modes`` is summarised by naming each (``--runs A --runs B``).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

from experiments.command import script_main
from experiments.planning.sweep import BASELINE, MODES, read_episodes
from experiments.rl.stats import probability_of_improvement, stratified_bootstrap
from hrn_pyg.rl.tasks import TASKS, get_task
from hrn_pyg.utils.files import atomic_write_json, json_safe

DESCRIPTION = "success, steps and planning time of a planning sweep per planner, with intervals and probability of improvement"
#: per-run scores, and whether higher is better
METRICS = {"success_rate": True, "steps": False, "plan_seconds": False}


def run_scores(episodes: list[dict], max_steps: int) -> dict[str, dict[int, dict[str, float]]]:
    """``{mode: {seed: {metric: mean over its scenes}}}`` (:data:`METRICS`)."""
    grouped: dict[str, dict[int, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for e in episodes:
        grouped[e["mode"]][e["seed"]].append(e)
    out: dict[str, dict[int, dict[str, float]]] = {}
    for mode, runs in grouped.items():
        out[mode] = {}
        for seed, eps in runs.items():
            n = len(eps)
            out[mode][seed] = {
                "success_rate": sum(e["success"] for e in eps) / n,
                "steps": sum(e["steps"] if e["success"] else max_steps for e in eps) / n,
                "plan_seconds": sum(e["plan_seconds"] for e in eps) / n,
                "physics_seconds": sum(e["physics_seconds"] for e in eps) / n,
                "scenes": n,
            }
    return out


def summarise(episodes: list[dict], task_name: str, ppo_summary: Path | None = None) -> dict:
    """The summary dict of a sweep's episodes (see the module docstring)."""
    task = get_task(task_name)
    scores = run_scores(episodes, task.max_steps)
    summary: dict = {"task": task.name, "baseline": BASELINE, "max_steps": task.max_steps, "modes": {}}
    for mode in [m for m in MODES if m in scores]:
        runs = scores[mode]
        entry = {"seeds": len(runs), "scenes": sorted({e["scene"] for e in episodes if e["mode"] == mode}),
                 "runs": {str(s): r for s, r in sorted(runs.items())}}
        for metric, higher in METRICS.items():
            values = [r[metric] for r in runs.values()]
            entry[metric] = stratified_bootstrap(values)
            if mode != BASELINE and BASELINE in scores:
                base = [r[metric] for r in scores[BASELINE].values()]
                entry.setdefault("versus_deterministic", {})[metric] = probability_of_improvement(
                    values, base, higher_is_better=higher)
        entry["physics_seconds"] = sum(r["physics_seconds"] for r in runs.values()) / len(runs)
        summary["modes"][mode] = entry
    if ppo_summary is not None and ppo_summary.exists():
        ppo = json.loads(ppo_summary.read_text())
        summary["ppo"] = {"source": str(ppo_summary),
                          "closed_loop_final_success": {m: s.get("closed_loop_final_success")
                                                        for m, s in ppo.get("statistics", {}).items()}}
    return json_safe(summary)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--task", required=True, choices=sorted(TASKS), help="the task of the sweep")
    parser.add_argument("--runs", required=True, action="append",
                        help="the sweep's folder (episodes.jsonl); repeat it for a sweep split by --modes")
    parser.add_argument("--ppo", default=None,
                        help="the PPO summary of the same scenes (default: docs/results/rl_<task>_summary.json)")
    parser.add_argument("--out", default=None, help="the summary (default: docs/results/planning_<task>.json)")


def read_sweeps(folders: list[Path]) -> list[dict]:
    """The episodes of one sweep kept in several folders (a sweep split by ``--modes``): their
    ``sweep.json`` settings must agree and no (mode, scene, seed) may appear twice."""
    settings, episodes, seen = None, [], set()
    for folder in folders:
        path = folder / "episodes.jsonl"
        if not path.exists():
            raise FileNotFoundError(f"no episodes at {path}")
        record = folder / "sweep.json"
        these = json.loads(record.read_text()) if record.exists() else None
        if settings is not None and these != settings:
            raise ValueError(f"{record} holds other settings than {folders[0] / 'sweep.json'}")
        settings = these
        for e in read_episodes(path):
            key = (e["mode"], e["scene"], e["seed"])
            if key in seen:
                raise ValueError(f"{path}: {key[0]} scene {key[1]} seed {key[2]} appears twice")
            seen.add(key)
            episodes.append(e)
    return episodes


def run(args: argparse.Namespace) -> int:
    episodes = read_sweeps([Path(r) for r in args.runs])
    ppo = Path(args.ppo) if args.ppo else Path("docs/results") / f"rl_{args.task}_summary.json"
    out = Path(args.out) if args.out else Path("docs/results") / f"planning_{args.task}.json"
    summary = summarise(episodes, args.task, ppo)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out, summary)
    for mode, entry in summary["modes"].items():
        s, st, t = entry["success_rate"], entry["steps"], entry["plan_seconds"]
        print(f"{mode:22s} success IQM {s['value']:.2f} [{s['low']:.2f}, {s['high']:.2f}]  "
              f"steps {st['value']:.1f}  plan {t['value']:.3f} s/step  ({entry['seeds']} seeds)")
    print(f"summary: {out}")
    return 0


def main(argv=None) -> int:
    return script_main("python -m experiments.planning.summary", DESCRIPTION, add_arguments, run, argv)


if __name__ == "__main__":
    sys.exit(main())
