"""Do the models hold? 1000-step rollouts of trained checkpoints from a scene's resting start.

For every (scene, checkpoint) and every start seed: the pybullet scene at model step 2 (objects
at rest, before any scripted push), rolled on by the model for ``--steps`` steps with no external
force, which in pybullet leaves every object where it is. Reported per run
(:func:`hrn_pyg.sim.stability.stability_report`, the package's check):

* ``finite`` and ``max_move`` (m): the package's 1000-step check asks for finite positions, no leaf
  further than 50 m from its start and ``min_z`` (lowest leaf) above -0.05 m (one voxel pitch);
* ``rigid_shape``: for rigid objects, the largest relative change of the mean pairwise leaf
  distance between the start and the end (the goal: within 1 %);
* ``rest_drift`` (m): the largest displacement of an object's mass-weighted centre between step
  ``--settle`` and the end (the goal: under 0.05 m; pybullet keeps them still);
* ``soft_extent``: for soft bodies and cloth, the ratio of the height extent (max z - min z of the
  object's leaves) at the end to the start.

Run: ``python -m benchmarks.long_rollouts --model soft_bounce=hrn_pyg/checkpoints/soft_bounce_ours.pt
[--model ...] [--seeds 8,18,28] [--steps 1000] [--mirror-average x|xy] [--rigid-fit LABEL]
[--out benchmarks/results/long_rollouts.json]``.
Validation seeds (``seed % 10 == 8``) by default, so it can be used for model selection. Prints a
markdown table and writes JSON atomically.
"""

from __future__ import annotations

import argparse
import time

import torch

from hrn_pyg.checkpoints import load_model, with_applied_options
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import NODE
from hrn_pyg.data.scene_file import SCENES
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sim.rollout import rollout
from hrn_pyg.sim.stability import stability_report
from hrn_pyg.utils.files import atomic_write_json


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", action="append", required=True, metavar="SCENE=PATH[:LABEL]")
    parser.add_argument("--seeds", default="8,18,28")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--settle", type=int, default=200, help="step after which objects should rest")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--mirror-average", choices=("x", "xy"), default=None,
                        help="roll every model as if averaged over these mirrors (HRNConfig.mirror_planes), "
                             "the same weights: what the average alone does, before any training with it")
    parser.add_argument("--rigid-fit", action="append", default=[], metavar="LABEL",
                        help="roll the model labelled LABEL with the rigid fit after its network "
                             "(e.g. a GNS trained without it; repeatable)")
    parser.add_argument("--out", default="benchmarks/results/long_rollouts.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    seeds = [int(s) for s in args.seeds.split(",") if s]
    rows = []
    for spec in args.model:
        scene, _, rest = spec.partition("=")
        path, _, label = rest.partition(":")
        if scene not in SCENES:
            parser.error(f"unknown scene {scene!r}; choose from {sorted(SCENES)}")
        model = load_model(path)
        if label and label in args.rigid_fit:
            model = with_applied_options(model, rigid_fit=True)
        if args.mirror_average:
            model = with_applied_options(model, mirror_average=True, mirror_planes=args.mirror_average)
        for seed in seeds:
            graph = episode_state(simulate_episode(scene, seed, steps=5), start=2, steps=3)
            del graph[NODE].pos_seq, graph[NODE].force_seq
            t0 = time.perf_counter()
            with torch.no_grad():
                try:
                    traj = rollout(model, graph, args.steps, sleep=None)  # the network alone: nothing held still
                except ValueError as exc:  # a rollout that left the finite numbers
                    rows.append({"scene": scene, "model": label or path, "seed": seed, "finite": False,
                                 "passes_check": False, "error": str(exc).splitlines()[0]})
                    print(rows[-1], flush=True)
                    continue
            row = {"scene": scene, "model": label or path, "seed": seed, **stability_report(traj, graph, args.settle),
                   "seconds": time.perf_counter() - t0}
            rows.append(row)
            print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)

    print("\n| scene | model | seed | passes | max move (m) | lowest leaf (m) | rigid shape change | "
          "rest drift (m) | soft extent ratio |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            print(f"| {r['scene']} | {r['model']} | {r['seed']} | no | {r['error']} | | | | |")
            continue
        print(f"| {r['scene']} | {r['model']} | {r['seed']} | {'yes' if r['passes_check'] else 'no'} | "
              f"{r['max_move']:.3g} | {r['min_z']:.3g} | {100 * r['rigid_shape']:.2f} % | "
              f"{r['rest_drift']:.3g} | {r['soft_extent']:.3g} |")
    atomic_write_json(args.out, {"steps": args.steps, "settle": args.settle, "seeds": seeds, "rows": rows})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
