"""What a run starts from and writes: checkpoints, snapshots, fine-tuning starts, the resumed state."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch

from hrn_pyg.checkpoints import APPLIED_OPTIONS, load_model, training_domain, with_applied_options
from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.nn.gns import GNS, fit_acceleration
from hrn_pyg.nn.hrn import HRN
from hrn_pyg.nn.networks import Network, NetworkConfig, build_network, network_from_dict
from hrn_pyg.nn.normalizer import fit_normalizer, isotropic_horizontal
from hrn_pyg.nn.pitch import is_pitch_aware
from hrn_pyg.nn.widen import widen_to_pitch_aware, with_collision_force
from hrn_pyg.train.config import TrainConfig
from hrn_pyg.utils.checkpoint import load_checkpoint, set_rng_state
from hrn_pyg.utils.weight_average import WeightAverage


#: windows used to fit the normaliser (the statistics converge long before this)
NORMALIZER_WINDOWS = 256


def model_payload(model: HRN, config: TrainConfig, step: int) -> dict[str, Any]:
    """The checkpoint of a model: its weights (normaliser included), its settings and the run's as
    JSON, the steps done and, when its datasets have episodes, the domain they span
    (:mod:`hrn_pyg.checkpoints.domain`, as JSON); what :func:`~hrn_pyg.checkpoints.load_model` reads."""
    payload = {
        "model": model.state_dict(),
        "config": json.dumps({"model": model.config.to_dict(), "train": asdict(config)}),
        "step": step,
    }
    domain = training_domain(tuple(config.data_folders), config.init_from or "", pitch_range=is_pitch_aware(model.config))
    if domain is not None:
        payload["domain"] = json.dumps(domain.to_dict())
    return payload


def checkpoint_to_resume(last: Path, resume: bool) -> dict[str, Any] | None:
    """The checkpoint ``last`` when resuming (an error if there is none); None for a new run."""
    if not resume:
        return None
    if not last.is_file():
        raise FileNotFoundError(f"--resume: no checkpoint at {last}")
    return load_checkpoint(last)


def initial_model(config: TrainConfig, model_config: NetworkConfig, train_set: EpisodeWindows,
                   ckpt: dict[str, Any] | None, given: frozenset[str] = frozenset()) -> Network:
    """The network the steps start from: the checkpoint's when resuming, else the model of
    ``init_from`` or a fresh one with its normaliser fitted; under ``augment_symmetry``, and for
    an equivariant network, a new run's normaliser is made isotropic."""
    torch.manual_seed(config.seed)
    # built in every case: its initialisation advances the global random stream, which the
    # dropout masks of a run from init_from then continue
    model = build_network(model_config)
    if ckpt is not None:
        model = network_from_dict(json.loads(ckpt["config"])["model"])
        model.load_state_dict(ckpt["model"])
        return model
    if config.init_from:
        model = _fine_tuned_start(config.init_from, model_config, given)
    else:
        _fit_to_training_windows(model, train_set, config.seed)
    if config.augment_symmetry or getattr(model.config, "equivariant", False):
        isotropic_horizontal(model.normalizer)
    return model


def _fine_tuned_start(path: str, model_config: NetworkConfig, given: frozenset[str] = frozenset()) -> Network:
    """The model of checkpoint ``path``, in training mode, for ``init_from``, with the checkpoint's
    settings: a ``model_config`` that sets something else (differing from the checkpoint and from
    the defaults or in ``given``) is an error, except :data:`APPLIED_OPTIONS`. ``pitch_aware`` from
    a plain checkpoint widens it (:func:`hrn_pyg.nn.widen.widen_to_pitch_aware`, taking
    ``model_config``'s applied options), ``collision_force`` from one without starts those weights
    at zero (:func:`hrn_pyg.nn.widen.with_collision_force`)."""
    model = load_model(path)
    if type(model.config) is not type(model_config):
        raise ValueError(f"init_from={path!r} is a {type(model).__name__}, this preset trains a "
                         f"{type(model_config).__name__.removesuffix('Config')}")
    if getattr(model_config, "pitch_aware", False) and not model.config.pitch_aware:
        applied = {k: getattr(model_config, k) for k in APPLIED_OPTIONS}
        model = widen_to_pitch_aware(model, reference_pitch=model_config.reference_pitch, **applied)
    if getattr(model_config, "collision_force", False) and not model.config.collision_force:
        model = with_collision_force(model)
    saved, wanted, default = model.config.to_dict(), model_config.to_dict(), type(model_config)().to_dict()
    changed = {k: value for k, value in wanted.items()
               if (value != default.get(k) or k in given) and value != saved.get(k)}
    clashes = sorted(k for k in changed if k not in APPLIED_OPTIONS)
    if clashes:
        raise ValueError(f"init_from={path!r} keeps that model's settings; these model options "
                         f"differ from it: {', '.join(clashes)}")
    if changed:
        model = with_applied_options(model, **changed)
    return model.train()


def _fit_to_training_windows(model: Network, train_set: EpisodeWindows, seed: int) -> None:
    """Fit the model's normaliser (and a GNS's acceleration statistics) on
    :data:`NORMALIZER_WINDOWS` training windows drawn by ``seed``."""
    picks = torch.randperm(len(train_set), generator=torch.Generator().manual_seed(seed))
    windows = [train_set[int(i)] for i in picks[:NORMALIZER_WINDOWS]]
    reference = model.config.reference_pitch if is_pitch_aware(model.config) else None
    fit_normalizer(windows, model.normalizer, reference_pitch=reference)
    if isinstance(model, GNS):
        fit_acceleration(windows, model)


def restore_training_state(ckpt: dict[str, Any], optimizer: torch.optim.Optimizer,
                            scheduler: torch.optim.lr_scheduler.LambdaLR) -> int:
    """Continue the checkpoint's optimiser, learning-rate schedule and global random streams;
    returns the number of steps it had done."""
    optimizer.load_state_dict(ckpt["optimizer"])
    scheduler.load_state_dict(ckpt["scheduler"])
    set_rng_state(ckpt["rng"])
    return int(ckpt["step"])


def weight_average(model: Network, config: TrainConfig, ckpt: dict[str, Any] | None) -> WeightAverage | None:
    """The run's weight average under ``ema_decay`` (None when off): the checkpoint's when it
    has one, else started at the model's weights (a new run, or a run that turns it on)."""
    if config.ema_decay == 0:
        return None
    average = WeightAverage(model, config.ema_decay)
    if ckpt is not None and "weight_average" in ckpt:
        average.load_state_dict(ckpt["weight_average"])
    return average


def snapshot_path(out: str | Path, step: int) -> Path:
    """Where a run in ``out`` keeps its model after ``step`` steps (``--snapshot-every``)."""
    return Path(out) / "snapshots" / f"step_{step:05d}.pt"
