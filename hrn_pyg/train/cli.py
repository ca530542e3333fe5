"""``hrn-pyg train``'s command line: its options (from :class:`~hrn_pyg.train.config.TrainConfig` and the network configs) in groups."""

from __future__ import annotations

import argparse
import os
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

from hrn_pyg.checkpoints import checkpoint_config
from hrn_pyg.nn.gns import GNSConfig
from hrn_pyg.nn.hrn import HRNConfig
from hrn_pyg.nn.networks import NetworkConfig
from hrn_pyg.train.config import PRESETS, TrainConfig
from hrn_pyg.train.loop import train
from hrn_pyg.utils.options import add_no_progress, add_removed, add_renamed, attribute_help, shown_default


#: options of earlier releases that no recipe or shipped model used; given, they warn and are
#: ignored, for one release
REMOVED_OPTIONS = ("--sample-copies", "--w-energy", "--w-contact", "--contact-floor", "--w-ground", "--ground-floor",
                   "--rest-leaves", "--model-material-heads")


#: the groups of ``hrn-pyg train --help``, each TrainConfig field in one (``model`` also holds the
#: ``--model-*`` options of the network's config)
OPTION_GROUPS: dict[str, tuple[str, ...]] = {
    "data": ("data", "extra_data", "data_weights", "batch_size", "input_noise", "input_noise_ratio",
             "augment_symmetry"),
    "model": ("init_from", "train_dropout"),
    "loss": ("shape_loss", "shape_chunk", "w_local", "w_global", "w_shape", "w_rest", "rest_threshold",
             "rest_rollout", "rest_rollout_draw"),
    "schedule": ("steps", "lr", "warmup", "grad_clip", "seq_start", "seq_end", "grow_until", "ema_decay", "stop_at"),
    "run": ("out", "seed", "device", "threads", "workers", "checkpoint_every", "eval_every", "snapshot_every",
            "time_limit"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.usage = "%(prog)s --preset {hrn,ours,gns} --data FOLDER [options]"
    parser.add_argument("--preset", choices=PRESETS, required=True,
                        help="hrn (baseline), ours, or gns (the flat GNS baseline)")
    groups = {name: parser.add_argument_group(name) for name in OPTION_GROUPS}
    groups["data"].add_argument("--data", required=True, help="episode folder from `hrn-pyg generate`")
    groups["run"].add_argument("--out", default=None, help="run folder (default: runs/train/<data's name>_<preset>)")
    groups["run"].add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    add_no_progress(groups["run"])
    helps = attribute_help(TrainConfig)
    group_of = {name: group for group, names in OPTION_GROUPS.items() for name in names}
    for f in fields(TrainConfig):
        if f.name in ("preset", "data", "out"):
            continue
        groups[group_of[f.name]].add_argument(train_flag(f.name), type=_option_type(f.default), default=None,
                                              dest=f.name, help=f"{helps.get(f.name, f.name)} ({preset_defaults(f.name)})")
    model_helps = attribute_help(GNSConfig) | attribute_help(HRNConfig)
    for f in _model_fields():
        groups["model"].add_argument(f"--model-{f.name.replace('_', '-')}", type=_option_type(f.default), default=None,
                                     dest=f"model_{f.name}",
                                     help=f"{model_helps.get(f.name, f.name)} (default: {shown_default(f.default)})")
    groups["model"].add_argument("--dropout-modules", default=None,
                                 help="comma-separated modules that take dropout masks (default: force,collision; "
                                      "gns: processor)")
    add_renamed(parser, "--steps", "--train-steps")
    add_removed(parser, REMOVED_OPTIONS, "no recipe or shipped model used it")


#: TrainConfig fields whose option is not ``--<field>``
TRAIN_FLAGS = {"steps": "--train-steps"}


def train_flag(name: str) -> str:
    """The ``hrn-pyg train`` option of a :class:`TrainConfig` field."""
    return TRAIN_FLAGS.get(name, f"--{name.replace('_', '-')}")


def preset_defaults(name: str) -> str:
    """``default: X`` of a :class:`TrainConfig` field, or ``default: hrn X, ours Y, gns Z``
    where the presets differ."""
    values = {preset: shown_default(getattr(TrainConfig.for_preset(preset), name)) or "''" for preset in PRESETS}
    if len(set(values.values())) == 1:
        return f"default: {next(iter(values.values()))}"
    return "default: " + ", ".join(f"{preset} {value}" for preset, value in values.items())


def _model_fields() -> list:
    """The config fields that are ``--model-*`` options: the HRN's, then those only the GNS has."""
    hrn = [f for f in fields(HRNConfig) if f.name not in ("dropout_modules", "skip_idle_modules")]
    names = {f.name for f in hrn}
    return hrn + [f for f in fields(GNSConfig) if f.name not in names and f.name not in ("dropout_modules", "network")]


def _parse_bool(text: str) -> bool:
    value = text.strip().lower()
    if value in ("1", "true", "yes", "on"):
        return True
    if value in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")


def _option_type(default: Any) -> Any:
    """The argparse type of a config field (``bool("False")`` is True, so booleans are parsed)."""
    return _parse_bool if isinstance(default, bool) else type(default)


def given_model_options(args: argparse.Namespace) -> frozenset[str]:
    """The model config fields set on the command line (``--model-*``, ``--dropout-modules``)."""
    names = {f.name for f in _model_fields() if getattr(args, f"model_{f.name}", None) is not None}
    return frozenset(names | ({"dropout_modules"} if args.dropout_modules else set()))


def config_from_args(args: argparse.Namespace) -> tuple[TrainConfig, NetworkConfig]:
    overrides = {f.name: getattr(args, f.name, None) for f in fields(TrainConfig)
                 if f.name not in ("preset", "data", "out")}
    out = args.out or str(Path("runs") / "train" / f"{Path(args.data).name}_{args.preset}")
    config = TrainConfig.for_preset(args.preset, data=args.data, out=out, **overrides)
    model_class = GNSConfig if args.preset == "gns" else HRNConfig
    model_kwargs = {f.name: getattr(args, f"model_{f.name}") for f in _model_fields()
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
