"""How far a model is from the lattice's symmetries: f(g s) against g f(s) for the eight of them.

The voxel lattice, gravity and the ground are unchanged by the eight horizontal maps ``g`` that
exchange and negate x and y (the group ``d4`` of :data:`hrn_pyg.nn.hrn.MIRROR_GROUPS`: four turns
about the vertical axis, four mirrors). A simulator that has no preferred horizontal direction
predicts the turned future of a turned scene:

.. math::
    \\epsilon_g(h) = \\frac{1}{N} \\sum_i \\lVert f^h(g s)_i - g\\, f^h(s)_i \\rVert^2,

``f^h`` the model's rollout ``h`` steps from state ``s`` with the episode's own forces (turned
with the scene). A model averaged over the eight (``mirror_average`` with ``mirror_planes="d4"``)
has ``epsilon = 0`` up to rounding; a one-pass model has only what its training gave it. Beside
``epsilon`` the table gives the model's own position error against the ground truth at the same
horizon (MSE over leaves, the untransformed rollout), so the two read on one scale.

For every episode of ``--data`` (its ``--split``, at most ``--episodes``), windows from step 2
every ``--stride`` steps; every rollout is the network alone (no object sleeps), one torch
thread. Each ``--model`` is scored as loaded and, when it averages over mirrors, also as one pass
(the same weights, ``mirror_average`` off).

Run::

    python -m benchmarks.equivariance --model shapes --data data/unseen_val_rigid --split all \\
        --out benchmarks/results/equivariance_shapes.json

Prints a markdown table and writes JSON atomically.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from hrn_pyg.checkpoints import load_model, with_applied_options
from hrn_pyg.data.dataset import read_episode, split_of_seed
from hrn_pyg.data.graph import NODE
from hrn_pyg.data.symmetry import apply_vertical_symmetry
from hrn_pyg.nn.hrn import MIRROR_GROUPS, SWAP_XY, reflection_signs
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sim.rollout import rollout
from hrn_pyg.utils.files import atomic_write_json

HISTORY_START = 2


def lattice_symmetries() -> list[tuple[str, torch.Tensor]]:
    """The eight maps of ``d4`` as ``(name, [3, 3] matrix)``: x and y exchanged where the element
    holds :data:`SWAP_XY`, then the axes of :func:`~hrn_pyg.nn.hrn.reflection_signs` negated."""
    group = MIRROR_GROUPS["d4"]
    out = []
    for element, signs in zip(group, reflection_signs(group)):
        swap = SWAP_XY in element
        matrix = torch.diag(signs) @ (torch.eye(3)[[1, 0, 2]] if swap else torch.eye(3))
        name = " ".join((["swap"] if swap else []) + [f"-{'xyz'[a]}" for a in element if a != SWAP_XY])
        out.append((name or "identity", matrix))
    return out


def turned_rollout(model, state, steps: int, matrix: torch.Tensor) -> torch.Tensor:
    """``g^-1 f^h(g s)``: the rollout of the turned scene ``[steps, N, 3]``, turned back."""
    turned = apply_vertical_symmetry(state, matrix[None])
    forces = turned[NODE].force_seq[:, :steps].transpose(0, 1)
    with torch.no_grad():
        pos = rollout(model, turned, steps, forces=forces, sleep=None)
    return pos @ matrix  # rows are vectors: v g^-T = g^-1 v for an orthogonal g


def equivariance_errors(model, state, horizons: list[int]) -> dict:
    """Per symmetry (not the identity) and horizon, ``epsilon`` over the leaves; and the model's
    own position MSE against the ground truth at each horizon."""
    steps = max(horizons)
    leaf = state[NODE].is_leaf
    plain = turned_rollout(model, state, steps, torch.eye(3))
    truth = state[NODE].pos_seq[:, 3:3 + steps].transpose(0, 1)
    out = {"truth_mse": {h: float(((plain[h - 1] - truth[h - 1]) ** 2).sum(-1)[leaf].mean()) for h in horizons},
           "symmetries": {}}
    for name, matrix in lattice_symmetries()[1:]:
        back = turned_rollout(model, state, steps, matrix)
        out["symmetries"][name] = {h: float(((back[h - 1] - plain[h - 1]) ** 2).sum(-1)[leaf].mean())
                                   for h in horizons}
    return out


def episode_files(folder: Path, split: str, limit: int | None) -> list[Path]:
    files = sorted(folder.glob("episode_*.npz"))
    if split != "all":
        files = [f for f in files if split_of_seed(int(f.stem.split("_")[1])) == split]
    return files[:limit] if limit else files


def variants_of(name: str) -> dict:
    """The model as loaded and, when it averages over mirrors, its weights in one pass."""
    model = load_model(name).eval()
    out = {"as loaded": model}
    if getattr(model.config, "mirror_average", False):
        out["one pass"] = with_applied_options(model, mirror_average=False)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", action="append", default=None, help="shipped name or path (repeatable; default shapes)")
    parser.add_argument("--data", action="append", required=True, type=Path, help="an episode folder (repeatable)")
    parser.add_argument("--split", choices=("train", "val", "test", "all"), default="val")
    parser.add_argument("--episodes", type=int, default=4, help="at most this many episodes per folder")
    parser.add_argument("--stride", type=int, default=50, help="steps between window starts")
    parser.add_argument("--horizons", default="1,15")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    horizons = sorted({int(h) for h in args.horizons.split(",") if h})
    if not horizons or horizons[0] < 1 or args.stride < 1 or args.episodes < 1:
        parser.error("--horizons must be >= 1, --stride and --episodes >= 1")
    torch.set_num_threads(args.threads)
    states = []
    for folder in args.data:
        files = episode_files(folder, args.split, args.episodes)
        if not files:
            parser.error(f"no {args.split} episodes in {folder}")
        for path in files:
            episode = read_episode(path)
            total = episode["positions"].shape[0] - 1
            for start in range(HISTORY_START, total - max(horizons) + 1, args.stride):
                states.append((f"{folder.name}/{path.stem}@{start}", episode_state(episode, start, max(horizons))))
    rows = []
    for name in args.model or ["shapes"]:
        for label, model in variants_of(name).items():
            per_window = [equivariance_errors(model, state, horizons) for _, state in states]
            row = {"model": name, "variant": label, "windows": len(states), "horizons": {}}
            for h in horizons:
                eps = [w["symmetries"][g][h] for w in per_window for g in w["symmetries"]]
                truth = [w["truth_mse"][h] for w in per_window]
                row["horizons"][h] = {"epsilon_mean": sum(eps) / len(eps), "epsilon_max": max(eps),
                                      "truth_mse": sum(truth) / len(truth),
                                      "epsilon_over_truth": (sum(eps) / len(eps)) / max(sum(truth) / len(truth), 1e-30)}
            rows.append(row)
            print(f"{name} {label}: " + "; ".join(
                f"t+{h} epsilon {r['epsilon_mean']:.2e} (max {r['epsilon_max']:.2e}), truth {r['truth_mse']:.2e}"
                for h, r in row["horizons"].items()), file=sys.stderr, flush=True)
    header = "| model | variant | windows | " + " | ".join(
        f"epsilon t+{h} (m², mean / max) | error t+{h} (m²) | epsilon / error t+{h}" for h in horizons) + " |"
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for row in rows:
        cells = [f"{r['epsilon_mean']:.2e} / {r['epsilon_max']:.2e} | {r['truth_mse']:.2e} | {r['epsilon_over_truth']:.3f}"
                 for r in row["horizons"].values()]
        print(f"| {row['model']} | {row['variant']} | {row['windows']} | " + " | ".join(cells) + " |")
    if args.out:
        atomic_write_json(args.out, {"data": [str(d) for d in args.data], "split": args.split, "stride": args.stride,
                                     "episodes": args.episodes, "threads": args.threads,
                                     "symmetries": [n for n, _ in lattice_symmetries()], "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
