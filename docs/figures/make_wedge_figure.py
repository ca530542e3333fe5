"""The wedge figure of docs/sampling.md (the seed paper's Figs. 1 and 6, made readable).

Three panels, from one run of ``benchmarks/wedge_sides.py`` (its JSON) plus one episode
re-simulated for the paths:

(a) side view (x against height) of one ridge drop: the wedge as a solid, the ground, the
    ball-centre paths of the model's samples (blue) and of a 1 cm perturbed-start pybullet
    ensemble (black), their end points marked; the axes hold every path (nothing out of view);
(b) where the ball ends along x in that episode: samples against the ensemble (histograms);
(c) every episode of the JSON: the model's share of samples ending at x < 0 against the 2 mm
    and the 1 cm ensembles' shares; the diagonal is a perfect match.

Run: ``python -m docs.figures.make_wedge_figure --sides benchmarks/results/wedge_sides_val.json
[--seed 18] [--rate 0.5] [--out docs/figures/sampling_wedge_sides.png]``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from hrn_pyg.checkpoints import load_model
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import HISTORY, NODE
from hrn_pyg.sampling.ensemble import (
    PerturbationConfig,
    episode_state,
    ground_truth_ensemble,
)
from hrn_pyg.sampling.sample import sample
from benchmarks.sides import RIDGE_X, ball_centres, ridge_config
from hrn_pyg.viz import save_figure

HERE = Path(__file__).resolve().parent
SAMPLE_COLOR, TRUTH_COLOR, WEDGE_COLOR = "#1f77b4", "#222222", "#b8b8b8"


def wedge_outline(width: float, height: float) -> np.ndarray:
    """The wedge's cross-section in the x-z plane: a triangle with its ridge at x = 0."""
    return np.array([[-width / 2, 0.0], [0.0, height], [width / 2, 0.0]])


def paths(model, episode: dict, config, k: int, members: int, std: float, rate: float, seed: int):
    """Ball-centre paths ``[K, T, 3]`` of the samples and ``[M, T, 3]`` of the ensemble."""
    steps = config.config.steps - HISTORY
    graph = episode_state(episode, start=HISTORY, steps=steps)
    gen = torch.Generator().manual_seed(0)
    futures = sample(model, graph, k, steps, rate, forces=graph[NODE].force_seq.transpose(0, 1),
                     generator=gen)  # [K, T, L, 3]
    start = torch.as_tensor(episode["positions"][:HISTORY + 1]).float()
    futures = torch.cat([start.expand(k, -1, -1, -1), futures], dim=1)
    ens = torch.as_tensor(ground_truth_ensemble("wedge", seed, members, config.config.steps,
                                                PerturbationConfig(position_std=std), config)).float()
    obj, mass = episode["leaf_object"], episode["leaf_mass"]
    return ball_centres(futures, obj, mass).numpy(), ball_centres(ens, obj, mass).numpy()


def draw(sides: dict, seed: int, model_path: str, data: str, out: Path, members: int, std: float,
         rate: float | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    config = ridge_config(data)
    rate = float(sides["rates"][0] if rate is None else rate)
    if f"below@{rate:g}" not in sides["episodes"][0]:
        raise ValueError(f"--rate {rate:g} was not scored in the JSON (rates {sides['rates']})")
    episode = simulate_episode(config, seed)
    params = json.loads(str(episode["params"]))["params"]
    samples, ensemble = paths(load_model(model_path), episode, config, sides["k"], members, std, rate, seed)

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6), dpi=110, gridspec_kw={"width_ratios": [2.2, 1.2, 1]})
    ax = axes[0]
    ax.add_patch(plt.Polygon(wedge_outline(config.settings["wedge_width"], params["wedge_height"]), closed=True,
                             facecolor=WEDGE_COLOR, edgecolor="#707070", zorder=1, label="wedge"))
    for path in ensemble:
        ax.plot(path[:, 0], path[:, 2], color=TRUTH_COLOR, lw=0.8, alpha=0.5, zorder=2)
    for path in samples:
        ax.plot(path[:, 0], path[:, 2], color=SAMPLE_COLOR, lw=0.8, alpha=0.5, zorder=3)
    ax.scatter(ensemble[:, -1, 0], ensemble[:, -1, 2], s=14, color=TRUTH_COLOR, zorder=4,
               label=f"pybullet, {len(ensemble)} starts ±{1e3 * std:g} mm")
    ax.scatter(samples[:, -1, 0], samples[:, -1, 2], s=14, color=SAMPLE_COLOR, zorder=5,
               label=f"model, {len(samples)} samples at rate {rate:g}")
    xs = np.concatenate([samples[..., 0].ravel(), ensemble[..., 0].ravel(), [-config.settings["wedge_width"] / 2,
                                                                             config.settings["wedge_width"] / 2]])
    zs = np.concatenate([samples[..., 2].ravel(), ensemble[..., 2].ravel(), [0.0]])
    pad = 0.05 * (xs.max() - xs.min())
    ax.set_xlim(xs.min() - pad, xs.max() + pad)
    ax.set_ylim(min(-0.02, zs.min()), zs.max() + 0.05)
    ax.axhline(0, color="#707070", lw=1)
    ax.set_xlabel("x (m), across the ridge")
    ax.set_ylabel("height of the ball's centre (m)")
    ax.set_title(f"(a) {sides['split']} drop, seed {seed}: ball paths, side view")
    ax.legend(frameon=False, fontsize=8, loc="upper left")

    ax = axes[1]
    bins = np.linspace(xs.min() - pad, xs.max() + pad, 25)
    ax.hist(ensemble[:, -1, 0], bins=bins, color=TRUTH_COLOR, alpha=0.6, label="pybullet ensemble")
    ax.hist(samples[:, -1, 0], bins=bins, color=SAMPLE_COLOR, alpha=0.6, label="model samples")
    ax.axvline(RIDGE_X, color="#707070", ls=":", lw=1)
    ax.set_xlabel("final x of the ball (m)")
    ax.set_ylabel("trajectories")
    ax.set_title("(b) where the ball ends")
    ax.legend(frameon=False, fontsize=8)

    ax = axes[2]
    rows = sides["episodes"]
    key = f"below@{rate:g}"
    model_p = [r[key] for r in rows]
    ax.plot([0, 1], [0, 1], color="#999999", lw=1, ls="--")
    ax.scatter([r["fine_below"] for r in rows], model_p, s=22, color=SAMPLE_COLOR,
               label=f"vs ±{1e3 * sides['fine_std']:g} mm ensemble")
    ax.scatter([r["coarse_below"] for r in rows], model_p, s=22, marker="x", color="#d62728",
               label=f"vs ±{1e3 * sides['coarse_std']:g} mm ensemble")
    ax.set_xlim(-0.05, 1.05)
    ax.set_ylim(-0.05, 1.05)
    ax.set_xlabel("pybullet: share ending at x < 0")
    ax.set_ylabel("model: share of samples at x < 0")
    ax.set_title(f"(c) {len(rows)} {sides['split']} drops")
    ax.legend(frameon=False, fontsize=8, loc="lower right")
    fig.tight_layout()
    save_figure(fig, out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sides", default="benchmarks/results/wedge_sides_val.json",
                        help="JSON written by benchmarks/wedge_sides.py")
    parser.add_argument("--seed", type=int, default=None, help="episode drawn in (a) and (b) (default: the JSON's first)")
    parser.add_argument("--members", type=int, default=16)
    parser.add_argument("--std", type=float, default=0.01, help="start perturbation of the drawn ensemble (m)")
    parser.add_argument("--rate", type=float, default=None, help="one of the JSON's rates (default: its first)")
    parser.add_argument("--out", default=str(HERE / "sampling_wedge_sides.png"))
    args = parser.parse_args()
    sides = json.loads(Path(args.sides).read_text())
    seed = args.seed if args.seed is not None else sides["seeds"][0]
    draw(sides, seed, sides["model"], sides["data"], Path(args.out), args.members, args.std, args.rate)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
