"""``hrn-pyg train``: fit an HRN on an episode folder, as the baseline HRN or as *ours*, or the
GNS baseline.

Two presets (seed paper, section 3.1):

* ``hrn``: one step ahead on ground-truth inputs, local + global + **group** shape loss.
* ``ours``: recurrent and state-invariant: the model's own predictions are fed back for ``T``
  steps (parent states and collision edges recomputed every step, no hidden state), the loss is
  summed over the steps with gradients through the whole unroll, ``T`` grows from 1 to 6 over
  training; local + global + **fully-connected** shape loss.
* ``gns``: the flat GNS baseline (:mod:`hrn_pyg.nn.gns`): one step ahead, the mean squared error
  of the leaves' normalised accelerations, per-leaf random-walk input noise at
  :data:`~hrn_pyg.nn.gns.NOISE_TO_VELOCITY_STD` of the fitted velocity scale, learning rate 1e-4
  (the paper's); ``--model-*`` options are those of :class:`~hrn_pyg.nn.gns.GNSConfig`.

One training step draws a mini-batch of windows, unrolls, and takes one optimiser step with
gradient clipping under a warm-up + cosine learning-rate schedule. Checkpoints are written
atomically every ``checkpoint_every`` steps and at exit (also on Ctrl-C); ``--resume`` continues
from the last one with the optimiser and random-number state, so the next loss is the one the
uninterrupted run would have had. Under ``torchrun --nproc_per_node N`` the same command trains
data-parallel (nccl on CUDA, gloo on CPU): each rank draws its own windows and gradients are
averaged. ``--device`` (default CUDA when available) places the model and every batch;
``--workers N`` assembles the batches in N background processes.

The package by role: :mod:`~hrn_pyg.train.config` (:class:`TrainConfig`), :mod:`~hrn_pyg.train.loss`
(the loss of one window), :mod:`~hrn_pyg.train.loader` (which windows a step draws),
:mod:`~hrn_pyg.train.checkpointing` (what a run starts from and writes),
:mod:`~hrn_pyg.train.distributed` (``torchrun``), :mod:`~hrn_pyg.train.loop` (:func:`train`) and
:mod:`~hrn_pyg.train.cli` (the command line). The names below are the ones other code imports.
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
