"""The command line of ``python -m experiments.recipe``: ``add_arguments`` and ``run``, which
carries the recipe out with a :class:`~experiments.recipe.runner.Runner` (exit code 1 when
something failed; a rerun continues), and ``main``."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from experiments.command import script_main

from experiments.recipe.runner import DEFAULT_CHECKPOINTS_DIR, RunConfig, Runner
from experiments.recipe.schema import RECIPE_PATH, load_recipe


#: how the command is run (from the checkout's root; ``make checkpoints`` runs it)
PROG = "python -m experiments.recipe"
DESCRIPTION = "remake the shipped checkpoints from data/recipes.toml"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--recipe", default=RECIPE_PATH, help="recipe file")
    parser.add_argument("--only", default="", help="NAME[,NAME]: only these models (default: all)")
    parser.add_argument("--data-dir", default="data", help="datasets go to DATA_DIR/<dataset>")
    parser.add_argument("--runs-dir", default="runs/recipe", help="run folders")
    parser.add_argument("--checkpoints-dir", default=str(DEFAULT_CHECKPOINTS_DIR),
                        help="where <model>.pt and manifest.json go, relative to the working directory "
                             "(`make checkpoints` names hrn_pyg/checkpoints, the shipped ones)")
    parser.add_argument("--device", default=None, help="passed to train (default: CUDA when available)")
    parser.add_argument("--jobs", type=int, default=1,
                        help="trainings at once, each its own process; also generate's --workers")
    parser.add_argument("--threads", type=int, default=0,
                        help="torch threads of every training in place of the recipe's (0: the recipe's); "
                             "not part of what makes a run the same, so a stopped run continues with more")
    parser.add_argument("--skip-generate", action="store_true",
                        help="the datasets are already there: not generated; each stage's are checked before it trains")
    parser.add_argument("--dry-run", action="store_true", help="print the commands, run and write nothing")
    parser.add_argument("--time-limit", type=float, default=0.0,
                        help="minutes each training may run in this call, 0 for no limit; a rerun continues it")


def config_from_args(args: argparse.Namespace) -> RunConfig:
    return RunConfig(recipe=Path(args.recipe), data_dir=Path(args.data_dir), runs_dir=Path(args.runs_dir),
                     checkpoints_dir=Path(args.checkpoints_dir), device=args.device or None, jobs=args.jobs,
                     skip_generate=args.skip_generate, dry_run=args.dry_run,
                     only=tuple(n for n in args.only.split(",") if n), time_limit=args.time_limit,
                     threads=args.threads)


def run(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    if not config.recipe.is_file():
        raise FileNotFoundError(f"recipe: {config.recipe} does not exist; run in a checkout of the repository "
                                "(its data/ folder holds the recipe and its scene files) or pass --recipe")
    runner = Runner(load_recipe(config.recipe), config, say=lambda line: print(line, flush=True))
    failed = runner.run()
    if failed:
        print(f"{PROG}: failed: {', '.join(failed)}; rerun to continue", file=sys.stderr)
        return 1
    if runner.paused:
        print(f"paused at the time limit: {', '.join(runner.paused)}; rerun the same command to continue")
        return 0
    if not config.dry_run:
        print(f"checkpoints up to date: {', '.join(m.name for m in runner.models)}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return script_main(PROG, DESCRIPTION, add_arguments, run, argv)
