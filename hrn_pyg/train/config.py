"""The settings of one training run (:class:`TrainConfig`) and the presets' defaults."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hrn_pyg.losses import DEFAULT_CHUNK_SIZE
from hrn_pyg.nn.gns import NOISE_TO_VELOCITY_STD


PRESETS = ("hrn", "ours", "gns")
#: what each preset sets over the field defaults (:meth:`TrainConfig.for_preset`)
PRESET_OVERRIDES: dict[str, dict[str, Any]] = {
    "hrn": {"seq_start": 1, "seq_end": 1, "shape_loss": "group"},
    "ours": {"seq_start": 1, "seq_end": 6, "shape_loss": "full"},
    "gns": {"seq_start": 1, "seq_end": 1, "lr": 1e-4, "input_noise_ratio": NOISE_TO_VELOCITY_STD},
}


SHAPE_LOSSES = ("group", "full")


#: how :func:`held_rest_sequence` draws its rollout length R from 1..R_max
REST_ROLLOUT_DRAWS = ("uniform", "log")


@dataclass(frozen=True)
class TrainConfig:
    """One training run. ``preset`` fixes the defaults of the loss and the unroll schedule.

    Attributes:
        preset: ``hrn`` (one-step, group shape loss) or ``ours`` (recurrent, full shape loss).
        data: episode folder (``hrn-pyg generate`` output).
        out: run folder: checkpoints, ``metrics.csv``, ``loss.png``, ``config.json``.
        steps: optimiser steps.
        batch_size: windows per step (per rank).
        lr: base learning rate (Adam), warm-up for ``warmup`` steps then cosine to 5 percent.
        grad_clip: global gradient-norm clip.
        seq_start, seq_end, grow_until: recurrent unroll length, grown from ``seq_start`` to
            ``seq_end`` over the first ``grow_until`` fraction of training.
        shape_loss: ``group`` (baseline HRN) or ``full`` (ours).
        shape_chunk: rows per chunk of the fully-connected shape loss (bounded memory).
        w_local, w_global, w_shape: loss weights.
        train_dropout: dropout rate on ``model.dropout_modules`` while training (0: none).
        checkpoint_every, eval_every: steps between checkpoints / validation scores.
        snapshot_every: keep the model every that many steps in ``snapshots/step_<step>.pt``
            (for selection on validation); 0: none.
        ema_decay: ``d`` of a moving average of the weights, ``w_avg <- d * w_avg + (1 - d) * w``
            after every step (:class:`~hrn_pyg.utils.weight_average.WeightAverage`, about
            ``1 / (1 - d)`` steps): the run's model and what validation scores; 0: off.
        seed: seeds the model initialisation, the window draws and the dropout masks.
        threads: torch intra-op threads (0: leave torch's default).
        input_noise: standard deviation (m) of a random walk added to the input positions
            ``x_{t-2}, x_{t-1}, x_t`` (GNS's remedy for error accumulation), one shift per rigid
            object (``gns``: one per leaf, the target correcting the velocity noise only).
        input_noise_ratio: with ``input_noise`` 0, the noise as a fraction of the normaliser's
            mean velocity scale (``gns``: :data:`~hrn_pyg.nn.gns.NOISE_TO_VELOCITY_STD`); 0: off.
        device: where the model and batches live ("" : CUDA when available, else CPU).
        workers: background processes assembling batches (0: in the training process).
        stop_at: end after this many of ``steps`` (the schedule still spans ``steps``) and write
            that step's ``model.pt``; 0: train all ``steps``.
        time_limit: minutes after which this call stops as if interrupted (``--resume``
            continues); 0: no limit.
        augment_symmetry: turn every window about the vertical axis at random (a mirror half the
            time), with symmetric normaliser statistics (:mod:`hrn_pyg.data.symmetry`).
        w_rest: weight of :func:`~hrn_pyg.losses.rest_velocity_loss`, the absolute velocity error
            of the objects the ground truth has at rest (0: off, the seed paper's loss).
        rest_threshold: metres per step under which a root's true velocity counts as rest.
        rest_rollout: R >= 1 starts every window whose scene is at rest from the model's own
            rollout of 1 to R steps (no gradient) and trains it to hold that state
            (:func:`held_rest_sequence`); 0: off.
        rest_rollout_draw: how R is drawn from 1..rest_rollout each batch: uniform, or log
            (log-uniform).
        init_from: a ``model.pt`` to fine-tune (weights, normaliser and model settings kept, a
            fresh optimiser); "" : a fresh network. Ignored when a run resumes.
        extra_data: more episode folders, comma-separated, joining ``data``'s in every split.
        data_weights: ``name=weight`` pairs, comma-separated, ``name`` a folder's last path
            component: its windows are drawn ``weight`` times as often as others (default 1).
    """

    preset: str = "ours"
    data: str = "data/soft_bounce"
    out: str = "runs/train/soft_bounce_ours"
    steps: int = 2000
    batch_size: int = 4
    lr: float = 1e-3
    warmup: int = 50
    grad_clip: float = 1.0
    seq_start: int = 1
    seq_end: int = 6
    grow_until: float = 0.6
    shape_loss: str = "full"
    shape_chunk: int = DEFAULT_CHUNK_SIZE
    w_local: float = 1.0
    w_global: float = 1.0
    w_shape: float = 1.0
    train_dropout: float = 0.0
    checkpoint_every: int = 200
    eval_every: int = 200
    snapshot_every: int = 0
    ema_decay: float = 0.0
    seed: int = 0
    threads: int = 0
    input_noise: float = 0.0
    input_noise_ratio: float = 0.0
    device: str = ""
    workers: int = 0
    stop_at: int = 0
    time_limit: float = 0.0
    augment_symmetry: bool = False
    w_rest: float = 0.0
    rest_threshold: float = 1e-3
    rest_rollout: int = 0
    rest_rollout_draw: str = "uniform"
    init_from: str = ""
    extra_data: str = ""
    data_weights: str = ""

    @property
    def data_folders(self) -> list[str]:
        """``data`` and the folders of ``extra_data``."""
        return [self.data, *(f for f in self.extra_data.split(",") if f)]

    @property
    def folder_weights(self) -> list[float]:
        """The draw weight of each folder of :attr:`data_folders` (see ``data_weights``)."""
        return parse_data_weights(self.data_weights, self.data_folders)

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f"preset must be one of {PRESETS}, got {self.preset!r}")
        parse_data_weights(self.data_weights, self.data_folders)  # a bad data_weights fails here, before any work
        if self.shape_loss not in SHAPE_LOSSES:
            raise ValueError(f"shape_loss must be one of {SHAPE_LOSSES}, got {self.shape_loss!r}")
        for name in ("steps", "batch_size", "seq_start", "seq_end", "shape_chunk", "checkpoint_every", "eval_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.lr > 0 or not math.isfinite(self.lr):
            raise ValueError(f"lr must be a positive number, got {self.lr}")
        if not 0.0 <= self.train_dropout < 1.0:
            raise ValueError(f"train_dropout must be in [0, 1), got {self.train_dropout}")
        if not 0.0 <= self.input_noise < math.inf:
            raise ValueError(f"input_noise must be a finite number >= 0, got {self.input_noise}")
        if not 0.0 <= self.input_noise_ratio < math.inf:
            raise ValueError(f"input_noise_ratio must be a finite number >= 0, got {self.input_noise_ratio}")
        if self.preset == "gns" and (self.w_rest or self.rest_rollout or self.seq_end != 1):
            raise ValueError("the gns preset trains one step on the acceleration loss: w_rest, rest_rollout "
                             "and seq_end > 1 are options of the HRN presets")
        if self.rest_rollout < 0:
            raise ValueError(f"rest_rollout must be >= 0 (0: off), got {self.rest_rollout}")
        if self.threads < 0:
            raise ValueError(f"threads must be >= 0 (0: torch's default), got {self.threads}")
        if self.rest_rollout_draw not in REST_ROLLOUT_DRAWS:
            raise ValueError(f"rest_rollout_draw must be one of {REST_ROLLOUT_DRAWS}, got {self.rest_rollout_draw!r}")
        if not 0 <= self.stop_at <= self.steps:
            raise ValueError(f"stop_at must be between 0 (off) and steps={self.steps}, got {self.stop_at}")
        if not 0.0 <= self.time_limit < math.inf:
            raise ValueError(f"time_limit must be a finite number of minutes >= 0, got {self.time_limit}")
        if self.workers < 0:
            raise ValueError(f"workers must be >= 0, got {self.workers}")
        if self.snapshot_every < 0:
            raise ValueError(f"snapshot_every must be >= 0 (0: none), got {self.snapshot_every}")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"ema_decay must be in [0, 1) (0: off), got {self.ema_decay}")
        if self.seq_start > self.seq_end:
            raise ValueError(f"seq_start ({self.seq_start}) must be <= seq_end ({self.seq_end})")
        if not 0.0 <= self.w_rest < math.inf:
            raise ValueError(f"w_rest must be a finite number >= 0, got {self.w_rest}")
        if not 0.0 < self.rest_threshold < math.inf:
            raise ValueError(f"rest_threshold must be a finite number > 0 (metres per step), got {self.rest_threshold}")

    @classmethod
    def for_preset(cls, preset: str, **overrides: Any) -> TrainConfig:
        """The preset's defaults (:data:`PRESET_OVERRIDES`), then ``overrides`` (None values ignored)."""
        base: dict[str, Any] = {"preset": preset, **PRESET_OVERRIDES.get(preset, {})}
        base.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**base)


def parse_data_weights(text: str, folders: Sequence[str]) -> list[float]:
    """The draw weight of each of ``folders`` from ``name=weight`` pairs (comma-separated,
    ``name`` a folder's last path component; folders not named weigh 1). A name that is no
    folder's, a name given twice, a name shared by two folders, or a weight that is not a
    finite number > 0 is a one-line ``ValueError``."""
    names = [Path(f).name for f in folders]
    weights = [1.0] * len(folders)
    given: set[str] = set()
    for pair in (p.strip() for p in text.split(",")):
        if not pair:
            continue
        name, sep, value = pair.partition("=")
        name = name.strip()
        if not sep or not name:
            raise ValueError(f"data_weights: expected name=weight, got {pair!r}")
        if name in given:
            raise ValueError(f"data_weights: {name!r} is given twice")
        if names.count(name) != 1:
            why = "is not a folder" if name not in names else "names more than one folder"
            raise ValueError(f"data_weights: {name!r} {why} of the training data ({', '.join(names)})")
        try:
            weight = float(value)
        except ValueError:
            raise ValueError(f"data_weights: the weight of {name!r} must be a number, got {value!r}") from None
        if not 0 < weight < math.inf:
            raise ValueError(f"data_weights: the weight of {name!r} must be a finite number > 0, got {value!r}")
        given.add(name)
        weights[names.index(name)] = weight
    return weights
