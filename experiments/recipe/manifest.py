"""The records of ``python -m experiments.recipe``: each run's ``recipe.json`` and the checkpoints'
manifest.

A run folder's ``recipe.json`` (:data:`RUN_RECORD`) holds its identity and every train
invocation (command, device, seconds, exit code). ``manifest.json`` (:data:`MANIFEST_NAME`)
holds one entry per shipped model: dataset recipe, commands, steps, device, wall and logged
training seconds, averaged stages, calibrated rate and modules, and the checkpoint's SHA-256,
built by :func:`model_entry` and written atomically when it changes (:func:`update_manifest`).
"""

from __future__ import annotations

import csv
import hashlib
import json
import shutil
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from experiments.recipe.schema import CALIBRATED_NAME, DatasetRecipe, ModelRecipe, shown
from hrn_pyg.utils.files import atomic_write, atomic_write_json

#: where the shipped checkpoints live
MANIFEST_NAME = "manifest.json"
#: per-run record of what the run folder was trained with, and of every train invocation
RUN_RECORD = "recipe.json"


def read_json(path: Path) -> dict[str, Any] | None:
    """The JSON object in ``path``; None when the file is missing or not valid JSON."""
    try:
        return json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def logged_train_seconds(metrics: Path) -> float | None:
    """The training seconds a run's ``metrics.csv`` logged, summed over its sittings (a ``seconds``
    value below the row before starts a new sitting; a sitting counts its last row); None when the
    file or the column is missing."""
    try:
        with open(metrics, newline="") as fh:
            values = [float(row["seconds"]) for row in csv.DictReader(fh) if row.get("seconds")]
    except (FileNotFoundError, KeyError, ValueError):
        return None
    if not values:
        return None
    ends = [a for a, b in zip(values, values[1:]) if b < a]
    return sum(ends) + values[-1]


def sha256(path: Path) -> str:
    """The hex SHA-256 digest of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def copy_atomic(source: Path, target: Path) -> None:
    """Copy ``source`` to ``target`` so that a reader never sees half a file."""
    with open(source, "rb") as src:
        atomic_write(target, lambda fh: shutil.copyfileobj(src, fh))


def model_entry(model: ModelRecipe, dataset: DatasetRecipe, data_dir: Path, runs_dir: Path, run: Path,
                digest: str, train_command: Callable[[int], Sequence[str]],
                calibrate_command: Callable[[], Sequence[str]]) -> dict[str, Any]:
    """A model's manifest entry from the records of its run folders under ``runs_dir``: ``dataset``,
    final ``run`` folder and the checkpoint's ``digest``; ``train_command(stage)`` and
    ``calibrate_command()`` give the commands of unfinished steps."""
    folders = [runs_dir / model.run_name(i) for i in range(model.num_stages)]
    # per stage: the invocations that ended, and the command that made its model.pt (its
    # last invocation), as one would type it afresh
    done = [[i for i in (read_json(f / RUN_RECORD) or {}).get("invocations", []) if i.get("seconds") is not None]
            for f in folders]
    commands = [shown([a for a in (d[-1]["args"] if d else train_command(i)) if a != "--resume"])
                for i, d in enumerate(done)]
    steps = [(read_json(f / "config.json") or {}).get("train", {}).get("steps") for f in folders]
    invocations = [i for d in done for i in d]
    logged = [t for t in (logged_train_seconds(f / "metrics.csv") for f in folders) if t is not None]
    stages = {"stage_commands": commands, "stage_steps": steps} if model.num_stages > 1 else {}
    return {
        "name": model.name,
        "aliases": list(model.aliases),
        "dataset": dataset.to_dict(),
        "generate_command": shown(dataset.generate_args(data_dir)),
        "train_command": commands[-1],
        "steps": steps[-1],
        "device": ",".join(sorted({i["device"] for i in invocations})),
        "wall_seconds": round(sum(i["seconds"] for i in invocations), 3),
        "train_invocations": len(invocations),
        **({"logged_train_seconds": round(sum(logged), 3)} if logged else {}),
        "sha256": digest,
        **stages,
        **({"averaged": {"stages": [s for s, _ in model.average], "weights": [w for _, w in model.average]}}
           if model.average else {}),
        **({"applied": dict(model.apply)} if model.apply else {}),
        **calibration_entry(model, run, calibrate_command),
    }


def calibration_entry(model: ModelRecipe, run: Path, calibrate_command: Callable[[], Sequence[str]]) -> dict[str, Any]:
    """The manifest's calibration fields: the command and the chosen rate and modules."""
    if not model.calibrate:
        return {}
    from hrn_pyg.sampling.calibrate import calibration_record  # imports torch

    record = calibration_record(run / CALIBRATED_NAME) or {}
    chosen = {k: record.get(k) for k in ("rate", "modules", "spread_ratio_median", "seeds")}
    return {"calibrate_command": shown(calibrate_command()), "calibrated": chosen}


def update_manifest(path: Path, name: str, entry: dict[str, Any]) -> None:
    """Set model ``name``'s entry in the manifest at ``path``, stamped with the time, rewriting the
    file (atomically) only when it differs; an entry without ``domain`` keeps the old one's for the
    same ``sha256``. Callers from several threads hold one lock."""
    manifest = read_json(path) or {}
    entries = manifest.get("checkpoints", {})
    old = dict(entries.get(name, {}))
    old.pop("updated", None)
    if "domain" not in entry and "domain" in old and old.get("sha256") == entry.get("sha256"):
        entry = {**entry, "domain": old["domain"]}
    if old == entry:
        return
    entries[name] = {**entry, "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    atomic_write_json(path, {"about": "how each checkpoint here was made: `make checkpoints` "
                                      "from data/recipes.toml", "checkpoints": dict(sorted(entries.items()))})
