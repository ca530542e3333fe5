"""``hrn-pyg train``'s work: a :class:`~hrn_pyg.train.config.TrainConfig` and a network config from
the options of :mod:`hrn_pyg.commands.train`, and the run."""

from __future__ import annotations

import argparse
import os
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

from hrn_pyg.checkpoints import checkpoint_config
from hrn_pyg.commands.train import (  # noqa: F401  the command's arguments, here too
    OPTION_GROUPS,
    REMOVED_OPTIONS,
    add_arguments,
    model_fields,
    preset_defaults,
    train_flag,
)
from hrn_pyg.nn.gns import GNSConfig
from hrn_pyg.nn.hrn import HRNConfig
from hrn_pyg.nn.networks import NetworkConfig
from hrn_pyg.train.config import TrainConfig
from hrn_pyg.train.loop import train


def given_model_options(args: argparse.Namespace) -> frozenset[str]:
    """The model config fields set on the command line (``--model-*``, ``--dropout-modules``)."""
    names = {f.name for f in model_fields() if getattr(args, f"model_{f.name}", None) is not None}
    return frozenset(names | ({"dropout_modules"} if args.dropout_modules else set()))


def config_from_args(args: argparse.Namespace) -> tuple[TrainConfig, NetworkConfig]:
    overrides = {f.name: getattr(args, f.name, None) for f in fields(TrainConfig)
                 if f.name not in ("preset", "data", "out")}
    out = args.out or str(Path("runs") / "train" / f"{Path(args.data).name}_{args.preset}")
    config = TrainConfig.for_preset(args.preset, data=args.data, out=out, **overrides)
    model_class = GNSConfig if args.preset == "gns" else HRNConfig
    model_kwargs = {f.name: getattr(args, f"model_{f.name}") for f in model_fields()
                    if getattr(args, f"model_{f.name}", None) is not None}
    foreign = sorted(set(model_kwargs) - {f.name for f in fields(model_class)})
    if foreign:
        raise ValueError(f"--model-{foreign[0].replace('_', '-')} is not an option of the "
                         f"{model_class.__name__.removesuffix('Config')} that preset {args.preset!r} trains")
    if args.dropout_modules:
        model_kwargs["dropout_modules"] = tuple(m for m in args.dropout_modules.split(",") if m)
    return config, _named_model_config(model_class, model_kwargs, config.init_from)


def _named_model_config(model_class: type[NetworkConfig], named: dict[str, Any], init_from: str) -> NetworkConfig:
    """The network config of the command line's ``--model-*`` options (``named``): over the
    defaults, or with ``init_from`` over that checkpoint's own config, so that an option whose
    check reads another field (``corotated_rest`` needs ``rest_offsets``) may be named alone in
    a fine-tuning. A checkpoint of another network type gives the defaults, and the fine-tuning
    then names the mismatch (:func:`_fine_tuned_start`)."""
    base = checkpoint_config(init_from) if init_from else None
    if not isinstance(base, model_class):
        return model_class(**named)
    return replace(base, **named)


def run(args: argparse.Namespace) -> int:
    config, model_config = config_from_args(args)
    summary = train(config, model_config, resume=args.resume, progress=not args.no_progress,
                    given_model_options=given_model_options(args))
    # the process group is gone once train() returns: the launcher's RANK says who reports
    if int(os.environ.get("RANK", "0")) == 0 and summary:
        done = int(summary["step"]) + 1
        if done >= config.steps:
            print(f"trained {config.preset} to step {config.steps}: loss {summary['loss']:.4g}; "
                  f"model at {Path(config.out) / 'model.pt'}")
        else:
            print(f"stopped {config.preset} at step {done} of {config.steps} (time limit): loss "
                  f"{summary['loss']:.4g}; continue with --resume")
    return 0
