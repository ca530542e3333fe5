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

    python -m experiments.accuracy_vs_time --budget 300 --episodes 40 --threads 1 --pitches 0.1,0.0333

Prints a markdown table, writes ``benchmarks/results/accuracy_vs_time.json`` and the Pareto plot
``benchmarks/results/accuracy_vs_time.png`` (time against error, Pareto front drawn).

**One model across pitches** (``--model``, a shipped name or a checkpoint path). Nothing is
trained: the one model is scored on the same scenes made at each pitch of ``--pitches`` (default
0.025, 0.035, 0.05, 0.08 m). The scenes are ``--episodes`` seeds (from ``--first-seed``) of one
scene file (``--scene-file``, default the generalist's validation drop of two unseen meshes,
``data/shapes/unseen/validation_rigid.toml``), simulated by pybullet at each pitch and kept under
``--work`` (an episode file there is reused: ``experiments/episode_cache.py``). At each pitch:
the position and shape MSE at each of ``--horizons`` (default 15 and 50), mean and standard error
over windows from step 2 and then every ``--stride`` steps
(:func:`hrn_pyg.evaluate.evaluate_model`, the network alone); the model's time per step (median
over ``--repeats`` rollouts of the first window, ``max(--horizons)`` steps, sleeping off,
``--threads`` torch threads); pybullet's time per model step on the first episode, simulated again
in the same process; with ``--compile``, also the same rollout as compiled fixed-shape steps
(:class:`hrn_pyg.sim.fixed_shape.FixedShapeSimulator`, ``compile=True``, the package's fast path;
median over ``--repeats`` after the compiling one); and each error over the one at pitch 0.05
when 0.05 is swept. A model reads
the pitch from every graph (a pitch-aware model uses it; a plain one does not), and the model's
domain check runs at each pitch: a pitch it was not trained at is warned about and recorded. Run::

    python -m experiments.accuracy_vs_time --model shapes --pitches 0.025,0.035,0.05,0.08 \\
        --out benchmarks/results/accuracy_vs_pitch_shapes.json

prints its own table (pitch, leaves, pybullet and model ms per step, errors, ratios to pitch
0.05) and writes its JSON (default ``benchmarks/results/accuracy_vs_pitch.json``) atomically.
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
from hrn_pyg.checkpoints.domain import dataset_domain, report_outside
from hrn_pyg.data.scene_file import builtin_scene, read_scene_file
from hrn_pyg.evaluate import evaluate_model, select_windows, summarise
from hrn_pyg.nn.hrn import HRNConfig
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sampling.sample import sample
from hrn_pyg.sim.rollout import rollout
from hrn_pyg.train import TrainConfig, train
from hrn_pyg.utils.files import atomic_write_json
from hrn_pyg.viz import save_figure

from benchmarks.common import HORIZONS, STRIDE, compiled_rollout, pybullet_ms_per_step
from experiments.episode_cache import cached_episodes, episode_leaves, scene_digest, windows_of


SCENES = ("soft_bounce", "cube_collision")
#: the base point every sweep varies one knob of
BASE_PITCH = 0.05
BASE_HIDDEN = 64
#: (branching, leaf_group_size) variants; (8, 8) is the package default
HIERARCHIES = ((8, 8), (2, 2), (1000, 1000))
HIDDENS = (32, 64, 128)
KS = (1, 4, 16)
#: the one-model mode's defaults: scene file, pitches, horizons, episodes and first seed (the seeds
#: the scene file's own comment generates its validation folder with)
PITCH_SCENE = "data/shapes/unseen/validation_rigid.toml"
PITCH_PITCHES = (0.025, 0.035, 0.05, 0.08)
PITCH_HORIZONS = (15, 50)
PITCH_EPISODES = 6
PITCH_FIRST_SEED = 4_000_000


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


# ---------------------------------------------------------------------------------------------
# one model across pitches


def pitch_point(model, spec, pitch: float, args) -> dict:
    """Errors and times of ``model`` on the scenes of ``spec`` made at ``pitch``."""
    at = spec.with_settings(pitch=pitch, steps=args.episode_steps)
    folder = Path(args.work) / "pitch" / f"{spec.name}_p{pitch:g}_{scene_digest(at)}"
    seeds = list(range(args.first_seed, args.first_seed + args.episodes))
    made = cached_episodes(at, folder, seeds)
    outside = report_outside(model, dataset_domain(folder), prefix=f"accuracy_vs_time (pitch {pitch:g}): warning: ")
    steps = max(args.horizons)
    windows = windows_of(folder, made["seeds"], steps, args.stride, args.limit)
    errors = summarise(evaluate_model(model, windows, args.horizons))
    first = Batch.from_data_list([windows[0]])  # the first kept episode from step 2
    forces = first[NODE].force_seq[:, :steps].transpose(0, 1).contiguous()
    with torch.no_grad():
        rollout(model, first, 2, forces[:2], sleep=None)  # warm-up
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            rollout(model, first, steps, forces, sleep=None)
            times.append((time.perf_counter() - start) / steps)
    seconds = statistics.median(times)
    compiled = compiled_times(model, made["timed_episode"], steps, args.repeats) if args.compile else {}
    leaves = [episode_leaves(folder / f"episode_{s:06d}.npz") for s in made["seeds"]]
    return {"pitch": pitch, "leaves": int(made["timed_episode"]["positions"].shape[1]),
            "leaves_mean": float(np.mean(leaves)), "episodes": len(made["seeds"]), "seeds": made["seeds"],
            "rejected": made["rejected"], "made": made["made"], "windows": len(windows), "folder": str(folder),
            "pybullet_ms": 1e3 * made["pybullet_s_per_step"], "model_ms": 1e3 * seconds,
            "model_ms_runs": [1e3 * t for t in times], "x_pybullet": seconds / made["pybullet_s_per_step"],
            "outside": outside, "errors": errors,
            **{key: (value / made["pybullet_s_per_step"] if key == "compiled_x_pybullet" else value)
               for key, value in compiled.items()}}


def compiled_times(model, episode: dict, steps: int, repeats: int) -> dict:
    """The compiled fixed-shape rollout of ``steps`` steps from step 2 of ``episode``: the
    seconds of the compiling run, the median ms per step of ``repeats`` more, and the median in
    seconds (``compiled_x_pybullet``, divided by pybullet's time by the caller); for a model the
    fixed-shape steps cannot run, only ``compiled_skipped``, the reason."""
    state = episode_state(episode, start=2, steps=steps)
    try:
        first, timed = compiled_rollout(model, state, steps)
    except ValueError as exc:  # a model the fixed-shape steps cannot run (a GNS)
        reason = str(exc).splitlines()[0]
        print(f"compiled: not timed ({reason})", flush=True)
        return {"compiled_skipped": reason}
    runs = [timed()[0] for _ in range(repeats)]
    return {"compile_s": first, "compiled_ms": 1e3 * statistics.median(runs),
            "compiled_ms_runs": [1e3 * t for t in runs], "compiled_x_pybullet": statistics.median(runs)}


def pitch_table(rows: list[dict], horizons: tuple[int, ...]) -> str:
    """One row per pitch: leaves, times, errors and their ratio to pitch 0.05 (when swept)."""
    head = ["pitch (m)", "leaves", "pybullet ms/step", "model ms/step", "model / pybullet"]
    compiled = all("compiled_ms" in r for r in rows)
    if compiled:
        head += ["compiled ms/step", "compiled / pybullet"]
    head += [f"{m} MSE t+{h}" for m in ("position", "shape") for h in horizons]
    ratios = any(r["pitch"] == BASE_PITCH for r in rows)
    if ratios:
        head += [f"{m} t+{h} x pitch {BASE_PITCH:g}" for m in ("position", "shape") for h in horizons]
    head += ["diverged", "in the model's domain"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [f"{r['pitch']:g}", str(r["leaves"]), f"{r['pybullet_ms']:.2f}", f"{r['model_ms']:.2f}",
                 f"{r['x_pybullet']:.2f}x"]
        if compiled:
            cells += [f"{r['compiled_ms']:.2f}", f"{r['compiled_x_pybullet']:.2f}x"]
        for m in ("position", "shape"):
            for h in horizons:
                s = r["errors"][m][f"t+{h}"]
                cells.append(f"{s['mean']:.3g}" + (f" ± {s['sem']:.2g}" if np.isfinite(s["sem"]) else ""))
        if ratios:
            cells += [f"{r[f'ratio_{m}@{h}']:.2f}x" for m in ("position", "shape") for h in horizons]
        cells += [str(r["errors"]["position"][f"t+{max(horizons)}"]["diverged"]), "no" if r["outside"] else "yes"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def one_model(args) -> dict:
    """The one-model mode: ``args.model`` scored and timed at each pitch of ``args.pitches``."""
    if args.repeats < 1 or args.episodes < 1 or args.stride < 1:
        raise SystemExit("--repeats, --episodes and --stride must be >= 1")
    args.horizons = tuple(int(h) for h in args.horizons.split(",") if h)
    if not args.horizons or min(args.horizons) < 1:
        raise SystemExit(f"--horizons must be positive integers, got {args.horizons}")
    torch.set_num_threads(args.threads)
    pitches = [float(p) for p in args.pitches.split(",") if p]
    model = load_model(args.model)
    spec = read_scene_file(args.scene_file)
    started = time.perf_counter()
    rows = []
    for pitch in pitches:
        row = pitch_point(model, spec, pitch, args)
        rows.append(row)
        print(f"pitch {pitch:g}: {row['leaves']} leaves, {row['windows']} windows ({row['made']} episodes made); "
              f"pybullet {row['pybullet_ms']:.2f} ms, model {row['model_ms']:.2f} ms per step; position MSE "
              + ", ".join(f"t+{h} {row['errors']['position'][f't+{h}']['mean']:.3g}" for h in args.horizons),
              flush=True)
    base = next((r for r in rows if r["pitch"] == BASE_PITCH), None)
    if base is not None:
        for r in rows:
            for m in ("position", "shape"):
                for h in args.horizons:
                    r[f"ratio_{m}@{h}"] = r["errors"][m][f"t+{h}"]["mean"] / base["errors"][m][f"t+{h}"]["mean"]
    table = pitch_table(rows, args.horizons)
    print()
    print(table, end="")
    result = {
        "what": "one model on the same scenes made at each pitch: time per step and error, pybullet's time beside",
        "model": args.model, "scene_file": args.scene_file, "episodes": args.episodes,
        "first_seed": args.first_seed, "episode_steps": args.episode_steps, "horizons": list(args.horizons),
        "stride": args.stride, "limit": args.limit, "repeats": args.repeats, "threads": args.threads,
        "statistics": "errors: mean and standard error over windows (from step 2, then every --stride steps), "
                      "the network alone; model_ms: median over --repeats of a max(--horizons)-step rollout "
                      "of the first window, sleeping off; compiled_ms (--compile): median over --repeats of the same "
                      "rollout as compiled fixed-shape steps, after the compiling one; pybullet_ms: median over the model steps of the "
                      "first episode, simulated again in this run",
        "machine": {"cpu": platform.machine(), "cpus": os.cpu_count(), "torch": torch.__version__,
                    "torch_threads": args.threads, "load_average_1m_at_end": os.getloadavg()[0]},
        "compile": bool(args.compile),
        "seconds": round(time.perf_counter() - started, 1), "rows": rows, "table": table,
    }
    atomic_write_json(args.out, result)
    print(f"wrote {args.out} ({result['seconds']:.0f} s)")
    return result


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(SCENES))
    parser.add_argument("--sweeps", default="pitch,hierarchy,hidden,k,dtype")
    parser.add_argument("--pitches", default=None,
                        help="voxel pitches (m): of the pitch sweep (default 0.1,0.0333), or with --model "
                             "the pitches the one model is scored at (default 0.025,0.035,0.05,0.08)")
    parser.add_argument("--budget", type=int, default=300, help="training steps per sweep point")
    parser.add_argument("--episodes", type=int, default=None,
                        help="episodes per generated dataset (default 40), or with --model per pitch (default 6)")
    parser.add_argument("--episode-steps", type=int, default=None,
                        help="model steps per episode (default 50; with --model the scene file's own)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--k-rate", type=float, default=0.05, help="dropout rate of the k sweep")
    parser.add_argument("--work", default="runs/accuracy_vs_time")
    parser.add_argument("--out", default=None, help="JSON (default benchmarks/results/accuracy_vs_time.json, "
                        "with --model benchmarks/results/accuracy_vs_pitch.json)")
    parser.add_argument("--plot", default="benchmarks/results/accuracy_vs_time.png", help="the sweep's plot")
    one = parser.add_argument_group("one model across pitches (--model)")
    one.add_argument("--model", default=None, help="score this one model (a shipped name or a path) at each "
                     "pitch instead of training a model per sweep point")
    one.add_argument("--scene-file", default=PITCH_SCENE)
    one.add_argument("--first-seed", type=int, default=PITCH_FIRST_SEED)
    one.add_argument("--horizons", default=",".join(map(str, PITCH_HORIZONS)))
    one.add_argument("--stride", type=int, default=STRIDE, help="steps between window starts in an episode")
    one.add_argument("--limit", type=int, default=None, help="at most this many windows per pitch")
    one.add_argument("--compile", action="store_true",
                     help="also time the rollout as compiled fixed-shape steps (a minute or so to compile per pitch)")
    args = parser.parse_args(argv)
    if args.model is not None:
        args.pitches = args.pitches or ",".join(map(str, PITCH_PITCHES))
        args.episodes = PITCH_EPISODES if args.episodes is None else args.episodes
        args.out = args.out or "benchmarks/results/accuracy_vs_pitch.json"
        return one_model(args)
    args.pitches = args.pitches or "0.1,0.0333"
    args.episodes = 40 if args.episodes is None else args.episodes
    args.episode_steps = 50 if args.episode_steps is None else args.episode_steps
    args.out = args.out or "benchmarks/results/accuracy_vs_time.json"
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
