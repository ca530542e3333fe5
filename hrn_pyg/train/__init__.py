"""``hrn-pyg train``: fit an HRN on an episode folder, as the baseline HRN or as *ours*, or the
GNS baseline.

Presets (seed paper, section 3.1):

* ``hrn``: one step ahead on ground-truth inputs, local + global + **group** shape loss.
* ``ours``: recurrent: the model's own predictions fed back for ``T`` steps (1 growing to 6),
  gradients through the unroll; local + global + **fully-connected** shape loss.
* ``gns``: the GNS baseline (:mod:`hrn_pyg.nn.gns`): one step, normalised acceleration error,
  random-walk input noise (:data:`~hrn_pyg.nn.gns.NOISE_TO_VELOCITY_STD`), learning rate 1e-4.

A step draws a mini-batch of windows, unrolls, and takes one clipped optimiser step under a
warm-up + cosine schedule. Checkpoints are atomic, every ``checkpoint_every`` steps and at exit;
``--resume`` continues bit for bit. Under ``torchrun`` it trains data-parallel.

Modules: :mod:`~hrn_pyg.train.config`, :mod:`~hrn_pyg.train.loss`, :mod:`~hrn_pyg.train.loader`,
:mod:`~hrn_pyg.train.checkpointing`, :mod:`~hrn_pyg.train.distributed`,
:mod:`~hrn_pyg.train.loop` (:func:`train`) and :mod:`~hrn_pyg.train.cli`.
"""

from hrn_pyg.train.checkpointing import NORMALIZER_WINDOWS, model_payload, snapshot_path
from hrn_pyg.train.cli import (
    OPTION_GROUPS,
    REMOVED_OPTIONS,
    add_arguments,
    config_from_args,
    given_model_options,
    preset_defaults,
    run,
    train_flag,
)
from hrn_pyg.train.config import PRESETS, REST_ROLLOUT_DRAWS, SHAPE_LOSSES, TrainConfig, parse_data_weights
from hrn_pyg.train.distributed import average_gradients
from hrn_pyg.train.loader import VAL_WINDOWS, StepWindows, draw_windows, window_draw_weights
from hrn_pyg.train.loop import LOG_FIELDS, preset_model_config, resolved_noise, train
from hrn_pyg.train.loss import (
    acceleration_loss,
    held_rest_sequence,
    input_noise,
    rest_rollout_length,
    resting_windows,
    validation_loss,
    window_loss,
)

__all__ = [
    "LOG_FIELDS", "NORMALIZER_WINDOWS", "OPTION_GROUPS", "PRESETS", "REMOVED_OPTIONS", "REST_ROLLOUT_DRAWS",
    "SHAPE_LOSSES", "VAL_WINDOWS", "StepWindows", "TrainConfig", "acceleration_loss", "add_arguments",
    "config_from_args", "given_model_options", "held_rest_sequence", "input_noise", "model_payload",
    "parse_data_weights", "preset_defaults", "preset_model_config", "resolved_noise", "rest_rollout_length",
    "resting_windows", "run", "snapshot_path", "train", "train_flag", "validation_loss", "window_draw_weights",
    "window_loss",
]
