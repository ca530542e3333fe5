"""``hrn-pyg demo``: the two-minute tour on the shipped checkpoints.

A script of the package's own commands, so every picture can be redrawn by hand:

1. a short Table 1 (``hrn-pyg evaluate``) on held-out ``soft_bounce`` and ``cube_collision``
   episodes, HRN vs ours;
2. 16 futures (``hrn-pyg sample``) on the wedge and the soft cube, at each model's calibrated
   rate (0.3 if never calibrated): PNG and GIF each;
3. the shipped cube-push policy in the learned environment, replayed in pybullet.

Everything lands under one output folder; a step whose checkpoint is not shipped is skipped
with a note. ``--device`` and ``--no-progress`` are passed on.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from types import ModuleType

import hrn_pyg.evaluate as evaluate_command
import hrn_pyg.sampling.cli as sample_command
from hrn_pyg.checkpoints import CHECKPOINT_DIR
from hrn_pyg.commands.demo import add_arguments  # noqa: F401  the command's arguments, here too
from hrn_pyg.rl.showcase import showcase_policy
from hrn_pyg.utils.device import resolve_device
from hrn_pyg.utils.files import atomic_write_text
from hrn_pyg.utils.options import HelpFormatter

#: test-split seeds (seed % 10 == 9) used for the demo's held-out episodes, far from the
#: seeds of the shipped training data (0..199)
DEMO_SEEDS = (1009, 1019, 1029)
#: model steps simulated per demo episode
DEMO_STEPS = 40


def checkpoint_dir() -> Path:
    """The folder the demo takes its checkpoints from (the shipped ones)."""
    return CHECKPOINT_DIR


def _held_out_episodes(scene: str, folder: Path) -> Path:
    from hrn_pyg.data.episodes import simulate_episode
    from hrn_pyg.data.io import save_episode

    for seed in DEMO_SEEDS:
        path = folder / f"episode_{seed:06d}.npz"
        if not path.exists():
            save_episode(path, simulate_episode(scene, seed, steps=DEMO_STEPS))
    return folder


def run_command(name: str, module: ModuleType, argv: list[str]) -> int:
    """``hrn-pyg <name> <argv>`` run in this process: a parser from ``module.add_arguments``
    (the one the command line builds, renamed options included), then ``module.run``."""
    parser = argparse.ArgumentParser(prog=f"hrn-pyg {name}", formatter_class=HelpFormatter)
    module.add_arguments(parser)
    return int(module.run(parser.parse_args(argv)) or 0)


def _note(lines: list[str], text: str) -> None:
    print(text, flush=True)
    lines.append(text)


def run(args: argparse.Namespace) -> int:
    if args.k < 1:
        raise ValueError(f"--k must be >= 1, got {args.k}")
    device = resolve_device(args.device)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = checkpoint_dir()
    report: list[str] = ["# hrn-pyg demo", ""]
    quiet = ["--no-progress"] if getattr(args, "no_progress", False) else []
    started = time.perf_counter()

    # 1. Table 1 on held-out episodes -----------------------------------------------------------
    for scene in ("soft_bounce", "cube_collision"):
        hrn, ours = ckpt / f"{scene}_hrn.pt", ckpt / f"{scene}_ours.pt"
        if not (hrn.is_file() and ours.is_file()):
            _note(report, f"skipped Table 1 on {scene}: {hrn.name} / {ours.name} not shipped "
                          f"(make them with `hrn-pyg train`, see docs/results.md)")
            continue
        data = _held_out_episodes(scene, out / "data" / scene)
        code = run_command("evaluate", evaluate_command, ["--data", str(data), "--model", f"HRN={hrn}", "--model", f"ours={ours}",
                    "--out", str(out / "table1" / scene), "--stride", "100", *quiet, "--device", str(device)])
        if code:
            return code
        report += [(out / "table1" / scene / "table.md").read_text(), ""]

    # 2. sampled futures ------------------------------------------------------------------------
    for scene in ("wedge", "soft_bounce"):
        if not (ckpt / f"{scene}.pt").is_file():
            _note(report, f"skipped sampling on {scene}: {scene}.pt not shipped")
            continue
        target = out / "samples" / scene
        # no --rate: the model's calibrated rate (hrn-pyg calibrate), 0.3 if it was never calibrated
        code = run_command("sample", sample_command, ["--scene", scene, "--k", str(args.k), "--episode-seed", str(DEMO_SEEDS[0]),
                    "--horizon", "30", "--out", str(target), *quiet, "--device", str(device)])
        if code:
            return code
        meta = json.loads((target / "samples.json").read_text())
        _note(report, f"- {scene}: {target / 'samples.png'}, {target / 'samples.gif'} "
                      f"(rate {meta['rate']:g}, {meta['rate_source']})")

    # 3. a learned cube-push policy ---------------------------------------------------------------
    policy = ckpt / "cube_push_policy.pt"
    if policy.is_file() and (ckpt / "cube_push.pt").is_file():
        summary = showcase_policy(ckpt / "cube_push.pt", policy, out / "policy", device=device)
        _note(report, f"- cube_push policy: {summary}")
    else:
        _note(report, "skipped the cube-push policy: cube_push_policy.pt not shipped (see docs/rl.md)")

    seconds = time.perf_counter() - started
    report += ["", f"demo took {seconds:.0f} s"]
    atomic_write_text(out / "README.md", "\n".join(report) + "\n")
    print(f"\nhrn-pyg demo: done in {seconds:.0f} s; everything is under {out.resolve()}")
    return 0
