"""What accuracy costs in time: a sweep of the knobs that trade one for the other.

For each scene (default ``soft_bounce`` and ``cube_collision``) and each sweep point, a model is
trained on matching data with the package's own trainer (:func:`hrn_pyg.train.train`, preset
``ours``) and scored on the held-out ``test`` split: time per rollout step (median of
``--repeats`` >= 5 timed 15-step rollouts of one test trajectory, one torch thread) and the
position and shape MSE at ``t+5`` and ``t+15`` (:func:`hrn_pyg.evaluate.evaluate_model`, mean
and standard error over the test trajectories). The sweeps, each against the base point
(pitch 0.05 m, k-means branching 8 / leaf group 8, hidden 64, float32, one deterministic
trajectory):

* ``pitch``: voxel pitch, i.e. particle count (a new dataset per pitch);
* ``hierarchy``: branching / leaf group size (``2/2`` a deep tree, ``1000`` a flat object: one
  root over all its leaves); the base dataset with its ``hierarchy_parent`` rebuilt;
* ``hidden``: MLP width;
* ``k``: k trajectories sampled with dropout (rate ``--k-rate`` on force + collision) as one
  batched graph, scored by the error of the k-sample mean; time is per step for all k;
* ``dtype``: the base model and data cast to float64 at rollout time (trained in float32).

pybullet's own cost for the same simulated time (one model step = ``substeps`` physics steps)
is timed on the same machine for each scene and pitch and drawn on the same axes.

Everything expensive is cached under ``--work`` (default ``runs/accuracy_vs_time``): datasets
are generated once, a model is trained once per point (``model.pt`` present -> reused), so an
interrupted sweep resumes where it stopped. ``--budget`` is the training steps per point
(small by default: these models are much less trained than the Table 1 ones, so compare points
with each other, not with Table 1).

Run (the reduced sweep of docs/performance.md)::

    python benchmarks/accuracy_vs_time.py --budget 300 --episodes 40 --threads 1 --pitches 0.1,0.0333

Prints a markdown table, writes ``benchmarks/results/accuracy_vs_time.json`` and the Pareto plot
``benchmarks/results/accuracy_vs_time.png`` (time against error, Pareto front drawn).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch_geometric.data import Batch, HeteroData

from hrn_pyg.checkpoints import load_model
from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import NODE
from hrn_pyg.data.hierarchy import HierarchyConfig, build_hierarchy
from hrn_pyg.data.io import load_episode, save_episode
from hrn_pyg.data.scene_file import builtin_scene, make_scene
from hrn_pyg.evaluate import evaluate_model, select_windows, summarise
from hrn_pyg.nn.hrn import HRNConfig
from hrn_pyg.sampling.sample import sample
from hrn_pyg.sim.rollout import rollout
from hrn_pyg.train import TrainConfig, train
from hrn_pyg.utils.files import atomic_write_json
from hrn_pyg.viz import save_figure

SCENES = ("soft_bounce", "cube_collision")
HORIZONS = (5, 15)
#: the base point every sweep varies one knob of
BASE_PITCH = 0.05
BASE_HIDDEN = 64
#: (branching, leaf_group_size) variants; (8, 8) is the package default
HIERARCHIES = ((8, 8), (2, 2), (1000, 1000))
HIDDENS = (32, 64, 128)
KS = (1, 4, 16)
#: window starts this many steps apart in a test episode (evaluate's default)
STRIDE = 10


@dataclass(frozen=True)
class Point:
    """One sweep point: which data and model settings it uses."""

    scene: str
    sweep: str
    label: str
    pitch: float = BASE_PITCH
    branching: int = 8
    leaf_group: int = 8
    hidden: int = BASE_HIDDEN
    k: int = 1
    dtype: str = "float32"
    extra: dict = field(default_factory=dict, compare=False)

    @property
    def data_key(self) -> str:
        key = f"{self.scene}_p{self.pitch:g}"
        if (self.branching, self.leaf_group) != (8, 8):
            key += f"_b{self.branching}g{self.leaf_group}"
        return key

    @property
    def model_key(self) -> str:
        return f"{self.data_key}_h{self.hidden}"


def points_for(scene: str, pitches: list[float], sweeps: list[str]) -> list[Point]:
    pts = [Point(scene, "base", "base")]
    if "pitch" in sweeps:
        pts += [Point(scene, "pitch", f"pitch {p:g}", pitch=p) for p in pitches if p != BASE_PITCH]
    if "hierarchy" in sweeps:
        pts += [Point(scene, "hierarchy", f"b{b}/g{g}" if b < 1000 else "flat", branching=b, leaf_group=g)
                for b, g in HIERARCHIES if (b, g) != (8, 8)]
    if "hidden" in sweeps:
        pts += [Point(scene, "hidden", f"hidden {h}", hidden=h) for h in HIDDENS if h != BASE_HIDDEN]
    if "k" in sweeps:
        pts += [Point(scene, "k", f"k={k}", k=k) for k in KS if k != 1]
    if "dtype" in sweeps:
        pts += [Point(scene, "dtype", "float64", dtype="float64")]
    return pts


# ---------------------------------------------------------------------------------------------
# data


def make_dataset(work: Path, point: Point, episodes: int, steps: int) -> Path:
    """The episode folder of ``point`` (generated, or derived from the base-hierarchy folder)."""
    folder = work / "data" / point.data_key
    done = folder / "complete.json"
    if done.is_file():
        return folder
    folder.mkdir(parents=True, exist_ok=True)
    if (point.branching, point.leaf_group) == (8, 8):
        config = builtin_scene(point.scene, pitch=point.pitch, steps=steps)
        for seed in range(episodes):  # one pybullet episode per seed
            path = folder / f"episode_{seed:06d}.npz"
            if not path.is_file():
                save_episode(path, simulate_episode(config, seed))
    else:
        base = make_dataset(work, Point(point.scene, "base", "base", pitch=point.pitch), episodes, steps)
        hcfg = HierarchyConfig(branching=point.branching, leaf_group_size=point.leaf_group)
        for seed in range(episodes):
            path = folder / f"episode_{seed:06d}.npz"
            if path.is_file():
                continue
            ep = load_episode(base / f"episode_{seed:06d}.npz")
            ep["hierarchy_parent"] = build_hierarchy(
                ep["positions"][0].astype(np.float64), ep["leaf_mass"].astype(np.float64), ep["leaf_object"], hcfg)
            save_episode(path, ep)
    atomic_write_json(done, {"episodes": episodes, "steps": steps, "pitch": point.pitch,
                             "branching": point.branching, "leaf_group_size": point.leaf_group})
    return folder


def pybullet_ms_per_step(scene: str, pitch: float, repeats: int, steps: int = 20) -> tuple[float, int]:
    """Median wall time (ms) of one model step of pybullet itself, and the leaf count."""
    times, leaves = [], 0
    for r in range(repeats):
        sim = make_scene(builtin_scene(scene, pitch=pitch), r)
        try:
            leaves = len(sim.reset())
            start = time.perf_counter()
            for t in range(steps):  # model steps, each `substeps` physics steps
                sim.step(*sim.scripted_action(t))
            times.append((time.perf_counter() - start) / steps)
        finally:
            sim.close()
    return 1e3 * statistics.median(times), leaves


# ---------------------------------------------------------------------------------------------
# training and scoring


def train_point(work: Path, point: Point, data: Path, budget: int, threads: int) -> Path:
    out = work / "models" / point.model_key
    if (out / "model.pt").is_file():
        return out / "model.pt"
    if out.exists():
        shutil.rmtree(out)  # a half-finished run from an older budget: start again
    config = TrainConfig.for_preset("ours", data=str(data), out=str(out), steps=budget, batch_size=4,
                                    warmup=max(1, min(50, budget // 10)), checkpoint_every=budget,
                                    eval_every=budget, threads=threads, seed=0)
    train(config, HRNConfig(hidden=point.hidden), progress=False)
    return out / "model.pt"


def _cast(graph: HeteroData, dtype: torch.dtype) -> HeteroData:
    """A copy of ``graph`` with every floating tensor of the particle store cast to ``dtype``."""
    graph = graph.clone()
    store = graph[NODE]
    for key in list(store.keys()):
        value = store[key]
        if torch.is_tensor(value) and value.is_floating_point():
            store[key] = value.to(dtype)
    return graph


def score_point(point: Point, model_path: Path, data: Path, repeats: int, k_rate: float) -> dict:
    model = load_model(model_path)
    dtype = torch.float64 if point.dtype == "float64" else torch.float32
    model = model.to(dtype)
    steps = max(HORIZONS)
    test = EpisodeWindows(data, "test", horizon=steps)
    windows = [_cast(w, dtype) for w in select_windows(test, STRIDE, None)]
    one = windows[0]
    store = one[NODE]
    forces_one = store.force_seq[:, :steps].transpose(0, 1).contiguous()

    if point.k == 1:
        errors = evaluate_model(model, windows, HORIZONS)
        summary = summarise(errors)

        def run_once() -> None:
            with torch.no_grad():
                rollout(model, Batch.from_data_list([one]), steps, forces_one, sleep=None)
    else:
        summary = _sample_errors(model, windows, point.k, k_rate, steps)
        gen = torch.Generator().manual_seed(1)

        def run_once() -> None:
            sample(model, one, point.k, steps, k_rate, forces=forces_one, generator=gen)

    run_once()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run_once()
        times.append((time.perf_counter() - start) / steps)
    leaves = int(store.is_leaf.sum())
    return {
        "ms_per_step": 1e3 * statistics.median(times),
        "ms_per_step_runs": [1e3 * t for t in times],
        "leaves": leaves, "nodes": int(store.num_nodes),
        "test_trajectories": len(windows), "test_episodes": len(test.seeds),
        "errors": summary,
    }


def _sample_errors(model, windows: list, k: int, rate: float, steps: int) -> dict:
    """Position / shape error of the k-sample mean trajectory, per test window, summarised."""
    from hrn_pyg.losses import full_shape_loss, shape_groups

    per = {m: {h: [] for h in HORIZONS} for m in ("position", "shape")}
    gen = torch.Generator().manual_seed(0)
    for w in windows:  # a handful of test windows; each samples k copies in one graph
        store = w[NODE]
        forces = store.force_seq[:, :steps].transpose(0, 1).contiguous()
        leaves = store.is_leaf.nonzero().flatten()
        moving = ~store.is_static[leaves]
        pred = sample(model, w, k, steps, rate, forces=forces, generator=gen).mean(0)  # [steps, L, 3]
        truth = store.pos_seq[leaves].transpose(0, 1)  # [steps+3, L, 3]
        idx, grp = shape_groups(w)
        pos_of_leaf = torch.full((store.num_nodes,), -1, dtype=torch.long)
        pos_of_leaf[leaves] = torch.arange(leaves.numel())
        for h in HORIZONS:
            p, t = pred[h - 1], truth[h + 2]
            per["position"][h].append(float((p - t)[moving].pow(2).mean()))
            per["shape"][h].append(float(full_shape_loss(p[pos_of_leaf[idx]], t[pos_of_leaf[idx]], grp)))
    return summarise({m: {h: np.asarray(v) for h, v in by.items()} for m, by in per.items()})


# ---------------------------------------------------------------------------------------------
# report


def pareto_front(rows: list[dict], metric: str) -> list[dict]:
    """Rows not dominated in (time, error): no other row is both faster and more accurate."""
    pts = sorted(rows, key=lambda r: (r["ms_per_step"], r[metric]))
    front, best = [], float("inf")
    for r in pts:
        if r[metric] < best:
            front.append(r)
            best = r[metric]
    return front


def plot(rows: list[dict], pybullet: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = sorted({r["scene"] for r in rows})
    fig, axes = plt.subplots(len(scenes), 2, figsize=(12, 4.5 * len(scenes)), squeeze=False)
    colors = {"base": "k", "pitch": "tab:blue", "hierarchy": "tab:green", "hidden": "tab:orange",
              "k": "tab:purple", "dtype": "tab:red"}
    for i, scene in enumerate(scenes):
        sub = [r for r in rows if r["scene"] == scene]
        for j, metric in enumerate(("position_t+15", "shape_t+15")):
            ax = axes[i][j]
            for r in sub:
                ax.scatter(r["ms_per_step"], r[metric], color=colors.get(r["sweep"], "grey"), zorder=3)
                ax.annotate(r["label"], (r["ms_per_step"], r[metric]), fontsize=7, xytext=(3, 3),
                            textcoords="offset points")
            front = pareto_front(sub, metric)
            ax.plot([r["ms_per_step"] for r in front], [r[metric] for r in front], "k--", lw=0.8,
                    label="Pareto front")
            for pb in (q for q in pybullet if q["scene"] == scene):
                ax.axvline(pb["ms_per_step"], color="grey", ls=":", lw=1)
                ax.annotate(f"pybullet p={pb['pitch']:g}\n(error 0)", (pb["ms_per_step"], 1.0), fontsize=7,
                            xycoords=("data", "axes fraction"), xytext=(2, -24), textcoords="offset points")
            for sweep, c in colors.items():
                if any(r["sweep"] == sweep for r in sub):
                    ax.scatter([], [], color=c, label=sweep)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("time per model step (ms, 1 thread; dotted: pybullet)")
            ax.set_ylabel(f"{metric.replace('_', ' ')} MSE (m²)")
            ax.set_title(f"{scene}: {metric.replace('_', ' ')}")
            ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(SCENES))
    parser.add_argument("--sweeps", default="pitch,hierarchy,hidden,k,dtype")
    parser.add_argument("--pitches", default="0.1,0.0333", help="voxel pitches (m) of the pitch sweep")
    parser.add_argument("--budget", type=int, default=300, help="training steps per sweep point")
    parser.add_argument("--episodes", type=int, default=40, help="episodes per generated dataset")
    parser.add_argument("--episode-steps", type=int, default=50, help="model steps per episode")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--k-rate", type=float, default=0.05, help="dropout rate of the k sweep")
    parser.add_argument("--work", default="runs/accuracy_vs_time")
    parser.add_argument("--out", default="benchmarks/results/accuracy_vs_time.json")
    parser.add_argument("--plot", default="benchmarks/results/accuracy_vs_time.png")
    args = parser.parse_args(argv)
    if args.repeats < 5:
        raise SystemExit("--repeats must be >= 5 (median of at least 5 runs)")
    if args.episodes < 20:
        raise SystemExit("--episodes must be >= 20 (seeds ending in 8 and 9 are val and test)")
    torch.set_num_threads(args.threads)
    work = Path(args.work)
    scenes = [s for s in args.scenes.split(",") if s]
    sweeps = [s for s in args.sweeps.split(",") if s]
    pitches = sorted({BASE_PITCH, *(float(p) for p in args.pitches.split(",") if p)}, reverse=True)
    t_start = time.perf_counter()

    pybullet = []
    for scene in scenes:
        for pitch in pitches if "pitch" in sweeps else [BASE_PITCH]:
            ms, leaves = pybullet_ms_per_step(scene, pitch, args.repeats)
            pybullet.append({"scene": scene, "pitch": pitch, "leaves": leaves, "ms_per_step": ms})
            print(f"pybullet {scene} pitch {pitch:g}: {leaves} leaves, {ms:.2f} ms per model step", flush=True)

    rows = []
    for scene in scenes:
        for point in points_for(scene, pitches, sweeps):
            t0 = time.perf_counter()
            data = make_dataset(work, point, args.episodes, args.episode_steps)
            t1 = time.perf_counter()
            model_path = train_point(work, point, data, args.budget, args.threads)
            t2 = time.perf_counter()
            scored = score_point(point, model_path, data, args.repeats, args.k_rate)
            row = {"scene": scene, "sweep": point.sweep, "label": point.label, "pitch": point.pitch,
                   "branching": point.branching, "leaf_group_size": point.leaf_group, "hidden": point.hidden,
                   "k": point.k, "dtype": point.dtype, "model": str(model_path), **scored,
                   "seconds": {"data": round(t1 - t0, 1), "train": round(t2 - t1, 1),
                               "score": round(time.perf_counter() - t2, 1)}}
            for m in ("position", "shape"):
                for h in HORIZONS:
                    row[f"{m}_t+{h}"] = scored["errors"][m][f"t+{h}"]["mean"]
                    row[f"{m}_t+{h}_sem"] = scored["errors"][m][f"t+{h}"]["sem"]
            rows.append(row)
            print(f"{scene:15s} {point.label:12s} {row['leaves']:5d} leaves  {row['ms_per_step']:8.2f} ms/step  "
                  f"pos t+15 {row['position_t+15']:.3g}  shape t+15 {row['shape_t+15']:.3g}  "
                  f"({row['seconds']})", flush=True)

    # rows of other scenes from an earlier run into the same --out are kept (one sweep per scene)
    previous = json.loads(Path(args.out).read_text()) if Path(args.out).is_file() else {}
    rows = [r for r in previous.get("rows", []) if r["scene"] not in scenes] + rows
    pybullet = [q for q in previous.get("pybullet", []) if q["scene"] not in scenes] + pybullet
    runs = [c for c in previous.get("commands", []) if c["scenes"] != scenes]
    runs.append({"scenes": scenes, "sweeps": sweeps, "pitches": pitches, "budget": args.budget,
                 "episodes": args.episodes, "seconds": round(time.perf_counter() - t_start, 1)})
    scenes = sorted({r["scene"] for r in rows}, key=lambda s: (s not in SCENES, s))
    table = ["| scene | sweep | point | leaves | ms/step | pos MSE t+5 | pos MSE t+15 | shape MSE t+15 | on Pareto front |",
             "|---|---|---|---:|---:|---:|---:|---:|:---:|"]
    for scene in scenes:
        sub = [r for r in rows if r["scene"] == scene]
        front = {id(r) for r in pareto_front(sub, "position_t+15")}
        for r in sub:
            table.append(f"| {scene} | {r['sweep']} | {r['label']} | {r['leaves']} | {r['ms_per_step']:.2f} | "
                         f"{r['position_t+5']:.3g} | {r['position_t+15']:.3g} ± {r['position_t+15_sem']:.2g} | "
                         f"{r['shape_t+15']:.3g} | {'yes' if id(r) in front else ''} |")
        for pb in (q for q in pybullet if q["scene"] == scene):
            table.append(f"| {scene} | pybullet | pitch {pb['pitch']:g} | {pb['leaves']} | {pb['ms_per_step']:.2f} | 0 | 0 | 0 | |")
    text = "\n".join(table)
    print()
    print(text)
    result = {
        "what": "time per rollout step against t+15 error on held-out episodes, one knob at a time",
        "budget_train_steps": args.budget, "episodes_per_dataset": args.episodes,
        "episode_steps": args.episode_steps, "preset": "ours", "repeats": args.repeats,
        "statistic": "ms_per_step: median of repeats of a 15-step rollout of one test trajectory / 15; "
                     "errors: mean and standard error over test trajectories (stride 10)",
        "k_rate": args.k_rate, "k_error": "error of the mean of the k sampled trajectories",
        "dtype_note": "float64 points use the float32-trained model cast to float64 at rollout time",
        "machine": {"cpu": platform.machine(), "cpus": os.cpu_count(), "python": platform.python_version(),
                    "torch": torch.__version__, "torch_threads": args.threads,
                    "load_average_1m_at_end": os.getloadavg()[0],
                    "note": "2 shared cores, loaded by other training jobs while this ran"},
        "pybullet": pybullet, "rows": rows, "table": text, "commands": runs,
    }
    atomic_write_json(args.out, result)
    plot(rows, pybullet, Path(args.plot))
    return result


if __name__ == "__main__":
    main()
