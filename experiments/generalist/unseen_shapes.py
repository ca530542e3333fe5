"""Shapes a model never saw: its errors per mesh and material, against its own test split.

Four sections, all on the CPU, every rollout the network alone (no object sleeps) except where
time is measured:

1. **Unseen meshes.** For each ``--unseen`` folder (episodes of a scene file; every episode, as
   ``hrn-pyg evaluate --split all``): windows ``--stride`` steps apart, rolled out with the
   episode's own forces; at each horizon (``--horizons``, default 15 and 50) the position and
   shape MSE of every object (:func:`experiments.scores.per_object_errors`), grouped by the mesh
   the seed drew for it and its material. Beside each group: the same model's error on its
   **own test split** (the ``--own`` folders' ``test`` splits, per material; ``--own-split val``
   when choosing between checkpoints) and the ratio.
   Windows whose rollout left the finite numbers are counted (``diverged``), not averaged.
2. **Against the specialists.** For each ``--specialist DATA=PATH``: Table 1's errors (per
   trajectory, :func:`hrn_pyg.evaluate.evaluate_model`) of the model and of the specialist on
   ``DATA``'s test split (``--own-split``), and their ratio (model / specialist; below 1: the model
   is better).
3. **Rest.** For every mesh and material of the unseen folders, the first ``--rest-episodes``
   episodes whose ground truth ends with every object at rest: the model started from the last
   three states and run ``--rest-steps`` steps with no force, scored by the package's stability
   check (:func:`experiments.scores.rest_check`; objects should rest from step 0). With
   ``--pybullet-rest WORK`` pybullet's own continuation of each such episode (the same seed run
   ``--rest-steps`` further, in a process of its own, kept under ``WORK`` and reused) is scored
   by the same check: an episode pybullet does not hold either was not at rest, whatever its last
   frames' speeds said, and the table says so beside the model's verdict.
4. **Time.** For one episode per unseen folder: the model's seconds per step over the whole
   episode (the default rollout, objects at rest sleeping; and all awake) and pybullet's seconds
   per step for the same episode (simulated again here), one torch thread, in one process.

Run (validation, for model selection; the test files are scored once, at the end)::

    python -m experiments.generalist.unseen_shapes --model runs/recipe/shapes/model.pt \\
        --unseen data/unseen_val_rigid --unseen data/unseen_val_soft \\
        --own data/shapes_drop --own data/shapes_push --own data/soft_bounce_shapes --own data/cube_collision \\
        --specialist data/cube_collision=hrn_pyg/checkpoints/cube_collision.pt \\
        --specialist data/soft_bounce=hrn_pyg/checkpoints/soft_bounce.pt \\
        --out benchmarks/results/unseen_shapes_validation.json --figures docs/figures/unseen

``--quick`` (stride 30, no rest or time sections) scores many checkpoints fast.
Prints markdown tables and writes JSON atomically.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import statistics
import subprocess
import sys
import time
import tomllib
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
from torch_geometric.data import Batch

from experiments.scores import per_object_errors, rest_check
from hrn_pyg.checkpoints import load_model, with_applied_options
from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import MATERIALS, NODE
from hrn_pyg.data.io import load_episode
from hrn_pyg.data.scene_file import read_scene_file
from hrn_pyg.evaluate import (
    comparison_figure,
    evaluate_model,
    guarded_rollout,
    select_windows,
    summarise,
)
from hrn_pyg.nn.hrn import HRNConfig
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sim.rollout import iterate
from hrn_pyg.sim.sleeping import DEFAULT_SLEEP
from hrn_pyg.sim.stability import stability_report
from hrn_pyg.utils.files import atomic_write_json

ERRORS = ("position", "shape")
#: the applied options (``HRNConfig``) a flag of their own sets: option, ``"switch"`` (on / off) or
#: ``"pitches"`` (a number of voxel pitches), what it does
APPLIED_FLAGS = (
    ("rigid_ground_depth", "pitches", "with --ground-projection on: how far under the plane a rigid object's "
                                      "lowest leaf may lie before it is lifted"),
    ("rigid_ground_speed", "pitches", "with --ground-projection on: how far a rigid object may move in a step "
                                      "and still be lifted; 0: at any speed"),
    ("ground_lift_velocity", "switch", "off: the ground lift carries x_t with it and is not a motion"),
    ("corotated_rest", "switch", "the rest shape of soft bodies and cloth turned onto their current leaves"),
    ("cloth_clearance", "pitches", "cloth leaves kept out of other objects; 0: off"),
    ("rigid_fit_rest", "switch", "each rigid object's motion fitted from its rest shape, not its current leaves"),
)
#: the options the JSON records as the model applied them
RECORDED_OPTIONS = ("ground_projection", "ground_projection_rigid", *(option for option, _, _ in APPLIED_FLAGS))
HRN_DEFAULTS = {f.name: f.default for f in dataclasses.fields(HRNConfig)}


def mesh_name(mesh: str) -> str:
    """A short name of a scene file's mesh: ``pybullet_data:torus/torus_textured.obj`` -> ``torus_textured``."""
    return Path(mesh.split(":", 1)[-1]).stem


def object_labels(path: Path) -> list[tuple[str, str]]:
    """``(mesh, material)`` of each object of one episode file, from the scene file text and the
    draws it records (a mesh list is indexed by the seed's draw)."""
    episode = load_episode(path)
    record = json.loads(str(episode["params"]))
    objects = tomllib.loads(record["scene_file"])["objects"]
    drawn = record["params"]["objects"]
    labels = []
    for index, (obj, draw) in enumerate(zip(objects, drawn, strict=True)):
        mesh = obj["mesh"]
        if isinstance(mesh, list):
            mesh = mesh[int(draw.get("mesh", 0))]
        material = MATERIALS[int(episode["object_material"][index])]
        labels.append((mesh_name(mesh), material))
    return labels


def windows_of(folder: Path, split: str, horizon: int, stride: int, limit: int | None) -> list:
    return select_windows(EpisodeWindows(folder, split, horizon=horizon), stride, limit)


def object_errors(model, windows: list, horizons: tuple[int, ...], batch: int) -> list[dict]:
    """One row per (window, object) with the object's errors at each horizon (NaN once its
    window diverged); rolled ``batch`` windows at a time."""
    rows = []
    for first in range(0, len(windows), batch):
        group = windows[first:first + batch]
        graph = Batch.from_data_list(group)
        store = graph[NODE]
        pred, diverged_at = guarded_rollout(model, group, max(horizons), graph=graph)
        truth = store.pos_seq.transpose(0, 1)  # x_{t-2} .. x_{t+H}
        span = int(store.object.max()) + 1
        per_h = {h: per_object_errors(pred[h - 1], truth[h + 2], graph) for h in horizons}
        for c, window in enumerate(group):
            for o in range(span):
                row = {"seed": int(window.episode_seed), "object": o, "start": int(window.start_step),
                       "diverged_at": int(diverged_at[c])}
                for h in horizons:
                    for m in ERRORS:
                        row[f"{m}@{h}"] = float(per_h[h][m][c * span + o])
                rows.append(row)
    return rows


def group_stats(rows: list[dict], key, horizons: tuple[int, ...]) -> dict[str, dict]:
    """Mean and count of the finite values of each error, per group ``key(row)``."""
    groups: dict[str, list[dict]] = defaultdict(list)
    for row in rows:
        groups[key(row)].append(row)
    out = {}
    for name, members in sorted(groups.items()):
        stats = {"objects": len(members), "episodes": len({r["seed"] for r in members})}
        for h in horizons:
            for m in ERRORS:
                values = np.array([r[f"{m}@{h}"] for r in members])
                finite = values[np.isfinite(values)]
                stats[f"{m}@{h}"] = float(finite.mean()) if len(finite) else float("nan")
                stats[f"diverged@{h}"] = int(len(values) - len(finite))
        out[name] = stats
    return out


def unseen_section(model, folders: list[Path], own: list[Path], args) -> dict:
    horizons = args.horizons
    labels: dict[int, list[tuple[str, str]]] = {}
    rows = []
    for folder in folders:
        windows = windows_of(folder, "all", max(horizons), args.stride, args.limit)
        for path in sorted(folder.glob("episode_*.npz")):
            seed = int(load_episode(path)["seed"])
            labels[seed] = object_labels(path)
        for row in object_errors(model, windows, horizons, args.batch):
            mesh, material = labels[row["seed"]][row["object"]]
            rows.append({**row, "folder": folder.name, "mesh": mesh, "material": material})
        print(f"  {folder}: {len(windows)} windows", flush=True)
    own_rows = []
    for folder in own:
        windows = windows_of(folder, args.own_split, max(horizons), args.stride, args.limit)
        materials = {}
        for path in sorted(folder.glob("episode_*.npz")):
            episode = load_episode(path)
            materials[int(episode["seed"])] = [MATERIALS[int(m)] for m in episode["object_material"]]
        for row in object_errors(model, windows, horizons, args.batch):
            if np.isnan(row[f"position@{horizons[0]}"]) and row["diverged_at"] == 0:
                continue  # a static object (the wedge, a ground plate): nothing to score
            own_rows.append({**row, "folder": folder.name, "material": materials[row["seed"]][row["object"]]})
        print(f"  {folder} ({args.own_split} split): {len(windows)} windows", flush=True)
    unseen = group_stats(rows, lambda r: f"{r['mesh']} ({r['material']})", horizons)
    own_stats = group_stats(own_rows, lambda r: r["material"], horizons)
    for name, stats in unseen.items():
        material = name.rsplit("(", 1)[1].rstrip(")")
        reference = own_stats.get(material)
        for h in horizons:
            for m in ERRORS:
                stats[f"ratio_{m}@{h}"] = stats[f"{m}@{h}"] / reference[f"{m}@{h}"] if reference else float("nan")
    by_material = group_stats(rows, lambda r: r["material"], horizons)
    for material, stats in by_material.items():
        reference = own_stats.get(material)
        for h in horizons:
            for m in ERRORS:
                stats[f"ratio_{m}@{h}"] = stats[f"{m}@{h}"] / reference[f"{m}@{h}"] if reference else float("nan")
    return {"unseen": unseen, "unseen_by_material": by_material, "own_test": own_stats,
            "unseen_by_folder": group_stats(rows, lambda r: f"{r['folder']} ({r['material']})", horizons),
            "own_by_folder": group_stats(own_rows, lambda r: f"{r['folder']} ({r['material']})", horizons)}


def specialist_section(model, specialists: dict[str, str], args) -> dict:
    out = {}
    horizons = args.horizons
    for data, path in specialists.items():
        windows = windows_of(Path(data), args.own_split, max(horizons), args.stride, args.limit)
        ours = summarise(evaluate_model(model, windows, horizons))
        theirs = summarise(evaluate_model(load_model(path), windows, horizons))
        cells = {}
        for m in ERRORS:
            for h in horizons:
                a, b = ours[m][f"t+{h}"], theirs[m][f"t+{h}"]
                cells[f"{m}@{h}"] = {"model": a["mean"], "specialist": b["mean"], "ratio": a["mean"] / b["mean"],
                                     "model_diverged": a["diverged"], "specialist_diverged": b["diverged"]}
        out[Path(data).name] = {"specialist": path, "windows": len(windows), **cells}
        print(f"  {data}: {len(windows)} windows", flush=True)
    return out


REPO = Path(__file__).resolve().parents[2]
#: largest difference (m) between pybullet's continuation and the episode over the episode's own
#: frames for the continuation to count as the same run
REPLAY_TOLERANCE = 1e-4
#: the report of a continuation pybullet lost (it left the finite numbers or the bounds)
LOST = {"holds": False, "same_run": False, "lost": True, "rest_drift": float("nan")}


def continuation_path(work: Path, folder: Path, seed: int, extra_steps: int) -> Path:
    return work / f"{folder.name}_plus{extra_steps}" / f"episode_{seed:06d}.npz"


def pybullet_continuation(folder: Path, seed: int, extra_steps: int, work: Path) -> Path | None:
    """The episode of ``seed`` in ``folder`` simulated again, ``extra_steps`` model steps longer,
    by ``hrn-pyg generate`` in a process of its own (pybullet keeps soft-body state per
    process); written once under ``work`` and reused. None when pybullet lost it (the seed's
    ``.rejected`` file there says why)."""
    path = continuation_path(work, folder, seed, extra_steps)
    if path.is_file():
        return path
    meta = json.loads((folder / "meta.json").read_text())
    scene_file = Path(meta.get("scene_file", ""))
    scene_file = scene_file if scene_file.is_absolute() else REPO / scene_file
    if not scene_file.is_file():
        raise FileNotFoundError(f"{folder}: its scene file {meta.get('scene_file')!r} is not there to simulate again")
    config = meta["config"]
    command = [sys.executable, "-m", "hrn_pyg.cli", "generate", "--scene-file", str(scene_file),
               "--episodes", "1", "--first-seed", str(seed), "--episode-steps", str(config["steps"] + extra_steps),
               "--substeps", str(config["substeps"]), "--physics-hz", str(config["physics_hz"]),
               "--pitch", str(config["pitch"]), "--out", str(path.parent), "--no-progress"]
    subprocess.run(command, check=True, cwd=REPO, stdout=subprocess.DEVNULL)
    return path if path.is_file() else None


def pybullet_rest_report(episode, continuation, steps: int) -> dict:
    """The stability check of pybullet's own ``steps`` frames after the end of ``episode``
    (from ``continuation``, the same seed run longer), as :func:`experiments.scores.rest_check`
    scores the model from there; ``replay_diff`` is how far the continuation strays from the
    episode over the episode's frames (above :data:`REPLAY_TOLERANCE` it is not the same run and
    the report says ``same_run`` false)."""
    truth = torch.as_tensor(episode["positions"], dtype=torch.float32)
    longer = torch.as_tensor(continuation["positions"], dtype=torch.float32)
    end = truth.shape[0]
    if longer.shape[0] < end - 1 + steps or longer.shape[1:] != truth.shape[1:]:
        raise ValueError(f"continuation has {tuple(longer.shape)}; needs {end - 1 + steps} frames of "
                         f"{tuple(truth.shape[1:])}")
    replay_diff = float((longer[:end] - truth).abs().max())
    # the state rest_check starts the model from, and pybullet's next ``steps`` frames (every node)
    graph = episode_state(continuation, start=end - 2, steps=steps)
    report = stability_report(graph[NODE].pos_seq[:, 3:].transpose(0, 1), graph, settle=0)
    return {**report, "replay_diff": replay_diff, "same_run": replay_diff <= REPLAY_TOLERANCE}


def rest_section(model, folders: list[Path], args) -> list[dict]:
    """1000 steps from the resting end of unseen episodes, a few per (mesh, material)."""
    wanted: dict[str, int] = defaultdict(int)
    rows = []
    for folder in folders:
        for path in sorted(folder.glob("episode_*.npz")):
            labels = object_labels(path)
            names = [f"{m} ({k})" for m, k in labels]
            if all(wanted[n] >= args.rest_episodes for n in names):
                continue
            episode = load_episode(path)
            t0 = time.perf_counter()
            report = rest_check(model, episode, args.rest_steps)
            if report is None:  # not at rest at the episode's end
                continue
            for n in names:
                wanted[n] += 1
            seed = int(episode["seed"])
            row = {"folder": folder.name, "seed": seed, "objects": names, **report,
                   "seconds": time.perf_counter() - t0}
            verdict = "holds" if report["holds"] else "FAILS"
            if args.pybullet_rest:
                longer = pybullet_continuation(folder, seed, args.rest_steps, Path(args.pybullet_rest))
                row["pybullet"] = (LOST if longer is None else
                                   pybullet_rest_report(episode, load_episode(longer), args.rest_steps))
                verdict += f" (pybullet {'holds' if row['pybullet']['holds'] else 'does not hold'})"
            rows.append(row)
            print(f"  rest {folder.name} seed {seed} {names}: {verdict}", flush=True)
    return rows


def time_section(model, folders: list[Path]) -> list[dict]:
    rows = []
    for folder in folders:
        meta = json.loads((folder / "meta.json").read_text())
        spec = read_scene_file(meta["scene_file"])
        path = sorted(folder.glob("episode_*.npz"))[0]
        seed = int(load_episode(path)["seed"])
        t0 = time.perf_counter()
        episode = simulate_episode(spec, seed)
        bullet = (time.perf_counter() - t0) / episode["forces"].shape[0]
        graph = episode_state(episode)
        forces = graph[NODE].force_seq.transpose(0, 1)
        steps = forces.shape[0]
        row = {"folder": folder.name, "seed": seed, "steps": steps, "pybullet_s_per_step": bullet}
        for name, sleep in (("model", DEFAULT_SLEEP), ("awake", None)):  # sleeping at rest, and not
            per_step = []
            with torch.no_grad():
                t = time.perf_counter()
                for _ in iterate(model, graph, steps, forces, sleep=sleep):
                    now = time.perf_counter()
                    per_step.append(now - t)
                    t = now
            row[f"{name}_s_per_step"] = sum(per_step) / steps  # the whole episode's time per step
            row[f"{name}_median_s_per_step"] = statistics.median(per_step)
        row["speedup"] = bullet / row["model_s_per_step"]
        rows.append(row)
        print(f"  time {folder.name}: model {row['model_s_per_step'] * 1e3:.1f} ms/step (all awake "
              f"{row['awake_s_per_step'] * 1e3:.1f}), pybullet {bullet * 1e3:.1f} ms/step", flush=True)
    return rows


def figures(model, folders: list[Path], out: Path) -> list[str]:
    written = []
    for folder in folders:
        window = windows_of(folder, "all", 50, 1000, 1)[0]
        path = out / f"unseen_{folder.name}.png"
        comparison_figure({"model": model}, window, path, times=(0, 10, 25, 50))
        written.append(str(path))
    return written


def markdown(result: dict, horizons: tuple[int, ...]) -> str:
    lines = []
    head = " | ".join(f"{m} t+{h} | ratio" for h in horizons for m in ERRORS)
    lines += [f"| mesh (material) | objects | {head} | diverged |", "|---|---|" + "---|---|" * 2 * len(horizons) + "---|"]
    unseen = result["unseen"]
    for block in ("unseen", "unseen_by_material"):
        for name, s in unseen[block].items():
            cells = " | ".join(f"{s[f'{m}@{h}']:.3g} | {s[f'ratio_{m}@{h}']:.2f}x" for h in horizons for m in ERRORS)
            label = name if block == "unseen" else f"**all {name}**"
            lines.append(f"| {label} | {s['objects']} | {cells} | {s[f'diverged@{max(horizons)}']} |")
    for name, s in unseen["own_test"].items():
        cells = " | ".join(f"{s[f'{m}@{h}']:.3g} | 1" for h in horizons for m in ERRORS)
        lines.append(f"| own {result['own_split']} split ({name}) | {s['objects']} | {cells} | {s[f'diverged@{max(horizons)}']} |")
    if result.get("specialists"):
        lines += ["", f"| {result['own_split']} split | " + " | ".join(f"{m} t+{h} model / specialist" for h in horizons for m in ERRORS)
                  + " |", "|---|" + "---|" * 2 * len(horizons)]
        for name, s in result["specialists"].items():
            cells = " | ".join(f"{s[f'{m}@{h}']['model']:.3g} / {s[f'{m}@{h}']['specialist']:.3g} "
                               f"({s[f'{m}@{h}']['ratio']:.2f}x)" for h in horizons for m in ERRORS)
            lines.append(f"| {name} | {cells} |")
    if result.get("rest"):
        lines += ["", "| folder | seed | objects | holds | max move (m) | lowest leaf (m) | rigid shape | drift (m) | "
                  "pybullet holds (drift, m) |", "|---|---|---|---|---|---|---|---|---|"]
        for r in result["rest"]:
            truth = r.get("pybullet")
            bullet = ("" if truth is None else "lost by pybullet" if truth.get("lost") else
                      f"{'yes' if truth['holds'] else 'no'} ({truth['rest_drift']:.3g})"
                      + ("" if truth["same_run"] else ", not the same run"))
            if "error" in r:
                lines.append(f"| {r['folder']} | {r['seed']} | {', '.join(r['objects'])} | no | {r['error']} | | | | {bullet} |")
                continue
            lines.append(f"| {r['folder']} | {r['seed']} | {', '.join(r['objects'])} | {'yes' if r['holds'] else 'no'} | "
                         f"{r['max_move']:.3g} | {r['min_z']:.3g} | {100 * r['rigid_shape']:.2f} % | {r['rest_drift']:.3g} | "
                         f"{bullet} |")
    if result.get("time"):
        lines += ["", "| folder | model ms/step (objects at rest sleep) | all awake | pybullet ms/step | "
                  "pybullet / model |", "|---|---|---|---|---|"]
        for r in result["time"]:
            lines.append(f"| {r['folder']} | {1e3 * r['model_s_per_step']:.1f} | {1e3 * r['awake_s_per_step']:.1f} | "
                         f"{1e3 * r['pybullet_s_per_step']:.1f} | {r['speedup']:.2f} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--unseen", action="append", default=[], help="a scene file's episode folder (repeatable)")
    parser.add_argument("--own", action="append", default=[], help="a training dataset; its test split (repeatable)")
    parser.add_argument("--own-split", default="test", choices=("test", "val"),
                        help="the split of the --own and --specialist folders (val when choosing between "
                             "checkpoints)")
    parser.add_argument("--specialist", action="append", default=[], metavar="DATA=PATH")
    parser.add_argument("--horizons", default="15,50")
    parser.add_argument("--stride", type=int, default=10)
    parser.add_argument("--limit", type=int, default=None, help="at most this many windows per folder")
    parser.add_argument("--batch", type=int, default=64, help="windows per batched rollout")
    parser.add_argument("--rest-episodes", type=int, default=2)
    parser.add_argument("--rest-steps", type=int, default=1000)
    parser.add_argument("--no-rest", action="store_true")
    parser.add_argument("--pybullet-rest", default=None, metavar="WORK",
                        help="also score pybullet's own continuation of each rest episode (simulated once "
                             "into WORK and reused)")
    parser.add_argument("--no-time", action="store_true")
    parser.add_argument("--quick", action="store_true", help="stride 30, no rest or time sections")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--mirror-average", choices=("x", "xy", "d4"), default=None,
                        help="apply the model averaged over these mirrors (HRNConfig.mirror_planes) everywhere")
    parser.add_argument("--ground-projection", choices=("on", "off", "deformable"), default=None,
                        help="apply the model with HRNConfig.ground_projection set so everywhere "
                             "(deformable: on for soft bodies and cloth only, ground_projection_rigid off)")
    for option, kind, meaning in APPLIED_FLAGS:
        flag = "--" + option.replace("_", "-")
        if kind == "switch":
            parser.add_argument(flag, choices=("on", "off"), default=None,
                                help=f"apply the model with HRNConfig.{option} set so ({meaning})")
        else:
            parser.add_argument(flag, type=float, default=None,
                                help=f"apply the model with HRNConfig.{option} set to this many pitches "
                                     f"({meaning})")
    parser.add_argument("--figures", default=None, help="folder for one picture per unseen folder")
    parser.add_argument("--out", default="benchmarks/results/unseen_shapes.json")
    args = parser.parse_args()
    if args.quick:
        args.stride, args.no_rest, args.no_time = 30, True, True
    args.horizons = tuple(int(h) for h in args.horizons.split(","))
    torch.set_num_threads(args.threads)
    specialists = {}
    for spec in args.specialist:
        data, sep, path = spec.partition("=")
        if not sep:
            parser.error(f"--specialist expects DATA=PATH, got {spec!r}")
        specialists[data] = path
    model = load_model(args.model)
    if args.mirror_average:
        model = with_applied_options(model, mirror_average=True, mirror_planes=args.mirror_average)
    if args.ground_projection:
        model = with_applied_options(model, ground_projection=args.ground_projection != "off",
                                     ground_projection_rigid=args.ground_projection == "on")
    for option, kind, _ in APPLIED_FLAGS:
        value = getattr(args, option)
        if value is not None:
            model = with_applied_options(model, **{option: value == "on" if kind == "switch" else value})
    unseen = [Path(f) for f in args.unseen]
    own = [Path(f) for f in args.own]
    started = time.perf_counter()
    result: dict = {"model": args.model, "unseen_folders": args.unseen, "own_folders": args.own,
                    "own_split": args.own_split, "horizons": list(args.horizons), "stride": args.stride,
                    "limit": args.limit, "mirror_average": args.mirror_average,
                    **{option: getattr(model.config, option, HRN_DEFAULTS[option]) for option in RECORDED_OPTIONS},
                    "machine": f"{platform.machine()}, {torch.get_num_threads()} torch thread(s)"}
    print("errors on unseen meshes and the own test split", flush=True)
    result["unseen"] = unseen_section(model, unseen, own, args)
    print("against the specialists", flush=True)
    result["specialists"] = specialist_section(model, specialists, args)
    if not args.no_rest:
        print(f"{args.rest_steps} steps from rest", flush=True)
        result["rest"] = rest_section(model, unseen, args)
    if not args.no_time:
        print("time per step", flush=True)
        result["time"] = time_section(model, unseen)
    if args.figures:
        result["figures"] = figures(model, unseen, Path(args.figures))
    result["seconds"] = time.perf_counter() - started
    table = markdown(result, args.horizons)
    result["table"] = table
    atomic_write_json(args.out, result)
    print(table)
    print(f"wrote {args.out} ({result['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
