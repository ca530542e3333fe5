"""``hrn-pyg evaluate``: Table 1 of the seed paper on held-out episodes.

Every model is rolled out from the same held-out initial states (the ``test`` split, disjoint by
seed from the training data) with the recorded external forces, feeding its own predictions
back. At the chosen horizons (default ``t+5`` and ``t+15``) three errors are measured against
pybullet's ground truth, over the moving leaves:

.. math::
    \\mathrm{MSE}_{pos} = \\frac{1}{3L}\\sum_l \\lVert \\hat x_l - x_l \\rVert^2, \\qquad
    \\mathrm{MSE}_{vel} = \\frac{1}{3L}\\sum_l \\lVert \\hat v_l - v_l \\rVert^2, \\qquad
    \\mathrm{MSE}_{shape} = \\frac{1}{P}\\sum_{o}\\sum_{i \\ne j \\in o}
        (\\lVert \\hat x_i - \\hat x_j \\rVert - \\lVert x_i - x_j \\rVert)^2

(velocities are per-step displacements, the shape error is the fully-connected pairwise-distance
error). Each trajectory gives one number per metric and horizon; the table shows their mean and
standard error. All test windows are rolled out together as one batched graph.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch_geometric.data import Batch
from torch_geometric.utils import scatter

from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.data.graph import NODE
from hrn_pyg.losses import full_shape_loss, shape_groups
from hrn_pyg.rollout import rollout
from hrn_pyg.train import load_model
from hrn_pyg.utils.files import atomic_write_json, atomic_write_text

METRICS = ("position", "velocity", "shape")
DEFAULT_HORIZONS = (5, 15)


def per_trajectory_errors(pred: Tensor, truth: Tensor, graph: Batch, prev_truth: Tensor,
                          prev_pred: Tensor) -> dict[str, Tensor]:
    """Position, velocity and shape error of each trajectory copy at one time.

    **Shapes:** ``pred``, ``truth``, ``prev_pred``, ``prev_truth`` ``[N, 3]`` (all nodes of the
    batched graph; ``prev_*`` one step earlier); returns ``{metric: [B]}``.
    """
    store = graph[NODE]
    moving_leaf = store.is_leaf & ~store.is_static
    batch = store.batch if "batch" in store else torch.zeros_like(store.object)
    copies = int(batch.max()) + 1
    b = batch[moving_leaf]
    pos_err = (pred - truth)[moving_leaf].pow(2).mean(-1)
    vel_err = ((pred - prev_pred) - (truth - prev_truth))[moving_leaf].pow(2).mean(-1)
    out = {
        "position": scatter(pos_err, b, dim=0, dim_size=copies, reduce="mean"),
        "velocity": scatter(vel_err, b, dim=0, dim_size=copies, reduce="mean"),
    }
    leaf_index, groups = shape_groups(graph)
    copy_of_leaf = batch[leaf_index]
    shape = torch.stack([  # one shape error per copy; a handful of copies, not particles
        full_shape_loss(pred[leaf_index][copy_of_leaf == c], truth[leaf_index][copy_of_leaf == c],
                        groups[copy_of_leaf == c])
        for c in range(copies)
    ])
    out["shape"] = shape
    return out


@torch.no_grad()
def evaluate_model(model, windows: list, horizons: tuple[int, ...]) -> dict[str, dict[int, np.ndarray]]:
    """Roll ``model`` out from every window (one batched graph); errors ``{metric: {h: [B]}}``."""
    graph = Batch.from_data_list(windows)
    store = graph[NODE]
    steps = max(horizons)
    forces = store.force_seq[:, :steps].transpose(0, 1)  # [steps, N, 3]
    pred = rollout(model, graph, steps, forces)  # [steps, N, 3]: x_{t+1..t+steps}
    truth = store.pos_seq.transpose(0, 1)  # [steps+3, N, 3]: x_{t-2..t+steps}
    result: dict[str, dict[int, np.ndarray]] = {m: {} for m in METRICS}
    for h in horizons:
        prev_pred = pred[h - 2] if h >= 2 else store.pos
        errors = per_trajectory_errors(pred[h - 1], truth[h + 2], graph, truth[h + 1], prev_pred)
        for m in METRICS:
            result[m][h] = errors[m].cpu().numpy()
    return result


def summarise(errors: dict[str, dict[int, np.ndarray]]) -> dict[str, dict[str, dict[str, float]]]:
    """Mean and standard error over trajectories of each metric and horizon."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    for m, by_h in errors.items():
        out[m] = {}
        for h, values in by_h.items():
            n = len(values)
            sem = float(values.std(ddof=1) / math.sqrt(n)) if n > 1 else float("nan")
            out[m][f"t+{h}"] = {"mean": float(values.mean()), "sem": sem, "n": n}
    return out


def markdown_table(summaries: dict[str, dict], horizons: tuple[int, ...], scene: str) -> str:
    """Table 1 layout: one row per model, position / velocity / shape MSE at each horizon."""
    head = "| scene | model | " + " | ".join(f"{m} MSE t+{h}" for m in METRICS for h in horizons) + " |"
    rule = "|" + "---|" * (2 + len(METRICS) * len(horizons))
    rows = [head, rule]
    for name, s in summaries.items():
        cells = [f"{s[m][f't+{h}']['mean']:.3g} ± {s[m][f't+{h}']['sem']:.2g}" for m in METRICS for h in horizons]
        rows.append(f"| {scene} | {name} | " + " | ".join(cells) + " |")
    return "\n".join(rows) + "\n"


def select_windows(dataset: EpisodeWindows, stride: int, limit: int | None) -> list:
    """Test windows whose start steps are ``stride`` apart within each episode."""
    chosen = []
    last_episode, last_start = -1, -10**9
    for idx in range(len(dataset)):
        episode, start = int(dataset._window_episode[idx]), int(dataset._window_start[idx])
        if episode != last_episode or start - last_start >= stride:
            chosen.append(idx)
            last_episode, last_start = episode, start
    if limit is not None:
        chosen = chosen[:limit]
    return [dataset[i] for i in chosen]


def comparison_figure(models: dict[str, Any], window, path: Path, times=(0, 5, 10, 15)) -> None:
    """Ground truth and each model on one test trajectory, side by side over time (Fig. 5)."""
    from hrn_pyg.viz import object_colors, rollout_grid

    graph = Batch.from_data_list([window])
    store = graph[NODE]
    steps = max(times)
    forces = store.force_seq[:, :steps].transpose(0, 1)
    leaves = store.is_leaf.nonzero().flatten()
    truth = store.pos_seq[:, 2:steps + 3].transpose(0, 1)[:, leaves].numpy()
    rows = {"ground truth": truth}
    for name, model in models.items():
        with torch.no_grad():
            pred = rollout(model, graph, steps, forces)
        rows[name] = torch.cat([store.pos[None], pred])[:, leaves].numpy()
    rollout_grid(rows, list(times), object_colors(store.object[leaves].numpy()), path)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, help="episode folder; its test split is used")
    parser.add_argument("--model", action="append", required=True, metavar="NAME=PATH",
                        help="a checkpoint to score, e.g. --model hrn=runs/hrn/model.pt (repeatable)")
    parser.add_argument("--out", required=True, help="folder for table.md, results.json and the figure")
    parser.add_argument("--horizons", default="5,15", help="comma-separated steps ahead (default 5,15)")
    parser.add_argument("--stride", type=int, default=10, help="steps between window starts in an episode")
    parser.add_argument("--limit", type=int, default=None, help="score at most this many trajectories")
    parser.add_argument("--split", default="test", choices=("test", "val"),
                        help="held-out split to score (val for model selection, test for reporting)")
    parser.add_argument("--no-figure", action="store_true")


def _parse_models(specs: list[str]) -> dict[str, str]:
    models = {}
    for spec in specs:
        name, sep, path = spec.partition("=")
        if not sep or not name or not path:
            raise ValueError(f"--model expects NAME=PATH, got {spec!r}")
        models[name] = path
    return models


def run(args: argparse.Namespace) -> int:
    horizons = tuple(int(h) for h in str(args.horizons).split(",") if h)
    if not horizons or min(horizons) < 1:
        raise ValueError(f"--horizons must be positive integers, got {args.horizons!r}")
    if args.stride < 1:
        raise ValueError(f"--stride must be >= 1, got {args.stride}")
    models = {name: load_model(path) for name, path in _parse_models(args.model).items()}
    dataset = EpisodeWindows(args.data, args.split, horizon=max(horizons))
    windows = select_windows(dataset, args.stride, args.limit)
    summaries = {name: summarise(evaluate_model(m, windows, horizons)) for name, m in models.items()}
    scene = Path(args.data).name
    table = markdown_table(summaries, horizons, scene)
    out = Path(args.out)
    atomic_write_text(out / "table.md", table)
    atomic_write_json(out / "results.json", {"scene": scene, "data": str(args.data), "split": args.split,
                                            "horizons": list(horizons),
                                            "trajectories": len(windows), "models": _parse_models(args.model),
                                            "results": summaries})
    if not args.no_figure:
        comparison_figure(models, windows[0], out / f"rollout_{scene}.png",
                          times=tuple(sorted({0, *horizons, max(horizons) // 2})))
    print(table, end="")
    print(f"{len(windows)} held-out trajectories ({args.split} split); written to {out}")
    return 0
