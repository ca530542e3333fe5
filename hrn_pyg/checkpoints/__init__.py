"""The shipped checkpoints, by name, and how to load any model checkpoint.

This folder holds the shipped models (``<name>.pt``, from ``make checkpoints`` and
``data/recipes.toml``; ``manifest.json`` says how each was made and on what).
:func:`load_model` reads a checkpoint of ``hrn-pyg train`` by path or name
(``load_model("shapes")``; weights-only unpickling); :func:`model_path`,
:func:`checkpoint_path` and :func:`resolve_model` find files; :func:`shipped_models` lists the
models (:class:`ShippedModel`) and :func:`checkpoint_domain` gives a training domain
(:mod:`hrn_pyg.checkpoints.domain`).
"""

from __future__ import annotations

import json
import os
import shlex
from dataclasses import dataclass, fields
from functools import lru_cache
from pathlib import Path
from typing import Any

import torch

from hrn_pyg.checkpoints.domain import Domain, dataset_domain, with_pitch_range
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.nn.networks import (NetworkConfig, applied_options, build_network, config_from_dict,
                                 network_from_dict)
from hrn_pyg.utils.checkpoint import CheckpointError, bounded_json, load_checkpoint
from hrn_pyg.utils.device import resolve_device
from hrn_pyg.utils.files import file_sha256

#: the folder of the shipped checkpoints (this package's own folder)
CHECKPOINT_DIR = Path(__file__).resolve().parent
#: how each shipped checkpoint was made, and its domain (``python -m experiments.recipe`` writes it)
MANIFEST_PATH = CHECKPOINT_DIR / "manifest.json"
#: shipped files that are policies (``hrn-pyg rl``), not models; :func:`hrn_pyg.rl.policy.load_policy` reads them
POLICY_NAMES = ("cube_push_policy",)

#: model options that change how trained weights are applied, not which weights there are: a
#: fine-tuning or a benchmark may set them on a trained model (:func:`with_applied_options`)
APPLIED_OPTIONS = ("mirror_average", "mirror_planes", "ground_projection", "ground_projection_rigid",
                   "rigid_ground_depth", "rigid_ground_speed", "rigid_ground_lift", "ground_lift_velocity", "rigid_leaf_siblings",
                   "corotated_rest", "cloth_clearance", "rigid_fit_rest", "energy_limit",
                   "solid_clearance", "rest_friction")


#: the most hidden layers per MLP a checkpoint's config may ask for (the shipped models have 2)
MAX_DEPTH = 16
#: the most message-passing steps (a GNS's processor; the shipped GNS has 10)
MAX_PASSES = 64
#: the largest any other whole-number size of a config may be (widths, channels, embeddings;
#: the shipped models' widest is 128)
MAX_WIDTH = 4096
#: the most parameters a checkpoint's config may describe, counted before any weight is made
#: (about 30 times the largest shipped model, a GNS of 1.6 M; 200 MB as float32)
MAX_PARAMETERS = 50_000_000


@dataclass(frozen=True)
class ShippedModel:
    """One shipped model as its manifest records it: ``datasets`` (its own first), ``scene`` of the
    first, calibrated ``rate`` and ``modules`` (None: never calibrated), ``test`` errors by metric."""

    name: str
    path: Path
    aliases: tuple[str, ...] = ()
    scene: str | None = None
    datasets: tuple[str, ...] = ()
    domain: Domain | None = None
    rate: float | None = None
    modules: tuple[str, ...] = ()
    test: tuple[tuple[str, float], ...] = ()
    sha256: str | None = None


def checkpoint_path(name: str) -> Path:
    """``<package>/checkpoints/<name>.pt``, the shipped checkpoint ``name`` (it may not exist)."""
    return CHECKPOINT_DIR / f"{name}.pt"


def shipped_names() -> tuple[str, ...]:
    """The names of the shipped models (aliases included, policies not), sorted."""
    return tuple(sorted(p.stem for p in CHECKPOINT_DIR.glob("*.pt") if p.stem not in POLICY_NAMES))


def model_path(model: str | os.PathLike) -> Path:
    """The checkpoint file ``model`` names: a path to a file, or a shipped model's name
    (``"shapes"`` or ``"shapes.pt"``). Raises FileNotFoundError listing the shipped names."""
    path = Path(model)
    if path.is_file():
        return path
    text = str(model)
    name = text[:-3] if text.endswith(".pt") else text
    if name and os.sep not in text and "/" not in text and name not in POLICY_NAMES and checkpoint_path(name).is_file():
        return checkpoint_path(name)
    raise FileNotFoundError(f"checkpoint not found: {text} is neither a file nor a shipped model "
                            f"({', '.join(shipped_names())}; `hrn-pyg models` lists them)")


def resolve_model(scene: str, path: str | os.PathLike | None = None) -> Path:
    """The checkpoint to use for ``scene``: ``path`` (a file or a shipped name), or the shipped
    ``<scene>.pt``; FileNotFoundError naming the file and the commands that make one."""
    if path:
        return model_path(path)
    model = checkpoint_path(scene)
    if not model.is_file():
        raise FileNotFoundError(
            f"no model checkpoint at {model}; train one with "
            f"`hrn-pyg generate --scene {scene} --out data/{scene}` then "
            f"`hrn-pyg train --preset ours --data data/{scene} --out runs/{scene} --train-dropout 0.1` "
            f"and pass --model runs/{scene}/model.pt"
        )
    return model


def display_name(path: str | os.PathLike) -> str:
    """How messages name a checkpoint: a shipped one by its file name (``shapes.pt``), another
    by its path."""
    path = Path(path)
    try:
        shipped = path.resolve().parent == CHECKPOINT_DIR
    except OSError:
        shipped = False
    return path.name if shipped else str(path)


def load_model(path: str | os.PathLike, device: str | torch.device | None = None) -> HRN:
    """An :class:`~hrn_pyg.nn.hrn.HRN` with its normaliser from a checkpoint of ``hrn-pyg train`` (a
    path or a shipped name), in eval mode on ``device`` (None: CPU), carrying ``domain`` (or None)
    and ``checkpoint_name``. FileNotFoundError for an unknown name;
    :class:`~hrn_pyg.utils.checkpoint.CheckpointError` (a ValueError) for a file that is not one."""
    path = model_path(path)
    ckpt = load_checkpoint(path)
    try:
        config = config_from_dict(json.loads(ckpt["config"])["model"])  # an HRN's, or a GNS's
        check_model_size(config)
        model = build_network(config)
        model.load_state_dict(ckpt["model"])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise _not_a_model(path, exc) from None
    model.domain = checkpoint_domain(path, ckpt)
    model.checkpoint_name = display_name(path)
    model.eval()
    return model.to(resolve_device(device)) if device is not None else model


def checkpoint_config(path: str | os.PathLike) -> NetworkConfig:
    """The network config a model checkpoint (a path or a shipped name) was saved with, without
    building its network. Raises :class:`~hrn_pyg.utils.checkpoint.CheckpointError` naming the
    file when it holds no model config."""
    path = model_path(path)
    try:
        config = config_from_dict(json.loads(load_checkpoint(path)["config"])["model"])
        check_model_size(config)
        return config
    except (KeyError, TypeError, ValueError) as exc:
        raise _not_a_model(path, exc) from None


def check_model_size(config: NetworkConfig) -> None:
    """ValueError naming the field when ``config`` exceeds :data:`MAX_DEPTH`, :data:`MAX_PASSES`,
    :data:`MAX_WIDTH` or :data:`MAX_PARAMETERS` (counted on the ``meta`` device, no memory)."""
    for field in fields(config):
        if field.type not in (int, "int"):
            continue
        name, value = field.name, getattr(config, field.name)
        limit = {"depth": MAX_DEPTH, "message_passing_steps": MAX_PASSES}.get(name, MAX_WIDTH)
        if not isinstance(value, int) or value > limit:
            raise ValueError(f"config field {name} = {value!r}; the limit is a whole number up to {limit}")
    count = parameter_count(config)
    if count > MAX_PARAMETERS:
        raise ValueError(f"config describes {count} parameters, more than the limit {MAX_PARAMETERS}")


def parameter_count(config: NetworkConfig) -> int:
    """The parameters of :func:`~hrn_pyg.nn.networks.build_network` ``(config)``, counted on the
    ``meta`` device (no weight is allocated)."""
    with torch.device("meta"):
        network = build_network(config)
    return sum(parameter.numel() for parameter in network.parameters())


def _not_a_model(path: Path, exc: Exception) -> CheckpointError:
    """The one-line error for a file that holds no model: its path, the error's type and its
    first line (for a state dict that does not fit, the first line that names a key)."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    if len(lines) > 1 and lines[0].endswith(":"):  # torch's "Error(s) in loading state_dict for HRN:"
        lines = [f"{lines[0]} {lines[1]}"]
    return CheckpointError(f"{path} is not an hrn_pyg model checkpoint "
                           f"({type(exc).__name__}: {lines[0] if lines else ''})")


def checkpoint_domain(path: str | os.PathLike, ckpt: dict[str, Any] | None = None) -> Domain | None:
    """The domain a checkpoint was trained on: its own record (``domain``, written by ``hrn-pyg
    train``), else the manifest's for a shipped file with the same bytes; None when neither
    has one. ``ckpt`` is the loaded checkpoint when the caller has it."""
    ckpt = load_checkpoint(model_path(path)) if ckpt is None else ckpt
    if isinstance(ckpt.get("domain"), str):
        try:
            return Domain.from_dict(bounded_json(ckpt["domain"], "domain"))
        except ValueError as exc:
            raise CheckpointError(f"{path}: {exc}") from None
    entry = _manifest_by_sha256().get(file_sha256(model_path(path)))
    return None if entry is None or entry.get("domain") is None else Domain.from_dict(entry["domain"])


@lru_cache(maxsize=8)
def training_domain(folders: tuple[str, ...], init_from: str = "", pitch_range: bool = False) -> Domain | None:
    """The domain a training on the dataset ``folders`` gives its model, with that of ``init_from``;
    None when a folder has no episodes. ``pitch_range``: also the span of its pitches. Cached."""
    try:
        domain = dataset_domain(list(folders))
    except FileNotFoundError:
        return None
    if init_from:
        try:
            prior = checkpoint_domain(init_from)
        except (FileNotFoundError, ValueError):
            prior = None
        if prior is not None:
            domain = prior.merge(domain)
    return with_pitch_range(domain) if pitch_range else domain


def read_manifest(path: str | os.PathLike | None = None) -> dict[str, dict[str, Any]]:
    """The manifest's entries, name -> record (empty without one); ``path`` defaults to the package's."""
    path = Path(MANIFEST_PATH if path is None else path)
    if not path.is_file():
        return {}
    return dict(json.loads(path.read_text()).get("checkpoints", {}))


@lru_cache(maxsize=1)
def _manifest_by_sha256() -> dict[str, dict[str, Any]]:
    return {entry["sha256"]: entry for entry in read_manifest().values() if entry.get("sha256")}


def entry_datasets(entry: dict[str, Any]) -> tuple[str, ...]:
    """The datasets a manifest entry trained on: its own, then those its stages add
    (``--extra-data`` folders, by name), each once."""
    names = [entry.get("dataset", {}).get("name")]
    for command in [*entry.get("stage_commands", []), entry.get("train_command", "")]:
        words = shlex.split(command or "")
        for i, word in enumerate(words[:-1]):
            if word == "--extra-data":
                names += [Path(folder).name for folder in words[i + 1].split(",") if folder]
    return tuple(dict.fromkeys(n for n in names if n))


def shipped_model(name: str, entry: dict[str, Any]) -> ShippedModel:
    """A manifest ``entry`` as a :class:`ShippedModel`."""
    calibrated = entry.get("calibrated") or {}
    test = entry.get("test") or {}
    return ShippedModel(
        name=name, path=checkpoint_path(name), aliases=tuple(entry.get("aliases", ())),
        scene=entry.get("dataset", {}).get("scene"), datasets=entry_datasets(entry),
        domain=None if entry.get("domain") is None else Domain.from_dict(entry["domain"]),
        rate=calibrated.get("rate"), modules=tuple(calibrated.get("modules") or ()),
        test=tuple((str(k), float(v)) for k, v in test.items() if k != "about"), sha256=entry.get("sha256"),
    )


def shipped_models() -> list[ShippedModel]:
    """Every shipped model, sorted by name: those the manifest records (with their aliases), then
    any other model file here (with no record)."""
    manifest = read_manifest()
    models = [shipped_model(name, entry) for name, entry in sorted(manifest.items())
              if checkpoint_path(name).is_file()]
    known = {n for m in models for n in (m.name, *m.aliases)}
    models += [ShippedModel(name=n, path=checkpoint_path(n)) for n in shipped_names() if n not in known]
    return models


def with_applied_options(model: HRN, **options: Any) -> HRN:
    """The same weights and normaliser under ``options`` of :data:`APPLIED_OPTIONS` (how the weights
    are applied, e.g. the mirror average), keeping mode, ``domain`` and ``checkpoint_name``."""
    allowed = applied_options(model, APPLIED_OPTIONS)  # a GNS: its rigid fit
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise ValueError(f"only {list(allowed)} can be applied to trained weights, not {unknown}")
    changed = network_from_dict({**model.config.to_dict(), **options})
    changed.load_state_dict(model.state_dict())
    for attribute in ("domain", "checkpoint_name"):
        if hasattr(model, attribute):
            setattr(changed, attribute, getattr(model, attribute))
    return changed.to(model.normalizer.velocity_std.device).train(model.training)

