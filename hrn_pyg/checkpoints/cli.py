"""``hrn-pyg models``: the shipped models, each with what it was trained on.

One row per model of :func:`hrn_pyg.checkpoints.shipped_models`, within 100 columns: its name
(and aliases), the first dataset it was trained on and how many more, their materials, pitch and
object counts (:mod:`hrn_pyg.checkpoints.domain`) and its calibrated sampling rate and modules.
``hrn-pyg models NAME`` prints one model's every field: all its datasets, object sizes (m across),
the fastest leaf, its file and hash, and its test errors where the manifest has them. ``--json``
prints the same as JSON. Any of the names loads with ``hrn_pyg.load_model(name)`` or
``--model name``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence

from hrn_pyg.checkpoints import ShippedModel, shipped_models

COLUMNS = ("model", "trained on", "materials", "pitch (m)", "objects", "sampling rate")
#: the table's width in characters at most (a cell too long is cut with "...")
WIDTH = 100


def pitch_cell(model: ShippedModel) -> str:
    d = model.domain
    if d is None:
        return "-"
    return f"{d.pitch_range[0]:g}-{d.pitch_range[1]:g}" if d.pitch_range else ", ".join(f"{p:g}" for p in d.pitches) or "-"


def model_row(model: ShippedModel) -> tuple[str, ...]:
    """The table's cells for one model (``-`` where the manifest records nothing): the first
    dataset and how many more, the calibrated rate alone (``hrn-pyg models NAME`` lists the
    datasets and the rate's modules)."""
    d = model.domain
    objects = "-" if d is None or d.objects is None else (
        f"{d.objects[0]}" if d.objects[0] == d.objects[1] else f"{d.objects[0]}-{d.objects[1]}")
    rate = "-" if model.rate is None else f"{model.rate:g}"
    datasets = model.datasets[0] + (f" +{len(model.datasets) - 1}" if len(model.datasets) > 1 else "") \
        if model.datasets else "-"
    return (model.name, datasets, "-" if d is None else ",".join(d.materials) or "-", pitch_cell(model), objects, rate)


def table(models: Sequence[ShippedModel], width: int = WIDTH) -> str:
    """A text table of ``models``, columns aligned, each line at most ``width`` characters (the
    widest cells but the name cut with ``...``), then a line naming the aliases."""
    rows = [COLUMNS, *(model_row(m) for m in models)]
    widths = [max(len(r[i]) for r in rows) for i in range(len(COLUMNS))]
    while sum(widths) + 2 * (len(widths) - 1) > width:  # a few columns: shrink the widest by one
        widest = max(range(1, len(widths)), key=widths.__getitem__)
        widths[widest] -= 1

    def cut(text: str, w: int) -> str:
        return text if len(text) <= w else text[: w - 3] + "..."

    lines = ["  ".join(cut(c, w).ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    aliases = ", ".join(f"{a} = {m.name}" for m in models for a in m.aliases)
    return "\n".join([lines[0], "  ".join("-" * w for w in widths), *lines[1:]]) + "\n" + (
        f"aliases: {aliases}\n" if aliases else "")


def details(model: ShippedModel) -> str:
    """Everything recorded of one model, a line per field."""
    d = model.domain
    fields = [("model", model.name), ("aliases", ", ".join(model.aliases) or "-"), ("file", str(model.path)),
              ("sha256", model.sha256 or "-"), ("scene", model.scene or "-"),
              ("trained on", ", ".join(model.datasets) or "-"),
              ("materials", "-" if d is None else ", ".join(d.materials) or "-"), ("pitch (m)", pitch_cell(model)),
              ("objects", model_row(model)[4]),
              ("size (m across)", "-" if d is None or d.object_size is None
               else "-".join(dict.fromkeys(f"{v:.2g}" for v in d.object_size))),
              ("fastest leaf (m/s)", "-" if d is None or d.speed is None else f"{d.speed:.2g}"),
              ("sampling rate", "-" if model.rate is None else f"{model.rate:g} on {', '.join(model.modules)}"),
              ("test errors", ", ".join(f"{k} {v:.3g}" for k, v in model.test) or "none recorded")]
    return "".join(f"{k + ':':<20}{v}\n" for k, v in fields)


def model_record(model: ShippedModel) -> dict:
    """One model as JSON (``--json``)."""
    return {"name": model.name, "aliases": list(model.aliases), "path": str(model.path), "scene": model.scene,
            "datasets": list(model.datasets), "domain": None if model.domain is None else model.domain.to_dict(),
            "rate": model.rate, "modules": list(model.modules), "test": dict(model.test), "sha256": model.sha256}




def run(args: argparse.Namespace) -> int:
    models = shipped_models()
    name = getattr(args, "name", None)
    if name is not None:
        chosen = [m for m in models if name in (m.name, *m.aliases)]
        if not chosen:
            raise ValueError(f"no shipped model {name!r}; the shipped models: "
                             f"{', '.join(n for m in models for n in (m.name, *m.aliases))}")
        print(json.dumps(model_record(chosen[0]), indent=2) if args.json else details(chosen[0]), end="\n" if args.json else "")
        return 0
    if args.json:
        print(json.dumps([model_record(m) for m in models], indent=2))
    else:
        print(table(models), end="")
    return 0
