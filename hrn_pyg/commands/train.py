"""``hrn-pyg train``'s arguments (the work: :mod:`hrn_pyg.train.cli`), in groups, one per
:class:`~hrn_pyg.train.config.TrainConfig` field and one ``--model-*`` per network config field,
read from the configs' source (:mod:`hrn_pyg.commands.configs`)."""

from __future__ import annotations

import argparse
from typing import Any

from hrn_pyg.commands.configs import SourceField, config_fields, config_help, source_constant
from hrn_pyg.utils.options import add_no_progress, add_removed, add_renamed, shown_default

TRAIN_CONFIG = ("hrn_pyg.train.config", "TrainConfig")
HRN_CONFIG, GNS_CONFIG = ("hrn_pyg.nn.hrn", "HRNConfig"), ("hrn_pyg.nn.gns", "GNSConfig")

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

#: TrainConfig fields whose option is not ``--<field>``
TRAIN_FLAGS = {"steps": "--train-steps"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    presets = source_constant(TRAIN_CONFIG[0], "PRESETS")
    parser.usage = f"%(prog)s --preset {{{','.join(presets)}}} --data FOLDER [options]"
    parser.add_argument("--preset", choices=presets, required=True,
                        help="hrn (baseline), ours, or gns (the flat GNS baseline)")
    groups = {name: parser.add_argument_group(name) for name in OPTION_GROUPS}
    groups["data"].add_argument("--data", required=True, help="episode folder from `hrn-pyg generate`")
    groups["run"].add_argument("--out", default=None, help="run folder (default: runs/train/<data's name>_<preset>)")
    groups["run"].add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    add_no_progress(groups["run"])
    helps = config_help(*TRAIN_CONFIG)
    group_of = {name: group for group, names in OPTION_GROUPS.items() for name in names}
    for f in config_fields(*TRAIN_CONFIG):
        if f.name in ("preset", "data", "out"):
            continue
        text = f"{helps.get(f.name, f.name)} ({preset_defaults(f.name)})"
        groups[group_of[f.name]].add_argument(train_flag(f.name), type=option_type(f.default), default=None,
                                              dest=f.name, help=text)
    model_helps = config_help(*GNS_CONFIG) | config_help(*HRN_CONFIG)
    for f in model_fields():
        groups["model"].add_argument(f"--model-{f.name.replace('_', '-')}", type=option_type(f.default), default=None,
                                     dest=f"model_{f.name}",
                                     help=f"{model_helps.get(f.name, f.name)} (default: {shown_default(f.default)})")
    groups["model"].add_argument("--dropout-modules", default=None,
                                 help="comma-separated modules that take dropout masks (default: force,collision; "
                                      "gns: processor)")
    add_renamed(parser, "--steps", "--train-steps")
    add_removed(parser, REMOVED_OPTIONS, "no recipe or shipped model used it")


def train_flag(name: str) -> str:
    """The ``hrn-pyg train`` option of a :class:`TrainConfig` field."""
    return TRAIN_FLAGS.get(name, f"--{name.replace('_', '-')}")


def preset_defaults(name: str) -> str:
    """``default: X`` of a :class:`TrainConfig` field, or ``default: hrn X, ours Y, gns Z``
    where the presets differ (the field's default under each preset's overrides)."""
    default = next(f.default for f in config_fields(*TRAIN_CONFIG) if f.name == name)
    overrides = source_constant(TRAIN_CONFIG[0], "PRESET_OVERRIDES")
    values = {preset: shown_default(changed.get(name, default)) or "''" for preset, changed in overrides.items()}
    if len(set(values.values())) == 1:
        return f"default: {next(iter(values.values()))}"
    return "default: " + ", ".join(f"{preset} {value}" for preset, value in values.items())


def model_fields() -> list[SourceField]:
    """The network config fields that are ``--model-*`` options: the HRN's, then those only the
    GNS has."""
    hrn = [f for f in config_fields(*HRN_CONFIG) if f.name not in ("dropout_modules", "skip_idle_modules")]
    names = {f.name for f in hrn}
    skipped = names | {"dropout_modules", "network"}
    return hrn + [f for f in config_fields(*GNS_CONFIG) if f.name not in skipped]


def _parse_bool(text: str) -> bool:
    value = text.strip().lower()
    if value in ("1", "true", "yes", "on"):
        return True
    if value in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")


def option_type(default: Any) -> Any:
    """The argparse type of a config field (``bool("False")`` is True, so booleans are parsed)."""
    return _parse_bool if isinstance(default, bool) else type(default)
