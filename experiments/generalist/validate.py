"""The validation suite a candidate of the next generalist is chosen by: one table per model.

Three benchmarks, all on validation episodes (model selection; the test files are scored once,
for the final table), each the network alone, one torch thread:

1. **Rest** (``experiments/generalist/unseen_shapes.py``): 1000 steps from the resting end of the first
   ``--rest-episodes`` episodes per mesh and material of the unseen validation folders
   (``unseen_val_rigid``, ``unseen_val_soft``, ``unseen_val_cloth``), scored by the package's
   stability check, and pybullet's own continuation of each (the same seed run 1000 steps
   longer, made once under ``--pybullet-rest``, default ``DATA/pybullet_rest``) scored by the
   same check; the table gives the episodes that hold per folder, those pybullet holds, and how
   many of those the model holds.
2. **The specialists** (the same script): position and shape error at t+15 and t+50 on the
   validation splits of cube_collision, soft_bounce and multi_material, as multiples of the
   shipped specialist's.
3. **Cloth inside** (``benchmarks/cloth_pass_through.py``): cloth leaves inside another object a
   step on the first six unseen cloth episodes, against pybullet's own count.
4. **A second mesh set** (``unseen_val2_rigid``, ``unseen_val2_soft``, ``unseen_val2_cloth``:
   random_urdfs objects 801, 881 and 022, ``data/shapes/unseen/validation2_*.toml``), when its
   folders are under ``--data``: every window's position and shape error beside the own
   validation split and beside ``shapes_d4.pt``'s on the same rigid and soft windows (the one-pass
   bar), and rest as in 1: more meshes, so that a model that holds on the first two alone is not
   chosen by chance. A **third mesh set** (``unseen_val3_*``: random_urdfs 050, 870 and 987,
   ``data/shapes/unseen/validation3_*.toml``) is run the same way when its folders are there, and
   the rigid and soft ratios to ``shapes_d4.pt`` are also given pooled over both sets' windows.
5. **Piles at rest** (``experiments/many_objects.py``): piles of 10 of the second and third sets'
   meshes (:data:`PILE_MESHES`), four seeds, 240 steps for pybullet to settle them, then 1000 steps of
   the model from each settled pile, scored by the same stability check: the validation twin of
   the final table's pile bar. The piles are kept under ``DATA/validation_piles``.

Each benchmark writes its JSON under ``--out``; a rerun skips the ones whose JSON is there, so a
stopped run continues. Run::

    python -m experiments.generalist.validate --model runs/generalist/shapes_next/model.pt \\
        --data data --out runs/generalist/validation/shapes_next

``--data`` is the folder holding the datasets of ``data/recipes.toml`` and the unseen validation
folders (``hrn-pyg generate`` commands in the scene files' headers). About 20 minutes a model on
a fast core, and as long again for the second mesh set (half of it ``shapes_d4.pt``'s eight passes a
step).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

from experiments.command import script_main

REPO = Path(__file__).resolve().parents[2]
#: the unseen validation folders, by material
UNSEEN = ("unseen_val_rigid", "unseen_val_soft", "unseen_val_cloth")
#: the second set of unseen validation folders, by material (optional)
UNSEEN2 = ("unseen_val2_rigid", "unseen_val2_soft", "unseen_val2_cloth")
#: the third set of unseen validation folders, by material (optional)
UNSEEN3 = ("unseen_val3_rigid", "unseen_val3_soft", "unseen_val3_cloth")
#: the further mesh sets, by the name of their benchmarks (``NAME.json``, ``NAME_shapes.json``),
#: each run only when its folders exist
MESH_SETS = {"unseen2": UNSEEN2, "unseen3": UNSEEN3}
#: the ordinal a message names each further set by
SET_ORDINALS = {"unseen2": "second", "unseen3": "third"}
#: the meshes of the validation piles: the second and third sets' (random_urdfs 801, 881, 022,
#: 050, 870, 987)
PILE_MESHES = tuple(f"pybullet_data:random_urdfs/{n}/{n}.obj" for n in ("801", "881", "022", "050", "870", "987"))
#: objects per validation pile (the final table's pile bar holds piles of this size)
PILE_OBJECTS = 10
#: the eight-pass generalist the one-pass bar compares with (a shipped name)
BASELINE = "shapes_d4"
#: the specialists the generalist is held to: (dataset folder, shipped model)
SPECIALISTS = (("cube_collision", "cube_collision"), ("soft_bounce", "soft_bounce"),
               ("multi_material", "multi_material"))
#: the four errors compared with a specialist's, in the tables' order
PARITY_KEYS = ("position@15", "shape@15", "position@50", "shape@50")


def unseen_shapes_command(model: str, out: Path, unseen: Sequence[Path] = (), own: Path | None = None,
                          split: str = "val", *options: str) -> list[str]:
    """``experiments/generalist/unseen_shapes.py`` on ``model``: each folder of ``unseen`` (``--unseen``), the
    ``split`` of ``own`` (``--own``) and the specialists' splits, then ``options``, into ``out``."""
    return [sys.executable, "-m", "experiments.generalist.unseen_shapes", "--model", model,
            *[a for folder in unseen for a in ("--unseen", str(folder))],
            *(["--own", str(own)] if own is not None else []), "--own-split", split, *options, "--out", str(out)]


def specialist_options(data: Path) -> list[str]:
    """``--specialist FOLDER=MODEL`` for each of :data:`SPECIALISTS` under ``data``."""
    return [a for folder, name in SPECIALISTS for a in ("--specialist", f"{data / folder}={name}")]


def commands(model: str, data: Path, out: Path, rest_episodes: int,
             pybullet_rest: Path | None = None) -> dict[str, list[str]]:
    """The benchmark command lines, by the name of the JSON each writes under ``out``."""
    python = [sys.executable]
    rest_options = ("--rest-episodes", str(rest_episodes), "--pybullet-rest", str(pybullet_rest or data / "pybullet_rest"))
    rest = unseen_shapes_command(model, out / "rest.json", [data / n for n in UNSEEN], data / "shapes_drop", "val",
                                 "--limit", "2", "--no-time", *rest_options)
    parity = unseen_shapes_command(model, out / "parity.json", (), None, "val", *specialist_options(data),
                                   "--no-rest", "--no-time")
    cloth = [*python, "-m", "benchmarks.cloth_pass_through", "--model", model,
             "--episodes", str(data / "unseen_val_cloth"), "--limit", "6", "--awake",
             "--out", str(out / "cloth.json")]
    further = {}
    for name, folders in MESH_SETS.items():
        further[f"{name}.json"] = unseen_shapes_command(model, out / f"{name}.json", [data / n for n in folders],
                                                        data / "shapes_drop", "val", "--no-time", *rest_options)
        further[f"{name}_shapes.json"] = unseen_shapes_command(
            BASELINE, out / f"{name}_shapes.json", [data / n for n in folders if "cloth" not in n],
            data / "shapes_drop", "val", "--no-rest", "--no-time")
    piles = [*python, "-m", "experiments.many_objects", "--model", model, "--counts", str(PILE_OBJECTS),
             "--meshes", ",".join(PILE_MESHES), "--steps", "240", "--episodes", "4", "--rest-steps", "1000",
             "--repeats", "1", "--work", str(data / "validation_piles"), "--out", str(out / "piles.json")]
    return {"rest.json": rest, "parity.json": parity, "cloth.json": cloth, **further, "piles.json": piles}


def summary(out: Path) -> str:
    """The one-table summary of the JSON files under ``out`` (missing ones are left out)."""
    lines = ["| measure | value |", "|---|---|"]
    lines += rest_lines(read_json(out / "rest.json"))
    lines += parity_lines(read_json(out / "parity.json"))
    lines += cloth_lines(read_json(out / "cloth.json"))
    pairs = []
    for name in MESH_SETS:
        unseen, baseline = read_json(out / f"{name}.json"), read_json(out / f"{name}_shapes.json")
        lines += rest_lines(unseen) + unseen_lines(unseen, baseline)
        if unseen is not None and baseline is not None:
            pairs.append((unseen, baseline))
    if len(pairs) > 1:
        lines += [f"| unseen {material} meshes, {len(pairs)} sets pooled / {BASELINE}.pt, position t+15, t+50 | "
                  f"{', '.join(f'{r:.2f}' for r in pair)} |" for material, pair in pooled_ratios(pairs).items()]
    lines += pile_lines(read_json(out / "piles.json"))
    return "\n".join(lines)


def rest_lines(rest: dict | None) -> list[str]:
    """Table rows of ``experiments/generalist/unseen_shapes.py``'s rest check, one per folder: the episodes
    that hold, and with pybullet's continuation those pybullet holds and how many of those the
    model holds."""
    by_folder: dict[str, list[dict]] = {}
    for row in (rest or {}).get("rest") or []:
        by_folder.setdefault(row["folder"], []).append(row)
    lines = []
    for folder, rows in by_folder.items():
        said = f"{sum(bool(r['holds']) for r in rows)} of {len(rows)} hold"
        truth = [r for r in rows if "pybullet" in r]
        if truth:
            held = [r for r in truth if r["pybullet"]["holds"] and r["pybullet"]["same_run"]]
            said += (f"; pybullet holds {len(held)} of {len(truth)}, the model "
                     f"{sum(bool(r['holds']) for r in held)} of those {len(held)}")
        lines.append(f"| rest, {folder} | {said} |")
    return lines


def pile_lines(piles: dict | None) -> list[str]:
    """Table rows of ``experiments/many_objects.py``'s rest section: per pile size, the settled
    piles that hold 1000 steps and the largest drift (a pile pybullet never settled counts as not
    held, as in the final table)."""
    lines = []
    for row in (piles or {}).get("rows", []):
        rows = row.get("rest") or []
        at_rest = [r for r in rows if r["at_rest"]]
        held = sum(bool(r.get("holds")) for r in at_rest)
        drift = max((r.get("rest_drift", float("nan")) for r in at_rest), default=float("nan"))
        lines.append(f"| 1000 steps from rest, piles of {row['objects']} | {held} of {len(rows)} hold "
                     f"({len(rows) - len(at_rest)} not settled), largest drift {100 * drift:.1f} cm |")
    return lines


def parity_lines(parity: dict | None) -> list[str]:
    """Table rows of the model's errors as multiples of each specialist's."""
    lines = []
    for name, cells in (parity or {}).get("specialists", {}).items():
        ratios = [f"{cells[key]['ratio']:.2f}" for key in PARITY_KEYS if key in cells]
        lines.append(f"| {name} / specialist (position, shape at t+15; position, shape at t+50) | "
                     f"{', '.join(ratios)} |")
    return lines


def _folder_names(result: dict | None) -> list[str]:
    return [Path(f).name for f in (result or {}).get("unseen_folders", [])]


def folder_sums(result: dict, folders: Sequence[str], material: str, key: str) -> tuple[float, int]:
    """``(sum, count)``: the ``key`` error (e.g. ``"position@50"``) of ``material``'s objects summed
    over the episode folders ``folders`` of ``experiments/generalist/unseen_shapes.py``'s JSON, each
    folder's mean weighted by its finite values, and how many those are. Raises ValueError when
    ``result`` has no per-folder errors."""
    by_folder = (result.get("unseen") or {}).get("unseen_by_folder")
    if by_folder is None:
        raise ValueError(f"{result.get('model')}: no per-folder errors in its unseen_shapes.py JSON; run it again")
    horizon = key.split("@")[1]
    total, count = 0.0, 0
    for folder in folders:
        stats = by_folder.get(f"{folder} ({material})")
        if stats:
            finite = stats["objects"] - stats[f"diverged@{horizon}"]
            total, count = total + stats[key] * finite, count + finite
    return total, count


def pooled_error(result: dict, folders: Sequence[str], material: str, key: str) -> float:
    """The mean ``key`` error of ``material``'s objects over the episode folders ``folders`` only
    (:func:`folder_sums`). Raises ValueError when there is no such object in those folders."""
    total, count = folder_sums(result, folders, material, key)
    if count == 0:
        raise ValueError(f"no {material} object in {', '.join(folders)}")
    return total / count


def unseen_ratios(unseen: dict | None, baseline: dict | None) -> tuple[float | None, dict[str, list[float]]]:
    """From ``experiments/generalist/unseen_shapes.py``'s JSON of a model (``unseen``) and of ``shapes_d4.pt``
    (``baseline``): the rigid meshes' position error at t+15 as a multiple of the own split's (None
    without rigid meshes), and per material (rigid, soft) the position errors at t+15 and t+50 as
    multiples of ``shapes_d4.pt``'s on the same windows: the model's errors are pooled over the
    baseline's folders only (the model's JSON may hold more, e.g. the cloth scenes' rigid and soft
    objects, which ``shapes_d4.pt`` never ran)."""
    by_material = ((unseen or {}).get("unseen") or {}).get("unseen_by_material", {})
    old = ((baseline or {}).get("unseen") or {}).get("unseen_by_material", {})
    own = by_material["rigid"].get("ratio_position@15") if "rigid" in by_material else None
    shared = _folder_names(baseline)
    ratios = {}
    for material in ("rigid", "soft"):
        if material in by_material and material in old:
            if shared and _folder_names(unseen) != shared:
                model = [pooled_error(unseen, shared, material, f"position@{h}") for h in (15, 50)]
            else:  # the same folders: the per-material means are on the same windows
                model = [by_material[material][f"position@{h}"] for h in (15, 50)]
            ratios[material] = [m / old[material][f"position@{h}"] for m, h in zip(model, (15, 50), strict=True)]
    return own, ratios


def pooled_ratios(pairs: Sequence[tuple[dict, dict]]) -> dict[str, list[float]]:
    """Per material (rigid, soft): the model's position errors at t+15 and t+50 pooled over the
    windows of several mesh sets, as multiples of ``shapes_d4.pt``'s pooled over the same windows.
    ``pairs``: ``(model JSON, baseline JSON)`` of each set, pooled over the baseline's folders
    (:func:`folder_sums`)."""
    ratios = {}
    for material in ("rigid", "soft"):
        pooled = []
        for key in ("position@15", "position@50"):
            sums = [[folder_sums(result, _folder_names(baseline), material, key) for result in (unseen, baseline)]
                    for unseen, baseline in pairs]
            (model, model_n), (base, base_n) = [(sum(s[i][0] for s in sums), sum(s[i][1] for s in sums))
                                                for i in (0, 1)]
            pooled.append(None if not (model_n and base_n) else (model / model_n) / (base / base_n))
        if None not in pooled:
            ratios[material] = pooled
    return ratios


def unseen_lines(unseen: dict | None, baseline: dict | None) -> list[str]:
    """Table rows of :func:`unseen_ratios`."""
    own, ratios = unseen_ratios(unseen, baseline)
    lines = [] if own is None else [f"| unseen rigid meshes / own validation split, position t+15 | {own:.2f} |"]
    return lines + [f"| unseen {material} meshes / {BASELINE}.pt, position t+15, t+50 | "
                    f"{', '.join(f'{r:.2f}' for r in pair)} |"
                    for material, pair in ratios.items()]


def cloth_lines(cloth: dict | None) -> list[str]:
    """Table rows of ``benchmarks/cloth_pass_through.py``: cloth leaves inside a step, pybullet's beside."""
    lines = []
    for run in (cloth or {}).get("runs", []):
        for name, folder in run["folders"].items():
            model, truth = folder["summary"]["model"], folder["summary"]["pybullet"]
            said = "diverged" if model is None else f"{model['mean']:.2f}"
            lines.append(f"| cloth leaves inside a step, {name} (pybullet) | {said} ({truth['mean']:.2f}) |")
    return lines


def read_json(path: Path) -> dict | None:
    """A JSON file's content, or None when there is no such file."""
    return json.loads(path.read_text()) if path.is_file() else None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, help="a checkpoint path or a shipped model's name")
    parser.add_argument("--data", type=Path, default=Path("data"), help="folder of the episode folders")
    parser.add_argument("--out", type=Path, required=True, help="folder for the benchmarks' JSON")
    parser.add_argument("--rest-episodes", type=int, default=6, help="rest episodes per mesh and material")
    parser.add_argument("--only", default="", help="rest,parity,cloth,unseen2,unseen2_shapes,unseen3,unseen3_shapes,piles: "
                                                   "run only these "
                                                   "(default: all)")
    parser.add_argument("--pybullet-rest", type=Path, default=None,
                        help="folder for pybullet's continuations of the rest episodes, shared by every "
                             "model (default: DATA/pybullet_rest)")


def run(args: argparse.Namespace) -> int:
    if args.rest_episodes < 1:
        raise ValueError("--rest-episodes must be >= 1")
    wanted = {f"{n}.json" for n in args.only.split(",") if n}
    unknown = sorted(wanted - set(commands("", args.data, args.out, 1)))
    if unknown:
        raise ValueError(f"--only: unknown {', '.join(n.removesuffix('.json') for n in unknown)}; "
                         f"choose from {', '.join(n.removesuffix('.json') for n in commands('', args.data, args.out, 1))}")
    missing = [name for name in (*UNSEEN, "shapes_drop", *(f for f, _ in SPECIALISTS))
               if not (args.data / name).is_dir()]
    if missing:
        raise FileNotFoundError(f"--data {args.data}: no folder {', '.join(missing)}")
    named = commands(args.model, args.data, args.out, args.rest_episodes, args.pybullet_rest)
    for name, folders in MESH_SETS.items():
        absent = [folder for folder in folders if not (args.data / folder).is_dir()]
        if not absent:
            continue
        jsons = {f"{name}.json", f"{name}_shapes.json"}
        if wanted & jsons:
            raise FileNotFoundError(f"--data {args.data}: no folder {', '.join(absent)}")
        print(f"the {SET_ORDINALS[name]} mesh set is not run: no folder {', '.join(absent)} under {args.data} "
              f"(data/shapes/unseen/validation{name.removeprefix('unseen')}_*.toml say how to make them)", flush=True)
        named = {k: v for k, v in named.items() if k not in jsons}
    run_missing(named, args.out, wanted)
    print(summary(args.out))
    return 0


def run_missing(named: dict[str, list[str]], out: Path, wanted: set[str]) -> None:
    """Run each command of ``named`` (by the JSON it writes under ``out``) that is ``wanted``
    (all when empty) and whose JSON is not there yet, one after the other, in the repository."""
    out.mkdir(parents=True, exist_ok=True)
    for name, command in named.items():
        if (wanted and name not in wanted) or (out / name).is_file():
            continue
        print(" ".join(command), flush=True)
        subprocess.run(command, check=True, cwd=REPO)


if __name__ == "__main__":
    sys.exit(script_main("python -m experiments.generalist.validate", __doc__.splitlines()[0], add_arguments, run))
