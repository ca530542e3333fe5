"""How wide are the sampled futures? Spread of the root positions over k samples against time,
for several dropout rates (the seed paper's supplement, Fig. 10 and 11).

* Fig. 10: ``soft_bounce``, dropout on the force module, rates 0.1, 0.3, 0.5;
* Fig. 11: ``tower``, dropout on the force and collision modules, rates 0.1, 0.3.

For each rate, :func:`hrn_pyg.sampling.sample` draws k futures of one test episode's start
state (the same masks seed for every rate) and :func:`hrn_pyg.sampling.metrics.root_spread`
gives, per time step and per object, the root-mean-square distance of the object's root (its
mass-weighted centre) from the samples' mean. The plot shows the mean over the moving objects.

Run: ``python -m benchmarks.sampling_spread [--soft-model PATH] [--tower-model PATH] [--k 16]
[--steps 30] [--seed 9] [--out benchmarks/results/sampling_spread]`` (checkpoints default to
``hrn_pyg/checkpoints/<scene>.pt``). ``--random-init`` runs untrained models: a pipeline check
whose numbers mean nothing. Writes ``<out>.json`` and ``<out>.png`` atomically.
"""

from __future__ import annotations

import argparse
import os
import platform

import numpy as np
import torch

from benchmarks.common import model_for, object_centres
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import HISTORY, NODE
from hrn_pyg.nn.hrn import HRN
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sampling.metrics import root_spread
from hrn_pyg.sampling.sample import sample
from hrn_pyg.utils.files import atomic_write_json
from hrn_pyg.viz import save_figure

#: (figure, scene, masked modules, rates), as in the seed paper's supplement
STUDIES = (
    ("fig10", "soft_bounce", ("force",), (0.1, 0.3, 0.5)),
    ("fig11", "tower", ("force", "collision"), (0.1, 0.3)),
)


def spread_against_rate(
    model: HRN, episode: dict, rates: tuple[float, ...], modules: tuple[str, ...], k: int, steps: int, seed: int
) -> dict[float, np.ndarray]:
    """``{rate: spread [steps, O]}`` of k samples from step ``HISTORY`` of ``episode``."""
    graph = episode_state(episode, start=HISTORY, steps=steps)
    forces = graph[NODE].force_seq.transpose(0, 1)
    leaf_object = torch.as_tensor(episode["leaf_object"])
    leaf_mass = torch.as_tensor(episode["leaf_mass"])
    out = {}
    for rate in rates:  # a handful of rates; each is one batched rollout of k copies
        gen = torch.Generator().manual_seed(seed)
        futures = sample(model, graph, k, steps, rate, forces=forces, generator=gen, modules=modules)
        out[rate] = root_spread(object_centres(futures, leaf_object, leaf_mass)).numpy()  # [steps, O]
    return out


def plot(results: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(5 * len(results), 3.4), dpi=100, squeeze=False)
    for ax, (name, study) in zip(axes[0], results.items()):
        moving = np.asarray(study["moving_objects"])
        for rate, spread in study["spread_m"].items():
            curve = np.asarray(spread)[:, moving].mean(axis=1)
            ax.plot(np.arange(1, len(curve) + 1), 100 * curve, label=f"rate {rate}")
        ax.set_title(f"{name}: {study['scene']}, dropout on {'+'.join(study['modules'])}", fontsize=9)
        ax.set_xlabel("predicted step")
        ax.set_ylabel("root spread over samples (cm)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--soft-model", default=None)
    parser.add_argument("--tower-model", default=None)
    parser.add_argument("--k", type=int, default=16)
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--seed", type=int, default=9, help="episode seed (a test-split seed: seed %% 10 == 9)")
    parser.add_argument("--sample-seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--random-init", action="store_true", help="untrained models: pipeline check only")
    parser.add_argument("--out", default="benchmarks/results/sampling_spread")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    paths = {"soft_bounce": args.soft_model, "tower": args.tower_model}
    results = {}
    for name, scene, modules, rates in STUDIES:
        episode = simulate_episode(scene, args.seed, steps=HISTORY + args.steps)
        model = model_for(scene, paths[scene], args.random_init, episode_state(episode, HISTORY, args.steps))
        spread = spread_against_rate(model, episode, rates, modules, args.k, args.steps, args.sample_seed)
        moving = [int(o) for o, m in enumerate(episode["object_material"]) if m != 3]
        results[name] = {
            "scene": scene, "modules": list(modules), "episode_seed": args.seed,
            "moving_objects": moving, "spread_m": {str(r): s.tolist() for r, s in spread.items()},
        }
        print(f"\n{name} ({scene}, dropout on {'+'.join(modules)}), k={args.k}: "
              "root spread (cm, mean over moving objects)")
        marks = sorted({max(1, args.steps // 4), args.steps // 2, args.steps})
        print("| rate | " + " | ".join(f"t+{t}" for t in marks) + " |")
        print("|---:|" + "---:|" * len(marks))
        for rate, s in spread.items():
            curve = s[:, moving].mean(axis=1)
            print(f"| {rate} | " + " | ".join(f"{100 * curve[t - 1]:.2f}" for t in marks) + " |")
    meta = {
        "what": "spread of root positions over k dropout samples against time (seed paper Fig. 10/11)",
        "k": args.k, "steps": args.steps, "sample_seed": args.sample_seed,
        "random_init": args.random_init,
        "models": {s: (None if args.random_init else str(p or f"hrn_pyg/checkpoints/{s}.pt")) for s, p in paths.items()},
        "spread_definition": "sqrt(mean_k ||r_k - mean_k r||^2) of each object's mass-weighted centre, metres",
        "machine": {"cpu": platform.machine(), "cpus": os.cpu_count(), "torch_threads": args.threads},
        "studies": results,
    }
    atomic_write_json(args.out + ".json", meta)
    plot(results, args.out + ".png")
    print(f"\nwrote {args.out}.json and {args.out}.png")
    return meta


if __name__ == "__main__":
    main()
