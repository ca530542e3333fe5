"""The ``hrn-pyg`` command: one entry point, one sub-command per job.

A sub-command's work is one module's ``run(args) -> int``; its ``add_arguments(parser)`` is in
the torch-free :mod:`hrn_pyg.commands` where there is one (:func:`arguments_module`). Bad input
raises ``ValueError`` (or ``FileNotFoundError``); here it becomes one line on stderr, exit code 2.

One name, one meaning, across every sub-command and the experiment scripts (:data:`MEANINGS`;
``tests/test_command_line.py`` checks it): a count is a plain plural (``--episodes``) or
``--num-<things>``, a list the plural alone (``--episode-seeds 8,18``); steps and seeds say which
(``--episode-steps``, ``--horizon``, ``--train-steps``; ``--seed``, ``--episode-seed``,
``--first-seed``, ``--sample-seed``); every ``--help`` shows each default; a command that draws
a progress bar takes ``--no-progress``; ``--scene`` takes the built-in scenes only.

An old spelling of a renamed option still works for one release with a one-line warning on
stderr (:func:`~hrn_pyg.utils.options.add_renamed`; :data:`RENAMED` lists them).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys
from collections.abc import Callable, Sequence
from types import ModuleType

from hrn_pyg.utils.options import HelpFormatter, run_reporting_errors
from hrn_pyg.version import __version__

#: sub-command -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "generate": ("hrn_pyg.data.generate", "simulate a scene in pybullet (or MuJoCo: --engine mujoco) and write episodes"),
    "check-data": ("hrn_pyg.data.check", "check that a folder of episode files is one training can read"),
    "import": ("hrn_pyg.data.tracks", "turn point tracks (npz, learning_to_simulate) into episode files"),
    "train": ("hrn_pyg.train", "train an HRN (presets: hrn, ours) or the GNS baseline (preset gns)"),
    "evaluate": ("hrn_pyg.evaluate", "Table 1: rollout errors of HRN vs ours on the test split"),
    "sample": ("hrn_pyg.sampling.cli", "sample K futures with Monte Carlo dropout"),
    "calibrate": ("hrn_pyg.sampling.calibrate",
                  "choose a model's sampling rate so its spread matches a validation ensemble"),
    "rl": ("hrn_pyg.rl.ppo", "train and score one PPO run in the learned environment "
           "(sweeps over modes and seeds: python -m experiments.rl.sweep in a checkout)"),
    "plan": ("hrn_pyg.rl.planning", "plan each action through the learned model (CEM over sampled "
             "futures), one closed-loop episode judged in pybullet"),
    "demo": ("hrn_pyg.demo", "the two-minute tour on the shipped checkpoints"),
    "models": ("hrn_pyg.checkpoints.cli", "list the shipped models and what each was trained on"),
    "view": ("hrn_pyg.export.view", "ground truth and sampled futures in 3D in the browser (one HTML file, served on 127.0.0.1)"),
}

#: commands that left the package -> where they are (given, one line on stderr and exit code 2)
MOVED: dict[str, str] = {
    "checkpoints": "a maintainer's tool beside the package: `make checkpoints` (python -m experiments.recipe) "
                   "in a checkout of the repository",
}

#: what each option name shared by two or more commands means (one meaning per name)
MEANINGS: dict[str, str] = {
    "--data": "an episode folder from `hrn-pyg generate` (calibrate: repeatable)",
    "--device": "the torch device (cpu, cuda, cuda:1); default cuda when available",
    "--episodes": "a count of episodes (generated, or demonstrations collected)",
    "--episode-seed": "the pybullet episode simulated",
    "--eval-every": "updates or optimiser steps between evaluations",
    "--first-seed": "the first of consecutive seeds, one per episode or run",
    "--fps": "frames per second of an animation",
    "--horizon": "model steps predicted from a start",
    "--k": "sampled futures per start",
    "--lr": "the optimiser's learning rate",
    "--model": "a model checkpoint: a path or a shipped model's name (evaluate: NAME=PATH, repeatable)",
    "--no-progress": "draw no progress bar",
    "--no-sleep": "every object runs at every step (no sleeping objects at rest)",
    "--out": "the output folder, by default under runs/<command>/ (generate: the dataset; calibrate: a checkpoint file)",
    "--pitch": "the spacing of the leaves on the lattice, in m",
    "--scene": "a built-in scene's name",
    "--scene-file": "a scene file (TOML)",
    "--seed": "seeds a run's own random draws (initialisation, batches, noise)",
    "--rate": "the dropout rate of sampled futures (default: the model's calibrated rate, else a default of the command)",
    "--sample-seed": "seeds the dropout masks of sampled futures",
    "--split": "the split of a dataset: test, val or all",
    "--strict": "data outside a model's training domain is an error, not a warning",
    "--task": "an RL task's name",
    "--threads": "torch threads",
    "--time-limit": "minutes a call may train before it stops as if interrupted",
    "--train-steps": "optimiser steps",
    "--workers": "processes working beside the main one",
}

#: old spelling -> new, per command (each still works, with a warning, for one release)
RENAMED: dict[str, dict[str, str]] = {
    "generate": {"--steps": "--episode-steps", "--seed-offset": "--first-seed"},
    "train": {"--steps": "--train-steps"},
    "sample": {"--steps": "--horizon", "--seed": "--episode-seed"},
    "calibrate": {"--steps": "--horizon", "--seeds": "--episode-seeds", "--modules": "--module-sets"},
}


def arguments_module(command: str) -> ModuleType:
    """The module defining ``command``'s arguments: ``hrn_pyg.commands.<command>`` (no torch, so
    ``--help`` answers at once) where there is one, else the command's own module."""
    light = f"hrn_pyg.commands.{command.replace('-', '_')}"
    return importlib.import_module(light if importlib.util.find_spec(light) else COMMANDS[command][0])


def deferred_run(module_name: str) -> Callable[[argparse.Namespace], int]:
    """``run`` of ``module_name``, imported when the command runs rather than when it is parsed."""
    def run(args: argparse.Namespace) -> int:
        return importlib.import_module(module_name).run(args)

    return run


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``command``'s arguments are imported (its work loads torch, pybullet, ...
    when it runs)."""
    parser = argparse.ArgumentParser(prog="hrn-pyg", description=__doc__.splitlines()[0],
                                     formatter_class=HelpFormatter)
    parser.add_argument("--version", action="version", version=f"hrn-pyg {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, (module_name, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text, formatter_class=HelpFormatter)
        if name != command:
            continue
        arguments_module(name).add_arguments(p)
        p.set_defaults(_run=deferred_run(module_name))
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    if command in MOVED:
        print(f"hrn-pyg {command}: {MOVED[command]}", file=sys.stderr)
        return 2
    args = build_parser(command if command in COMMANDS else None).parse_args(argv)
    return run_reporting_errors(f"hrn-pyg {args.command}", args._run, args)


if __name__ == "__main__":
    sys.exit(main())
