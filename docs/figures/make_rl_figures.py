"""Draw the RL figures of docs/rl.md and copy the small result artefacts next to them.

``docs/figures/rl_<task>_policy.png`` (the seed paper's Fig. 9): the final policies of one
seed, trained in the deterministic and in the stochastic learned environment, each run from
the same start scene and goal in the learned model (dropout 0) and replayed open loop in
pybullet, at a few moments. The goal disc is drawn in red on the ground; the episode is the
shortest one (of ``--episodes``, at least ``MIN_STEPS`` long where possible) that the
stochastic policy solves in both the learned model and pybullet (failing that, in the learned
model; failing that, the first).

Also copies ``<runs>/episode_length.png`` to ``docs/figures/rl_<task>_episode_length.png`` and
``<runs>/summary.{json,md}`` to ``docs/results/rl_<task>_summary.{json,md}`` and
``<runs>/comparison.{json,md}`` (bootstrap intervals, :mod:`experiments.rl.stats`) to
``docs/results/rl_<task>_comparison.{json,md}``.

Run: ``python docs/figures/make_rl_figures.py --task cube_push --runs runs/rl/cube_push
--model hrn_pyg/checkpoints/cube_push.pt [--seed 0] [--episodes 32]``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path

import numpy as np
import torch

from hrn_pyg.rl.env import HRNEnv
from hrn_pyg.rl.evaluate import record_episodes, replay_in_pybullet
from hrn_pyg.rl.hrn_dynamics import HISTORY_STEPS, HRNDynamics
from hrn_pyg.rl.showcase import load_actor
from hrn_pyg.utils.files import atomic_path
from hrn_pyg.viz import object_colors, rollout_grid

HERE = Path(__file__).resolve().parent
#: points drawn on the goal disc's rim, and its colour
GOAL_POINTS = 32
GOAL_COLOR = "#D00000"
#: environment seed of the figure's episodes (fixes the start scenes and goals)
FIGURE_ENV_SEED = 123
#: columns of the picture
COLUMNS = 4
#: episodes shorter than this are drawn only if nothing longer qualifies: a very short episode
#: shows little pushing (goals start at least tasks.goal_margin outside the success radius)
MIN_STEPS = 3


def goal_ring(goal: np.ndarray, radius: float) -> np.ndarray:
    """``GOAL_POINTS`` points on the goal disc's rim on the ground, ``[GOAL_POINTS, 3]``."""
    angle = np.linspace(0, 2 * np.pi, GOAL_POINTS, endpoint=False)
    return np.stack([goal[0] + radius * np.cos(angle), goal[1] + radius * np.sin(angle),
                     np.zeros_like(angle)], axis=1)


def pad_frames(frames: np.ndarray, length: int) -> np.ndarray:
    """Repeat the last frame so that there are ``length`` frames, ``[length, L, 3]``."""
    extra = length - frames.shape[0]
    return frames if extra <= 0 else np.concatenate([frames, np.repeat(frames[-1:], extra, 0)])


def stochastic_mode(runs: Path, seed: int) -> str:
    """The sweep's stochastic mode with a policy for ``seed``: ``stochastic`` (constant rate,
    cube_push's Fig. 7) or else ``stochastic_annealed`` (the tower's Fig. 8)."""
    for mode in ("stochastic", "stochastic_annealed"):
        if (runs / mode / f"seed{seed}" / "policy.pt").is_file():
            return mode
    raise FileNotFoundError(f"no stochastic or stochastic_annealed policy of seed {seed} under {runs}")


def policy_figure(task: str, runs: Path, model: Path, seed: int, episodes: int, path: Path) -> dict:
    dynamics = HRNDynamics.from_checkpoint(model, task)
    L = dynamics.num_leaves
    recs = {}
    stochastic = stochastic_mode(runs, seed)
    for mode in ("deterministic", stochastic):
        env = HRNEnv(task, dynamics, batch_size=episodes, seed=FIGURE_ENV_SEED, dropout_rate=0.0)
        actor = load_actor(runs / mode / f"seed{seed}" / "policy.pt", env)
        recs[mode] = record_episodes(actor, env, episodes)
    replays = {mode: [replay_in_pybullet(r["actions"], task, r["seed"], r["goal"], HISTORY_STEPS)
                      for r in rs] for mode, rs in recs.items()}
    sto, sto_real = recs[stochastic], replays[stochastic]
    order = sorted(range(episodes), key=lambda i: (not (sto[i]["success"] and sto_real[i]["success"]),
                                                   not sto[i]["success"],
                                                   sto[i]["length"] < MIN_STEPS, sto[i]["length"]))
    pick = order[0]
    rows, info = {}, {"episode": pick, "scene_seed": sto[pick]["seed"]}
    length = 1 + max(max(recs[m][pick]["length"], replays[m][pick]["steps"]) for m in recs)
    goal = recs[stochastic][pick]["goal"].numpy()
    ring = goal_ring(goal, dynamics.task.goal_radius)
    for mode in recs:
        rec, real = recs[mode][pick], replays[mode][pick]
        learned = rec["states"][:, :-1].reshape(-1, 3, L, 3)[:, 2].numpy()  # x_t of each state
        for name, frames, ok, steps in (("model", learned, rec["success"], rec["length"]),
                                        ("pybullet", real["leaves"].numpy(), real["success"], real["steps"])):
            frames = pad_frames(frames, length)
            frames = np.concatenate([frames, np.broadcast_to(ring, (length, GOAL_POINTS, 3))], axis=1)
            label = f"{mode[:3]}. {name}: {'goal' if ok else 'miss'} @{steps}"
            rows[label] = frames
            info[f"{mode}/{name}"] = {"success": bool(ok), "steps": int(steps)}
    colors = np.concatenate([object_colors(dynamics.leaf_object.numpy()), [GOAL_COLOR] * GOAL_POINTS])
    times = sorted(set(int(round(t)) for t in np.linspace(0, length - 1, COLUMNS)))
    rollout_grid(rows, times, colors, path,
                 title=f"{task}, seed {seed}: deterministic- and stochastic-trained policies,\n"
                       "learned model vs pybullet replay (goal disc in red)")
    return info


def copy_artefacts(task: str, runs: Path) -> list[Path]:
    """Copy the sweep's figure and summaries into docs (atomically); returns what was written."""
    results = HERE.parent / "results"
    results.mkdir(exist_ok=True)
    pairs = [(runs / "episode_length.png", HERE / f"rl_{task}_episode_length.png"),
             (runs / "summary.json", results / f"rl_{task}_summary.json"),
             (runs / "summary.md", results / f"rl_{task}_summary.md"),
             (runs / "summary.csv", results / f"rl_{task}_summary.csv"),
             (runs / "comparison.json", results / f"rl_{task}_comparison.json"),
             (runs / "comparison.md", results / f"rl_{task}_comparison.md")]
    written = []
    for src, dst in pairs:
        if src.is_file():
            with atomic_path(dst, suffix=dst.suffix) as tmp:
                shutil.copyfile(src, tmp)
            written.append(dst)
    return written


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="cube_push")
    parser.add_argument("--runs", type=Path, default=None, help="sweep folder (default runs/rl/<task>)")
    parser.add_argument("--model", type=Path, default=None,
                        help="learned checkpoint (default hrn_pyg/checkpoints/<task>.pt)")
    parser.add_argument("--seed", type=int, default=0, help="training seed of the policies drawn")
    parser.add_argument("--episodes", type=int, default=32)
    parser.add_argument("--no-policy", action="store_true", help="only copy the artefacts")
    args = parser.parse_args()
    torch.set_num_threads(1)
    runs = args.runs or Path("runs/rl") / args.task
    model = args.model or Path("hrn_pyg/checkpoints") / f"{args.task}.pt"
    for path in copy_artefacts(args.task, runs):
        print(f"wrote {os.path.relpath(path)}")
    if not args.no_policy:
        path = HERE / f"rl_{args.task}_policy.png"
        info = policy_figure(args.task, runs, model, args.seed, args.episodes, path)
        print(f"wrote {os.path.relpath(path)}: {json.dumps(info)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
