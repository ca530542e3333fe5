"""The shipped checkpoints and how to load any model checkpoint.

This folder holds the trained models the package ships (``<name>.pt``, remade by
``make checkpoints`` from ``data/recipes.toml``; ``manifest.json`` says how each was made).
:func:`load_model` reads a model checkpoint written by ``hrn-pyg train`` (weights-only
unpickling, so loading cannot run code); :func:`checkpoint_path` finds a shipped one by name and :func:`resolve_model` the one a
command should use.
Evaluation, sampling and RL load models through here, without the training stack.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch

from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.nn.networks import applied_options, network_from_dict
from hrn_pyg.utils.checkpoint import CheckpointError, load_checkpoint
from hrn_pyg.utils.device import resolve_device

#: the folder of the shipped checkpoints (this package's own folder)
CHECKPOINT_DIR = Path(__file__).resolve().parent

#: model options that change how trained weights are applied, not which weights there are: a
#: fine-tuning or a benchmark may set them on a trained model (:func:`with_applied_options`)
APPLIED_OPTIONS = ("mirror_average", "mirror_planes")


def checkpoint_path(name: str) -> Path:
    """``<package>/checkpoints/<name>.pt``, the shipped checkpoint ``name`` (it may not exist)."""
    return CHECKPOINT_DIR / f"{name}.pt"


def resolve_model(scene: str, path: str | os.PathLike | None = None) -> Path:
    """The checkpoint to use for ``scene``: ``path``, or the shipped ``<scene>.pt`` when None.

    Raises FileNotFoundError naming the missing file and the commands that make one.
    """
    model_path = Path(path) if path else checkpoint_path(scene)
    if not model_path.is_file():
        raise FileNotFoundError(
            f"no model checkpoint at {model_path}; train one with "
            f"`hrn-pyg generate --scene {scene} --out data/{scene}` then "
            f"`hrn-pyg train --preset ours --data data/{scene} --out runs/{scene} --train-dropout 0.1` "
            f"and pass --model runs/{scene}/model.pt"
        )
    return model_path


def load_model(path: str | os.PathLike, device: str | torch.device | None = None) -> HRN:
    """An :class:`~hrn_pyg.nn.hrn.HRN` with its normaliser from a checkpoint written by
    ``hrn-pyg train``, in eval mode, on ``device`` (None: the CPU).

    Raises :class:`~hrn_pyg.utils.checkpoint.CheckpointError` (a ValueError) naming the file
    when it is not a model checkpoint.
    """
    ckpt = load_checkpoint(path)
    try:
        config = json.loads(ckpt["config"])
        model = network_from_dict(config["model"])  # an HRN, or a GNS (its config says so)
        model.load_state_dict(ckpt["model"])
    except (KeyError, TypeError, RuntimeError) as exc:
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise CheckpointError(f"{path} is not an hrn_pyg model checkpoint "
                              f"({type(exc).__name__}: {first_line})") from None
    model.eval()
    return model.to(resolve_device(device)) if device is not None else model


def with_applied_options(model: HRN, **options: Any) -> HRN:
    """The same weights and normaliser under a config with ``options`` changed, for options of
    :data:`APPLIED_OPTIONS` only (they change how the weights are applied, e.g. the mirror
    average); the other settings fix which weights there are. Keeps ``model``'s train/eval mode.
    """
    allowed = applied_options(model, APPLIED_OPTIONS)  # a GNS: its rigid fit
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise ValueError(f"only {list(allowed)} can be applied to trained weights, not {unknown}")
    changed = network_from_dict({**model.config.to_dict(), **options})
    changed.load_state_dict(model.state_dict())
    return changed.to(model.normalizer.velocity_std.device).train(model.training)
