"""The ``hrn-pyg`` command: one entry point, one sub-command per job.

Each sub-command lives in the module that does the work; that module exposes
``add_arguments(parser)`` and ``run(args) -> int``. A sub-command may have further jobs, named
right after it (``hrn-pyg rl clone ...``, :data:`JOBS`), each in its own module the same way. Bad input raises ``ValueError`` (or
``FileNotFoundError``) with a message naming the problem; here it becomes one line on stderr
and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from hrn_pyg.version import __version__

#: sub-command -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "generate": ("hrn_pyg.data.generate", "simulate a scene in pybullet and write episodes"),
    "train": ("hrn_pyg.train", "train an HRN (presets: hrn, ours) or the GNS baseline (preset gns)"),
    "evaluate": ("hrn_pyg.evaluate", "Table 1: rollout errors of HRN vs ours on the test split"),
    "sample": ("hrn_pyg.sampling.cli", "sample K futures with Monte Carlo dropout"),
    "calibrate": ("hrn_pyg.sampling.calibrate",
                  "choose a model's sampling rate so its spread matches a validation ensemble"),
    "rl": ("hrn_pyg.rl.ppo", "train a PPO agent in the learned environment"),
    "demo": ("hrn_pyg.demo", "the two-minute tour on the shipped checkpoints"),
    "checkpoints": ("hrn_pyg.recipe", "remake the shipped checkpoints from data/recipes.toml"),
    "models": ("hrn_pyg.checkpoints.cli", "list the shipped models and what each was trained on"),
}

#: jobs under a sub-command, ``hrn-pyg <command> <job> ...``: command -> job -> (module, one-line help)
JOBS: dict[str, dict[str, tuple[str, str]]] = {
    "rl": {"clone": ("hrn_pyg.rl.clone", "clone a task's scripted planner into a PPO actor "
                     "(the initial policy of --init-policy)"),
           "summary": ("hrn_pyg.rl.summary", "the statistics of a sweep's runs so far "
                       "(rl_<task>_summary.json and a table)")},
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``command``'s module is imported (the others load torchrl, pybullet, ...)."""
    parser = argparse.ArgumentParser(prog="hrn-pyg", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"hrn-pyg {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, (module_name, help_text) in COMMANDS.items():
        jobs = JOBS.get(name, {})
        epilog = "; ".join(f"`hrn-pyg {name} {job} --help`: {text}" for job, (_, text) in jobs.items())
        p = sub.add_parser(name, help=help_text, epilog=epilog or None)
        if name != command:
            continue
        module = importlib.import_module(module_name)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def build_job_parser(command: str, job: str) -> argparse.ArgumentParser:
    """The parser of ``hrn-pyg <command> <job>`` (:data:`JOBS`)."""
    module_name, help_text = JOBS[command][job]
    parser = argparse.ArgumentParser(prog=f"hrn-pyg {command} {job}", description=help_text)
    module = importlib.import_module(module_name)
    module.add_arguments(parser)
    parser.set_defaults(_run=module.run, command=f"{command} {job}")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if len(argv) >= 2 and argv[1] in JOBS.get(argv[0], {}):
        args = build_job_parser(argv[0], argv[1]).parse_args(argv[2:])
    else:
        command = next((a for a in argv if not a.startswith("-")), None)
        args = build_parser(command if command in COMMANDS else None).parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except (ValueError, FileNotFoundError) as exc:
        print(f"hrn-pyg {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"hrn-pyg {args.command}: interrupted; finished work is kept", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
