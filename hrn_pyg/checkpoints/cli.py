"""``hrn-pyg models``: the shipped models, each with what it was trained on.

One row per model of :func:`hrn_pyg.checkpoints.shipped_models`: its name (and aliases), the
datasets it was trained on, their materials, pitch, object sizes (m across) and counts and the
fastest leaf (:mod:`hrn_pyg.checkpoints.domain`), its calibrated sampling rate and modules, and
its test errors where the manifest has them. ``--json`` prints the same as JSON. Any of the
names loads with ``hrn_pyg.load_model(name)`` or ``--model name``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence

from hrn_pyg.checkpoints import ShippedModel, shipped_models

COLUMNS = ("model", "trained on", "materials", "pitch (m)", "objects", "size (m across)",
           "fastest leaf (m/s)", "sampling rate", "test errors")


def model_row(model: ShippedModel) -> tuple[str, ...]:
    """The table's cells for one model (``-`` where the manifest records nothing)."""
    d = model.domain
    name = model.name + (f" (= {', '.join(model.aliases)})" if model.aliases else "")
    objects = "-" if d is None or d.objects is None else (
        f"{d.objects[0]}" if d.objects[0] == d.objects[1] else f"{d.objects[0]}-{d.objects[1]}")
    size = "-" if d is None or d.object_size is None else "-".join(dict.fromkeys(f"{v:.2g}" for v in d.object_size))
    rate = "-" if model.rate is None else f"{model.rate:g} on {','.join(model.modules)}"
    test = ", ".join(f"{k} {v:.3g}" for k, v in model.test) or "-"
    return (name, ", ".join(model.datasets) or "-",
            "-" if d is None else ", ".join(d.materials) or "-",
            "-" if d is None else (f"{d.pitch_range[0]:g}-{d.pitch_range[1]:g}" if d.pitch_range
                                   else ", ".join(f"{p:g}" for p in d.pitches) or "-"),
            objects, size, "-" if d is None or d.speed is None else f"{d.speed:.2g}", rate, test)


def table(models: Sequence[ShippedModel]) -> str:
    """A text table of ``models``, columns aligned."""
    rows = [COLUMNS, *(model_row(m) for m in models)]
    widths = [max(len(r[i]) for r in rows) for i in range(len(COLUMNS))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    return "\n".join([lines[0], "  ".join("-" * w for w in widths), *lines[1:]]) + "\n"


def model_record(model: ShippedModel) -> dict:
    """One model as JSON (``--json``)."""
    return {"name": model.name, "aliases": list(model.aliases), "path": str(model.path), "scene": model.scene,
            "datasets": list(model.datasets), "domain": None if model.domain is None else model.domain.to_dict(),
            "rate": model.rate, "modules": list(model.modules), "test": dict(model.test), "sha256": model.sha256}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table (default: a table)")


def run(args: argparse.Namespace) -> int:
    models = shipped_models()
    if args.json:
        print(json.dumps([model_record(m) for m in models], indent=2))
    else:
        print(table(models), end="")
    return 0
