"""Do rigid shapes survive a collision, and what does a step cost? One row per model on a split.

For every episode of the split (``seed % 10 == 9`` for ``test``, ``8`` for ``val``) the model is
rolled out from step 2 to the episode's end with the recorded forces, sleeping off (the network
alone). For each episode in which two rigid objects touch in pybullet (some leaves of two objects
closer than ``--contact`` metres, default 1.5 voxel pitches), the shapes are read after the first
touch: an object's *shape change* at a step is the root mean square over its leaf pairs of the
relative change of their distance, :math:`\\sqrt{\\mathrm{mean}_{ij} ((d_{ij}(t) - d_{ij}(0)) /
d_{ij}(0))^2}`, and a collision *keeps the shapes* when every rigid object's largest shape change
from the first touch to the end is within ``--tolerance`` (1 %). Also per model: the time per
step (median over the episodes of the rollout's seconds per step, one thread, sleeping off) and
the parameter count.

Run: ``python -m benchmarks.rigid_collisions --data data/cube_collision --split test
--model ours=cube_collision_ours --model gns=runs/gns_cube_collision/model.pt
--model "gns + rigid fit=runs/gns_cube_collision/model.pt" --rigid-fit "gns + rigid fit"
[--out benchmarks/results/rigid_collisions_cube_collision.json]``. Prints a markdown table and
writes JSON atomically.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from pathlib import Path

import numpy as np
import torch

import hrn_pyg
from hrn_pyg.checkpoints import load_model, with_applied_options
from hrn_pyg.data.dataset import split_of_seed
from hrn_pyg.data.graph import NODE, RIGID
from hrn_pyg.data.io import load_episode
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.utils.files import atomic_write_json

#: leaves of two objects closer than this many voxel pitches touch
CONTACT_PITCHES = 1.5


def shape_change(positions: np.ndarray, rest: np.ndarray) -> float:
    """RMS relative change of the pairwise distances of one object's leaves, ``[L, 3]`` each."""
    i, j = np.triu_indices(len(rest), k=1)
    d0 = np.linalg.norm(rest[i] - rest[j], axis=-1)
    d = np.linalg.norm(positions[i] - positions[j], axis=-1)
    return float(np.sqrt(np.mean(((d - d0) / d0) ** 2)))


def first_touch(positions: np.ndarray, leaf_object: np.ndarray, objects: list[int], contact: float) -> int | None:
    """The first step at which leaves of two of ``objects`` are closer than ``contact``, or None."""
    for t in range(len(positions)):
        for a in range(len(objects)):
            for b in range(a + 1, len(objects)):
                pa = positions[t][leaf_object == objects[a]]
                pb = positions[t][leaf_object == objects[b]]
                if np.min(np.linalg.norm(pa[:, None] - pb[None], axis=-1)) < contact:
                    return t
    return None


def score_episode(model, episode: dict, contact: float, tolerance: float) -> dict:
    """One rollout from step 2: the seconds per step, and the shapes after pybullet's first touch."""
    state = episode_state(episode, start=2)
    steps = state[NODE].force_seq.size(1)
    forces = state[NODE].force_seq.transpose(0, 1).contiguous()
    start = time.perf_counter()
    with torch.no_grad():
        pred = hrn_pyg.rollout(model, state, steps, forces, sleep=None)  # [steps, N, 3]
    seconds = (time.perf_counter() - start) / steps
    leaves = int(np.asarray(episode["positions"]).shape[1])
    pred_leaves = pred[:, :leaves].numpy()
    truth = np.asarray(episode["positions"])[3:3 + steps]
    leaf_object = np.asarray(episode["leaf_object"])
    rigid = [o for o, m in enumerate(np.asarray(episode["object_material"])) if m == RIGID]
    rest = np.asarray(episode["positions"])[0]
    touch = first_touch(truth, leaf_object, rigid, contact) if len(rigid) > 1 else None
    row = {"seed": int(episode["seed"]), "seconds_per_step": seconds, "steps": steps, "touch_step": touch}
    if touch is not None:
        worst = max(shape_change(p[leaf_object == o], rest[leaf_object == o])
                    for p in pred_leaves[touch:] for o in rigid)
        row.update(shape_change_after_touch=worst, keeps_shapes=bool(worst <= tolerance))
    return row


def dataset_pitch(folder: Path) -> float:
    """The voxel pitch (m) a dataset was generated at, from its ``meta.json``."""
    meta = json.loads((folder / "meta.json").read_text())
    return float(meta["config"]["pitch"])


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="episode folder")
    parser.add_argument("--split", choices=("test", "val"), default="val")
    parser.add_argument("--model", action="append", required=True, metavar="NAME=PATH",
                        help="a checkpoint (path or shipped name) per row (repeatable)")
    parser.add_argument("--rigid-fit", action="append", default=[], metavar="NAME",
                        help="apply the rigid fit after the network of row NAME (repeatable)")
    parser.add_argument("--tolerance", type=float, default=0.01, help="shape change that still counts as kept")
    parser.add_argument("--limit", type=int, default=0, help="score at most this many episodes (0: all)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default="benchmarks/results/rigid_collisions.json")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    paths = sorted(p for p in Path(args.data).glob("episode_*.npz"))
    episodes = [ep for ep in map(load_episode, paths) if split_of_seed(int(ep["seed"])) == args.split]
    if args.limit:
        episodes = episodes[:args.limit]
    if not episodes:
        raise SystemExit(f"no {args.split} episodes in {args.data}")
    pitch = dataset_pitch(Path(args.data))
    contact = CONTACT_PITCHES * pitch
    rows = []
    for spec in args.model:
        name, _, path = spec.partition("=")
        model = load_model(path or name)
        if name in args.rigid_fit:
            model = with_applied_options(model, rigid_fit=True)
        per_episode = [score_episode(model, ep, contact, args.tolerance) for ep in episodes]
        touched = [r for r in per_episode if r["touch_step"] is not None]
        kept = sum(r["keeps_shapes"] for r in touched)
        share = kept / len(touched) if touched else math.nan
        rows.append({
            "name": name, "path": path or name, "rigid_fit": name in args.rigid_fit,
            "parameters": sum(p.numel() for p in model.parameters()),
            "ms_per_step": 1e3 * statistics.median(r["seconds_per_step"] for r in per_episode),
            "collisions": len(touched), "kept": kept, "share_kept": share,
            "share_kept_se": math.sqrt(share * (1 - share) / len(touched)) if touched else math.nan,
            "median_shape_change": statistics.median(r["shape_change_after_touch"] for r in touched) if touched else None,
            "episodes": per_episode,
        })
    print(f"{args.data}, {args.split} split: {len(episodes)} episodes, contact within {contact:.3f} m, "
          f"shape kept within {100 * args.tolerance:g} %; one thread, sleeping off")
    print()
    print("| model | parameters | ms per step | collisions | shapes kept | median shape change |")
    print("|---|---:|---:|---:|---:|---:|")
    for r in rows:
        change = "-" if r["median_shape_change"] is None else f"{100 * r['median_shape_change']:.2f} %"
        print(f"| {r['name']} | {r['parameters']:,} | {r['ms_per_step']:.2f} | {r['collisions']} | "
              f"{r['kept']}/{r['collisions']} ({r['share_kept']:.2f} ± {r['share_kept_se']:.2f}) | {change} |")
    result = {"what": "rigid shapes after collisions and time per step", "data": args.data, "split": args.split,
              "contact_m": contact, "tolerance": args.tolerance, "threads": args.threads, "rows": rows}
    atomic_write_json(args.out, result)
    return result


if __name__ == "__main__":
    main()
