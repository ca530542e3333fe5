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
   chosen by chance.

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
#: the benchmarks of the second set, run only when its folders exist
SECOND_SET = ("unseen2.json", "unseen2_shapes.json")
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
    unseen2 = unseen_shapes_command(model, out / "unseen2.json", [data / n for n in UNSEEN2], data / "shapes_drop",
                                    "val", "--no-time", *rest_options)
    baseline = unseen_shapes_command(BASELINE, out / "unseen2_shapes.json",
                                     [data / n for n in UNSEEN2 if "cloth" not in n], data / "shapes_drop", "val",
                                     "--no-rest", "--no-time")
    return {"rest.json": rest, "parity.json": parity, "cloth.json": cloth,
            "unseen2.json": unseen2, "unseen2_shapes.json": baseline}


def summary(out: Path) -> str:
    """The one-table summary of the JSON files under ``out`` (missing ones are left out)."""
    lines = ["| measure | value |", "|---|---|"]
    lines += rest_lines(read_json(out / "rest.json"))
    lines += parity_lines(read_json(out / "parity.json"))
    lines += cloth_lines(read_json(out / "cloth.json"))
    unseen2 = read_json(out / "unseen2.json")
    lines += rest_lines(unseen2) + unseen_lines(unseen2, read_json(out / "unseen2_shapes.json"))
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


def pooled_error(result: dict, folders: Sequence[str], material: str, key: str) -> float:
    """The mean ``key`` error (e.g. ``"position@50"``) of ``material``'s objects over the episode
    folders ``folders`` only, pooled from ``experiments/generalist/unseen_shapes.py``'s per-folder means
    (each weighted by its finite values). Raises ValueError when ``result`` has no per-folder
    errors or no such object in those folders."""
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
    parser.add_argument("--only", default="", help="rest,parity,cloth,unseen2,unseen2_shapes: run only these "
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
                         "choose from rest, parity, cloth, unseen2, unseen2_shapes")
    missing = [name for name in (*UNSEEN, "shapes_drop", *(f for f, _ in SPECIALISTS))
               if not (args.data / name).is_dir()]
    if missing:
        raise FileNotFoundError(f"--data {args.data}: no folder {', '.join(missing)}")
    named = commands(args.model, args.data, args.out, args.rest_episodes, args.pybullet_rest)
    absent = [name for name in UNSEEN2 if not (args.data / name).is_dir()]
    if absent:
        if wanted & set(SECOND_SET):
            raise FileNotFoundError(f"--data {args.data}: no folder {', '.join(absent)}")
        print(f"the second mesh set is not run: no folder {', '.join(absent)} under {args.data} "
              "(data/shapes/unseen/validation2_*.toml say how to make them)", flush=True)
        named = {k: v for k, v in named.items() if k not in SECOND_SET}
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
