"""``python -m experiments.rl.sweep``: PPO runs of a task over modes and seeds, and what
compares the modes (the sweeps of docs/rl.md).

Each run is one :func:`hrn_pyg.rl.ppo.train` (what ``hrn-pyg rl`` runs, with the same options
of :func:`~hrn_pyg.rl.ppo.add_training_arguments`) in ``<out>/<mode>/seed<k>``, seed by seed
with every mode of a seed together, so that a sweep cut short has all modes on its first seeds.
Running the command again continues each run from its ``policy.pt``. Then, under ``--out``
(default ``runs/rl/<task>``), over every run recorded there so far::

    summary.json                  per run: what hrn-pyg rl writes to result.json (a rerun of a
                                  mode and seed replaces its entry)
    summary.csv, summary.md       the same per run, and per mode over seeds (median [min, max]);
                                  experiments.rl.episode_length
    comparison.json, .md          per mode: updates to fixed episode lengths, final length and
                                  success, median over seeds with bootstrap 95 % intervals, and
                                  each mode's difference from deterministic (experiments.rl.stats)
    rl_<task>_summary.json        per run: partial-hit share (update 0, along training), frames to
                                  50 / 80 % success and success AUC; per mode: IQM with stratified
                                  bootstrap intervals, probability of improvement over
                                  deterministic, performance profiles (experiments.rl.summary)
    episode_length.png            every mode found under --out: median over seeds, range shaded
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from experiments.command import script_main
from experiments.rl.episode_length import plot_episode_length, write_summary
from experiments.rl.stats import write_comparison
from experiments.rl.summary import write_task_summary
from hrn_pyg.rl.ppo import add_training_arguments, setup_from_args, train_from_args
from hrn_pyg.rl.tasks import MODES
from hrn_pyg.utils.files import atomic_write_json
from hrn_pyg.utils.options import add_renamed

#: what the script does (its --help)
DESCRIPTION = "PPO runs of a task over modes and seeds, and the tables and statistics that compare the modes"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_training_arguments(parser)
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES), help="one or more modes")
    parser.add_argument("--num-seeds", type=int, default=3, dest="seeds", metavar="N", help="runs per mode, one seed each")
    parser.add_argument("--first-seed", type=int, default=0, dest="seed_start", metavar="SEED",
                        help="seed of each mode's first run (run k: first seed + k)")
    parser.add_argument("--out", default=None, help="the sweep's folder (default: runs/rl/<task>)")
    add_renamed(parser, "--mode", "--modes")
    add_renamed(parser, "--seeds", "--num-seeds")
    add_renamed(parser, "--seed-start", "--first-seed")


def run(args: argparse.Namespace) -> int:
    if args.seeds < 1:
        raise ValueError(f"--num-seeds must be >= 1, got {args.seeds}")
    setup = setup_from_args(args)
    task = setup.task
    out = Path(args.out) if args.out else Path("runs/rl") / task.name
    modes = list(dict.fromkeys(args.modes))
    results = [train_from_args(args, setup, mode, seed, out / mode / f"seed{seed}")
               for seed in range(args.seed_start, args.seed_start + args.seeds) for mode in modes]
    summary_path = out / "summary.json"
    previous = json.loads(summary_path.read_text()) if summary_path.is_file() else []
    done = {(r["mode"], r["seed"]) for r in results}
    runs = [r for r in previous if (r.get("mode"), r.get("seed")) not in done] + results
    atomic_write_json(summary_path, runs)
    write_summary(out, runs)
    write_comparison(out, runs, task.name, task.max_steps)
    write_task_summary(out, task)
    drawn = plot_episode_length(out, out / "episode_length.png",
                                title=f"{task.name}: average episode length"
                                + ("" if args.model else " (point-mass dynamics)"))
    print(f"wrote {out / 'episode_length.png'} ({', '.join(drawn)})")
    return 0


def main(argv: list[str] | None = None) -> int:
    return script_main("python -m experiments.rl.sweep", DESCRIPTION, add_arguments, run, argv)


if __name__ == "__main__":
    sys.exit(main())
