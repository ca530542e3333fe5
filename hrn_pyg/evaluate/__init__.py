r"""``hrn-pyg evaluate``: Table 1 of the seed paper on held-out episodes.

Every model is rolled out from the same held-out initial states (the ``test`` split) with the
recorded external forces, feeding its own predictions back. At the chosen horizons (default
``t+5`` and ``t+15``) three errors are measured against pybullet over the moving leaves:

.. math::
    \mathrm{MSE}_{pos} = \frac{1}{3L}\sum_l \lVert \hat x_l - x_l \rVert^2, \qquad
    \mathrm{MSE}_{vel} = \frac{1}{3L}\sum_l \lVert \hat v_l - v_l \rVert^2, \qquad
    \mathrm{MSE}_{shape} = \frac{1}{P}\sum_{o}\sum_{i \ne j \in o}
        (\lVert \hat x_i - \hat x_j \rVert - \lVert x_i - x_j \rVert)^2

(velocities are per-step displacements). The table shows the mean and standard error over
trajectories, all rolled out as one batched graph. A rollout that leaves the finite numbers is
isolated (:func:`guarded_rollout`), NaN from its failing step on and counted as ``diverged``.

**Long rollouts**: one rollout per held-out episode from ``t = 2`` to its end, read at the long
horizons (default ``t+50``, ``t+100``; past an episode's end at the end, e.g. ``t+47 (end)``),
plus the rest metrics of :mod:`hrn_pyg.evaluate.rest`.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch_geometric.data import Batch, HeteroData
from torch_geometric.utils import scatter

from hrn_pyg.checkpoints import load_model, with_applied_options
from hrn_pyg.checkpoints.domain import dataset_domain, report_outside
from hrn_pyg.commands.evaluate import DEFAULT_LONG_HORIZONS, add_arguments  # noqa: F401  the command's arguments, here too
from hrn_pyg.data.dataset import EpisodeWindows, episode_steps
from hrn_pyg.data.graph import HISTORY, NODE, copy_object_ids, object_span
from hrn_pyg.losses import full_shape_loss, shape_groups
from hrn_pyg.evaluate.rest import REST_SPEED, REST_STEPS, rest_metrics
from hrn_pyg.sim.rollout import iterate, rollout
from hrn_pyg.sim.step import NEXT_POS
from hrn_pyg.utils.device import resolve_device
from hrn_pyg.utils.files import atomic_write_json, atomic_write_text
from hrn_pyg.utils.options import progress_bar

METRICS = ("position", "velocity", "shape")
#: The rest metrics of each model, in table order.
REST_METRICS = ("ground_depth", "rest_height_error", "rest_drift")


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


def _diverged(err: ValueError) -> bool:
    """Whether ``err`` is the error of a rollout step whose positions left the finite numbers."""
    return str(err).startswith(NEXT_POS)


@torch.no_grad()
def guarded_rollout(model, windows: list, steps: int, device: torch.device | str = "cpu",
                    graph: Batch | None = None) -> tuple[Tensor, np.ndarray]:
    """Roll ``windows`` out ``steps`` steps with their recorded forces, surviving divergence.

    One batched graph; on a non-finite step the batch is halved and rolled again, down to the
    window that diverged. Returns the positions ``[steps, N, 3]`` (windows in
    :meth:`Batch.from_data_list`'s order), NaN for a diverged window from its failing step on, and
    each window's 1-based failing step, 0 for none (``[E]`` int). ``graph``: the windows already
    batched on ``device``, if the caller has them.
    """
    graph = Batch.from_data_list(windows).to(device) if graph is None else graph
    forces = graph[NODE].force_seq[:, :steps].transpose(0, 1)
    try:
        return rollout(model, graph, steps, forces, sleep=None), np.zeros(len(windows), dtype=np.int64)
    except ValueError as err:
        if not _diverged(err):
            raise
    if len(windows) > 1:
        half = len(windows) // 2
        first, at_first = guarded_rollout(model, windows[:half], steps, device)
        second, at_second = guarded_rollout(model, windows[half:], steps, device)
        return torch.cat([first, second], dim=1), np.concatenate([at_first, at_second])
    pred = torch.full((steps, graph[NODE].num_nodes, 3), float("nan"), device=graph[NODE].pos.device)
    done = 0
    try:
        for done, result in enumerate(iterate(model, graph, steps, forces, sleep=None), start=1):
            pred[done - 1] = result.pos
    except ValueError as err:
        if not _diverged(err):
            raise
    return pred, np.array([done + 1], dtype=np.int64)  # steps 1..done were finite


@torch.no_grad()
def evaluate_model(model, windows: list, horizons: tuple[int, ...],
                   device: torch.device | str = "cpu") -> dict[str, dict[int, np.ndarray]]:
    """Roll ``model`` (on ``device``) out from every window; errors ``{metric: {h: [B]}}`` on the CPU,
    NaN past a divergence (:func:`guarded_rollout`)."""
    graph = Batch.from_data_list(windows).to(device)
    store = graph[NODE]
    steps = max(horizons)
    pred, _ = guarded_rollout(model, windows, steps, device, graph)  # [steps, N, 3]: x_{t+1..t+steps}; the network alone
    truth = store.pos_seq.transpose(0, 1)  # [steps+3, N, 3]: x_{t-2..t+steps}
    result: dict[str, dict[int, np.ndarray]] = {m: {} for m in METRICS}
    for h in horizons:
        prev_pred = pred[h - 2] if h >= 2 else store.pos
        errors = per_trajectory_errors(pred[h - 1], truth[h + 2], graph, truth[h + 1], prev_pred)
        for m in METRICS:
            result[m][h] = errors[m].cpu().numpy()
    return result


def summarise(errors: dict[str, dict[int, np.ndarray]]) -> dict[str, dict[str, dict[str, float]]]:
    """Mean and standard error over the finite values of each metric and horizon; ``n`` counts them,
    ``diverged`` the NaN ones."""
    return {m: {f"t+{h}": _mean_sem(values) for h, values in by_h.items()} for m, by_h in errors.items()}


def markdown_table(summaries: dict[str, dict], horizons: tuple[int, ...], scene: str) -> str:
    """Table 1 layout: one row per model, position / velocity / shape MSE at each horizon."""
    head = "| scene | model | " + " | ".join(f"{m} MSE t+{h}" for m in METRICS for h in horizons) + " |"
    rule = "|" + "---|" * (2 + len(METRICS) * len(horizons))
    rows = [head, rule]
    for name, s in summaries.items():
        cells = [_cell(s[m][f"t+{h}"]) for m in METRICS for h in horizons]
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


def episode_start_windows(data: str | Path, split: str, limit: int | None = None) -> list[HeteroData]:
    """One window per episode of ``split``, from ``t = 2`` to its end (horizon ``T_e = S_e - 2``);
    episodes under 3 steps skipped, at most ``limit``, in seed order.

    **Shapes:** window ``e`` holds ``pos_seq`` ``[N_e, S_e + 1, 3]`` and ``force_seq``
    ``[N_e, S_e - 2, 3]``.
    """
    probe = EpisodeWindows(data, split, horizon=1)
    lengths = [episode_steps(path) - HISTORY for path in probe.paths]
    chosen = [(episode, length) for episode, length in enumerate(lengths) if length >= 1][:limit]
    datasets: dict[int, EpisodeWindows] = {1: probe}
    windows = []
    for episode, length in chosen:  # one window per episode
        if length not in datasets:
            datasets[length] = EpisodeWindows(data, split, horizon=length)
        ds = datasets[length]
        index = np.flatnonzero((ds._window_episode == episode) & (ds._window_start == HISTORY))
        windows.append(ds[int(index[0])])
    return windows


@torch.no_grad()
def evaluate_long(model, windows: list, horizons: tuple[int, ...],
                  device: torch.device | str = "cpu") -> dict[str, Any]:
    """Roll ``model`` (on ``device``) over whole-episode windows (:func:`episode_start_windows`, equal
    lengths batched) and score them: horizon ``h`` read at step ``min(h, T_e)``, the rest metrics
    (:func:`hrn_pyg.evaluate.rest.rest_metrics`) over the whole rollout.

    **Shapes** (``E`` windows, ``R`` objects at rest at the end of the truth): returns ``errors``
    ``{metric: {h: [E]}}``, ``steps`` ``{h: [E]}``, ``ground_depth`` and ``truth_ground_depth``
    ``[E]``, ``rest_height_error`` and ``rest_drift`` ``[R]``, ``diverged_at`` ``[E]`` (0 for none).
    """
    lengths = np.array([int(w[NODE].force_seq.shape[1]) for w in windows])
    count = len(windows)
    errors = {m: {h: np.empty(count) for h in horizons} for m in METRICS}
    depth, truth_depth = np.empty(count), np.empty(count)
    diverged_at = np.zeros(count, dtype=np.int64)
    height: list[np.ndarray] = []
    drift: list[np.ndarray] = []
    for length in np.unique(lengths).tolist():  # one batched rollout per distinct episode length
        members = np.flatnonzero(lengths == length)
        group = [windows[i] for i in members]
        graph = Batch.from_data_list(group).to(device)
        store = graph[NODE]
        steps, diverged_at[members] = guarded_rollout(model, group, length, device, graph)
        pred = torch.cat([store.pos[None], steps])  # [T+1, N, 3]: x_2..x_S
        truth = store.pos_seq[:, HISTORY:].transpose(0, 1)  # [T+1, N, 3]: x_2..x_S
        for h in horizons:
            s = min(h, length)
            err = per_trajectory_errors(pred[s], truth[s], graph, truth[s - 1], pred[s - 1])
            for m in METRICS:
                errors[m][h][members] = err[m].cpu().numpy()
        leaf = store.is_leaf.nonzero().flatten()
        copy = store.batch[leaf]
        n_obj = object_span(store.object)
        rest = rest_metrics(pred[:, leaf], truth[:, leaf], copy_object_ids(copy, store.object[leaf], n_obj),
                            ~store.is_static[leaf], copy, num_objects=len(members) * n_obj,
                            num_groups=len(members), mass=store.mass[leaf, 0])
        depth[members] = np.where(diverged_at[members] > 0, np.nan, rest.depth.cpu().numpy())
        truth_depth[members] = rest.truth_depth.cpu().numpy()
        height.append(rest.height_error[rest.at_rest].cpu().numpy())
        drift.append(rest.drift[rest.at_rest].cpu().numpy())
    return {
        "errors": errors,
        "steps": {h: np.minimum(h, lengths) for h in horizons},
        "ground_depth": depth,
        "truth_ground_depth": truth_depth,
        "rest_height_error": np.concatenate(height) if height else np.empty(0),
        "rest_drift": np.concatenate(drift) if drift else np.empty(0),
        "diverged_at": diverged_at,
    }


def horizon_label(horizon: int, steps: np.ndarray) -> str:
    """Header of a long horizon read at ``steps``: ``t+50``, ``t+47 (end)`` when all end earlier at
    one step, ``t+40..50 (end)`` when some end earlier."""
    lo, hi = int(steps.min()), int(steps.max())
    if lo == hi == horizon:
        return f"t+{horizon}"
    if lo == hi:
        return f"t+{lo} (end)"
    return f"t+{lo}..{hi} (end)"


def _mean_sem(values: np.ndarray) -> dict[str, float]:
    """Mean, standard error and count of the finite values of a sample (NaN where undefined),
    and ``diverged``: how many were not finite."""
    values = np.asarray(values, dtype=np.float64)
    finite = values[np.isfinite(values)]
    n = len(finite)
    mean = float(finite.mean()) if n else float("nan")
    sem = float(finite.std(ddof=1) / math.sqrt(n)) if n > 1 else float("nan")
    return {"mean": mean, "sem": sem, "n": n, "diverged": len(values) - n}


def summarise_long(result: dict[str, Any]) -> dict[str, dict]:
    """Mean ± standard error of :func:`evaluate_long`'s output: ``{"long": {metric: {"t+h": {mean,
    sem, n, label, step_min, step_max}}}, "rest": {name: {mean, sem, n[, max]}}}``."""
    long: dict[str, dict[str, dict]] = {}
    for m, by_h in result["errors"].items():
        long[m] = {}
        for h, values in by_h.items():
            steps = result["steps"][h]
            long[m][f"t+{h}"] = {**_mean_sem(values), "label": horizon_label(h, steps),
                                 "step_min": int(steps.min()), "step_max": int(steps.max())}
    depth = result["ground_depth"]
    rest = {
        "ground_depth": {**_mean_sem(depth), "max": float(np.nanmax(depth)) if np.isfinite(depth).any() else float("nan")},
        "rest_height_error": _mean_sem(result["rest_height_error"]),
        "rest_drift": _mean_sem(result["rest_drift"]),
    }
    return {"long": long, "rest": rest}


def _cell(stats: dict[str, float], count: bool = False) -> str:
    diverged = f" ({stats['diverged']} diverged)" if stats.get("diverged") else ""
    if stats["n"] == 0:
        return ("n/a (no object at rest)" if count else "n/a") + diverged
    text = f"{stats['mean']:.3g} ± {stats['sem']:.2g}"
    return (f"{text} (n={stats['n']})" if count else text) + diverged


def long_table(summaries: dict[str, dict], scene: str) -> str:
    """Long rollouts, one row per model (:func:`summarise_long`): the MSEs at each distinct long
    horizon, then the lowest leaf below the ground and the rest height error and drift."""
    first = next(iter(summaries.values()))["long"]
    columns: dict[str, str] = {}  # label -> "t+h" key, first horizon per label
    for key, stats in first[METRICS[0]].items():
        columns.setdefault(stats["label"], key)
    head = ("| scene | model | " + " | ".join(f"{m} MSE {label}" for m in METRICS for label in columns)
            + (" | " if columns else "") + "below ground (m) | rest height error (m) | rest drift (m) |")
    rule = "|" + "---|" * (2 + len(METRICS) * len(columns) + len(REST_METRICS))
    rows = [head, rule]
    for name, s in summaries.items():
        cells = [_cell(s["long"][m][key]) for m in METRICS for key in columns.values()]
        cells += [_cell(s["rest"]["ground_depth"]), _cell(s["rest"]["rest_height_error"], count=True),
                  _cell(s["rest"]["rest_drift"], count=True)]
        rows.append(f"| {scene} | {name} | " + " | ".join(cells) + " |")
    return "\n".join(rows) + "\n"


def comparison_figure(models: dict[str, Any], window, path: Path, times=(0, 5, 10, 15),
                      device: torch.device | str = "cpu") -> None:
    """Ground truth and each model on one test trajectory, side by side over time (Fig. 5)."""
    from hrn_pyg.viz import object_colors, rollout_grid

    graph = Batch.from_data_list([window]).to(device)
    store = graph[NODE]
    steps = max(times)
    forces = store.force_seq[:, :steps].transpose(0, 1)
    leaves = store.is_leaf.nonzero().flatten()
    truth = store.pos_seq[:, 2:steps + 3].transpose(0, 1)[:, leaves].cpu().numpy()
    rows = {"ground truth": truth}
    for name, model in models.items():
        with torch.no_grad():
            pred = rollout(model, graph, steps, forces, sleep=None)
        rows[name] = torch.cat([store.pos[None], pred])[:, leaves].cpu().numpy()
    rollout_grid(rows, list(times), object_colors(store.object[leaves].cpu().numpy()), path)


def _parse_models(specs: list[str]) -> dict[str, str]:
    models = {}
    for spec in specs:
        name, sep, path = spec.partition("=")
        if not sep and name:  # a shipped model by its name: labelled with it
            name, path = Path(name).stem, name
        if not name or not path:
            raise ValueError(f"--model expects NAME=PATH or a shipped model's name, got {spec!r}")
        models[name] = path
    return models


def _parse_horizons(text: str, option: str, allow_empty: bool = False) -> tuple[int, ...]:
    try:
        horizons = tuple(int(h) for h in str(text).split(",") if h.strip())
    except ValueError:
        raise ValueError(f"{option} must be comma-separated positive integers, got {text!r}") from None
    if (not horizons and not allow_empty) or (horizons and min(horizons) < 1):
        raise ValueError(f"{option} must be positive integers, got {text!r}")
    return horizons


def run(args: argparse.Namespace) -> int:
    device = resolve_device(getattr(args, "device", None))
    horizons = _parse_horizons(args.horizons, "--horizons")
    long_horizons = _parse_horizons(getattr(args, "long_horizons", ""), "--long-horizons", allow_empty=True)
    if args.stride < 1:
        raise ValueError(f"--stride must be >= 1, got {args.stride}")
    models = {name: load_model(path).to(device) for name, path in _parse_models(args.model).items()}
    for name in getattr(args, "rigid_fit", None) or []:
        if name not in models:
            raise ValueError(f"--rigid-fit {name}: no --model of that name (models: {', '.join(models)})")
        models[name] = with_applied_options(models[name], rigid_fit=True)
    dataset = EpisodeWindows(args.data, args.split, horizon=max(horizons))
    data_domain = dataset_domain(args.data)
    for model in models.values():
        report_outside(model, data_domain, strict=getattr(args, "strict", False), prefix="hrn-pyg evaluate: warning: ")
    windows = select_windows(dataset, args.stride, args.limit)
    starts = episode_start_windows(args.data, args.split, args.limit)
    bar = progress_bar(2 * len(models), "evaluate", "rollout", enabled=not getattr(args, "no_progress", False))
    summaries, long_results = {}, {}
    for name, m in models.items():
        bar.set_postfix_str(f"{name}: {len(windows)} windows")
        summaries[name] = summarise(evaluate_model(m, windows, horizons, device))
        bar.update()
        bar.set_postfix_str(f"{name}: {len(starts)} whole episodes")
        long_results[name] = evaluate_long(m, starts, long_horizons, device)
        bar.update()
    bar.close()
    long_summaries = {name: summarise_long(r) for name, r in long_results.items()}
    truth_depth = _mean_sem(next(iter(long_results.values()))["truth_ground_depth"])
    scene = Path(args.data).name
    caption = (f"Long rollouts: {len(starts)} episode{'s' if len(starts) != 1 else ''}, each rolled out from "
               f"t=2 to its end; rest = every "
               f"leaf moved < {REST_SPEED * 1e3:g} mm/step over the last {REST_STEPS} steps of the ground "
               f"truth; ground truth below ground: {truth_depth['mean']:.3g} m.")
    table = markdown_table(summaries, horizons, scene) + "\n" + caption + "\n\n" + long_table(long_summaries, scene)
    out = Path(args.out) if args.out else Path("runs") / "evaluate" / scene
    atomic_write_text(out / "table.md", table)
    atomic_write_json(out / "results.json", {
        "scene": scene, "data": str(args.data), "split": args.split, "device": str(device),
        "horizons": list(horizons), "trajectories": len(windows), "models": _parse_models(args.model),
        "results": summaries,
        "long_horizons": list(long_horizons), "long_trajectories": len(starts),
        "long_results": {name: s["long"] for name, s in long_summaries.items()},
        "rest": {name: s["rest"] for name, s in long_summaries.items()},
        "rest_truth": {"ground_depth": truth_depth},
        "long_diverged": {name: int((r["diverged_at"] > 0).sum()) for name, r in long_results.items()},
        "rest_definition": {"speed_m_per_step": REST_SPEED, "steps": REST_STEPS},
    })
    if not args.no_figure:
        comparison_figure(models, windows[0], out / f"rollout_{scene}.png",
                          times=tuple(sorted({0, *horizons, max(horizons) // 2})), device=device)
    print(table, end="")
    print(f"{len(windows)} held-out trajectories and {len(starts)} whole episode{'s' if len(starts) != 1 else ''} "
          f"({args.split} split, {device}); written to {out}")
    return 0
