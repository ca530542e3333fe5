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
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from collections.abc import Collection, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor
from torch.utils.data import DataLoader
from torch_geometric.data import Batch, HeteroData
from tqdm import tqdm

from hrn_pyg.checkpoints import APPLIED_OPTIONS, checkpoint_config, load_model, training_domain, with_applied_options
from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.data.graph import CHILD_TO_PARENT, NODE, RIGID, WITHIN_SIBLINGS, set_state
from hrn_pyg.data.symmetry import apply_vertical_symmetry, random_vertical_symmetries
from hrn_pyg.losses import (
    DEFAULT_CHUNK_SIZE,
    full_shape_loss,
    global_velocity_loss,
    group_shape_loss,
    local_velocity_loss,
    rest_velocity_loss,
    shape_groups,
)
from hrn_pyg.nn.gns import NOISE_TO_VELOCITY_STD, GNS, GNSConfig, fit_acceleration
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.nn.networks import Network, NetworkConfig, build_network, network_from_dict
from hrn_pyg.nn.normalizer import fit_normalizer, isotropic_horizontal
from hrn_pyg.nn.pitch import collision_radius_of, is_pitch_aware
from hrn_pyg.nn.state import to_local_velocity
from hrn_pyg.nn.widen import widen_to_pitch_aware, with_collision_force, with_material_heads
from hrn_pyg.sim.rollout import iterate
from hrn_pyg.sim.step import root_of
from hrn_pyg.utils.checkpoint import (
    load_checkpoint,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from hrn_pyg.utils.device import resolve_device
from hrn_pyg.utils.files import atomic_write_json
from hrn_pyg.utils.metrics import CSVLog
from hrn_pyg.utils.options import add_no_progress, add_removed, add_renamed, attribute_help, shown_default
from hrn_pyg.utils.schedules import SequenceLengthSchedule, cosine_lr_factor
from hrn_pyg.utils.weight_average import WeightAverage
from hrn_pyg.viz import plot_curves

PRESETS = ("hrn", "ours", "gns")
SHAPE_LOSSES = ("group", "full")
#: how :func:`held_rest_sequence` draws its rollout length R from 1..R_max
REST_ROLLOUT_DRAWS = ("uniform", "log")
#: windows used to fit the normaliser (the statistics converge long before this)
NORMALIZER_WINDOWS = 256
#: validation windows scored at every evaluation
VAL_WINDOWS = 8
#: columns of ``metrics.csv`` (read by name; ``rest`` is empty unless ``w_rest`` > 0; ``acceleration``
#: is the ``gns`` preset's loss, the HRN terms are empty there)
LOG_FIELDS = ["step", "seq_len", "lr", "loss", "local", "global", "shape", "rest", "val_loss", "seconds", "acceleration"]
#: options of earlier releases that no recipe or shipped model used; given, they warn and are
#: ignored, for one release
REMOVED_OPTIONS = ("--sample-copies", "--w-energy", "--w-contact", "--contact-floor", "--w-ground", "--ground-floor",
                   "--rest-leaves")


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
        snapshot_every: keep the model (weights, config and normaliser, like ``model.pt``) every
            that many steps in ``snapshots/step_<step>.pt``, so a model can be selected on
            validation afterwards; 0: none.
        ema_decay: keep an exponential moving average of the weights,
            ``w_avg <- d * w_avg + (1 - d) * w`` after every optimiser step
            (:class:`~hrn_pyg.utils.weight_average.WeightAverage`), starting at the run's first
            weights: the average is the run's model (``model.pt``, snapshots) and is what the
            validation loss scores, and ``last.pt`` keeps both it and the trained weights, so a
            resumed run continues the same average. It spans about ``1 / (1 - d)`` steps
            (0.997: about 330). 0: off, the last weights are the model.
        seed: seeds the model initialisation, the window draws and the dropout masks.
        threads: torch intra-op threads (0: leave torch's default).
        input_noise: standard deviation (m) of a random walk added to the input positions
            ``x_{t-2}, x_{t-1}, x_t`` of each window (GNS's remedy for error accumulation); the
            first step's velocity target is measured from the noisy ``x_t``. Rigid objects get one
            shift per object, so their inputs stay rigid (``gns``: every leaf its own walk, and
            the target corrects the velocity noise only, as the GNS paper's).
        input_noise_ratio: with ``input_noise`` 0, the noise is this fraction of the mean
            per-axis velocity scale of the fitted normaliser (the ``gns`` preset's
            :data:`~hrn_pyg.nn.gns.NOISE_TO_VELOCITY_STD`); the resolved ``input_noise`` is what
            ``config.json`` records. 0: off.
        device: where the model and batches live ("" : CUDA when available, else CPU).
        workers: background processes assembling batches (0: in the training process).
        stop_at: end the training after this many of its ``steps`` (the learning-rate schedule
            still spans ``steps``) and write ``model.pt`` of that step: a stage that keeps an
            early point of a longer schedule; 0: train all ``steps``.
        time_limit: minutes after which this call stops as if interrupted (checkpoint written,
            ``--resume`` continues); 0: no limit. For fixed-length sittings and lent machines.
        augment_symmetry: map every training window by a random turn about the vertical axis
            (and a mirror half the time), one per copy, and give the normaliser the symmetric
            statistics (no horizontal mean): :mod:`hrn_pyg.data.symmetry`.
        w_rest: weight of :func:`~hrn_pyg.losses.rest_velocity_loss`, the absolute velocity error
            of the objects the ground truth has at rest (0: off, the seed paper's loss).
        rest_threshold: metres per step under which a root's true velocity counts as rest.
        rest_rollout: R >= 1 starts every window whose scene is at rest from the model's own
            rollout of 1 to R steps (drawn per batch, no gradient) and trains it to hold the state
            it reached (:func:`held_rest_sequence`), so the slow creep of a long rollout from rest
            is seen where it happens, away from the true rest state; 0: off.
        rest_rollout_draw: how R is drawn from 1..rest_rollout each batch: uniform, or log
            (log-uniform, as many draws in 1-16 as in 16-256, so long rollouts are seen without
            paying for one every batch).
        init_from: a model checkpoint (``model.pt``) to start from instead of a fresh network:
            its weights, normaliser and model settings are kept, the optimiser starts anew
            (fine-tuning); "" : a fresh network. Ignored when a run resumes.
        extra_data: more episode folders, comma-separated, whose episodes join ``data``'s in
            every split (e.g. a fine-tuning on a mix of the scene's data and a dataset of one
            situation it must learn); "" : ``data`` alone. A seed repeats across them only
            between different scenes (``meta.json``).
        data_weights: ``name=weight`` pairs, comma-separated, ``name`` a folder of ``data`` or
            ``extra_data`` by its last path component: each window of that folder is drawn
            ``weight`` times as often as a window of a folder not named (weight 1). Windows are
            otherwise drawn uniformly, so a folder's share of the batches is its share of the
            windows; a weight corrects that (a small dataset of one situation the model must
            learn, a large one it knows). "" : every window equally likely.
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
        """The preset's defaults, then ``overrides`` (None values ignored)."""
        base: dict[str, Any] = {"preset": preset}
        if preset == "hrn":
            base.update(seq_start=1, seq_end=1, shape_loss="group")
        elif preset == "ours":
            base.update(seq_start=1, seq_end=6, shape_loss="full")
        elif preset == "gns":
            base.update(seq_start=1, seq_end=1, lr=1e-4, input_noise_ratio=NOISE_TO_VELOCITY_STD)
        base.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**base)


# --------------------------------------------------------------------------------------------
# the loss of one window


def _batch_size_of(graph: HeteroData) -> int:
    if isinstance(graph, Batch):
        return int(graph.num_graphs)
    store = graph[NODE]
    return int(store.batch.max()) + 1 if "batch" in store and store.batch.numel() else 1


def window_loss(model: HRN, window: HeteroData, seq_len: int, config: TrainConfig,
                generator: torch.Generator | None = None,
                noise_generator: torch.Generator | None = None) -> tuple[Tensor, dict[str, float]]:
    r"""Loss of unrolling the model ``seq_len`` steps from a (batched) window.

    .. math::
        \mathcal{L} = \sum_{k=1}^{T} w_{loc}\mathcal{L}_{loc}^{(k)} + w_{glob}\mathcal{L}_{glob}^{(k)}
            + w_{shape}\mathcal{L}_{shape}^{(k)} \; [+\, w_{rest}\mathcal{L}_{rest}^{(k)}]

    Step ``k`` starts from the model's own prediction of step ``k-1`` (ground truth for
    ``k = 1``). The local term compares velocities in the parent's frame, the global term the
    positions of roots and leaves (at ``k = 1`` the same as their global velocity error), both
    divided by the velocity scale; the shape term is the group or fully-connected
    pairwise-distance error. With ``seq_len = 1`` this is the baseline HRN's one-step loss.
    With ``config.w_rest > 0``, :func:`~hrn_pyg.losses.rest_velocity_loss` adds the absolute
    velocity error of the objects at rest in the truth (step ``k``'s own prediction against the
    true displacement ``x_{k+1} - x_k``).

    A :class:`~hrn_pyg.nn.gns.GNS` is scored by :func:`acceleration_loss` instead.
    """
    if isinstance(model, GNS):
        return acceleration_loss(model, window, config, generator, noise_generator)
    store = window[NODE]
    if "pos_seq" not in store or store.pos_seq.size(1) < seq_len + 3:
        have = store.pos_seq.size(1) - 3 if "pos_seq" in store else 0
        raise ValueError(f"window holds {have} future steps, the unroll needs {seq_len}")
    seq, forces = store.pos_seq, store.force_seq
    if config.rest_rollout > 0:
        seq = held_rest_sequence(model, window, seq_len, config.rest_rollout, config.rest_threshold, noise_generator,
                                 draw=config.rest_rollout_draw)
    inputs = seq[:, :3]
    if config.input_noise > 0:
        inputs = inputs + input_noise(window, config.input_noise, noise_generator)
    radius = collision_radius_of(model.config, window)  # one per window when their pitches differ
    graph = set_state(window, inputs[:, 0], inputs[:, 1], inputs[:, 2], radius=radius)
    norm = model.normalizer
    vel_scale = norm.velocity_std
    shape_scale = vel_scale.mean()
    c2p = window[CHILD_TO_PARENT].edge_index
    leaf_index, groups = shape_groups(window)
    # rigid bodies under the rigid fit keep their input's distances: no gradient to compute
    fixed_shape = store.material[leaf_index, RIGID].bool() if getattr(model.config, "rigid_fit", False) else None
    copies = _batch_size_of(window)
    parts = {"local": seq.new_zeros(()), "global": seq.new_zeros(()), "shape": seq.new_zeros(())}
    if config.w_rest > 0:
        parts["rest"] = seq.new_zeros(())
    total = seq.new_zeros(())
    masks_fn = None
    if config.train_dropout > 0:  # one mask per copy per step, drawn as the step starts
        def masks_fn(t: int, g: HeteroData) -> dict[str, Tensor]:
            return model.sample_masks(copies, config.train_dropout, generator)
    unrolled = iterate(model, graph, seq_len, forces.transpose(0, 1), masks_fn, sleep=None)
    for k, result in enumerate(unrolled):  # unrolled time steps, with gradients through all of them
        # the first target is measured from the (possibly noisy) input, later ones from the truth
        true_prev, true_next = (graph[NODE].pos if k == 0 else seq[:, k + 2]), seq[:, k + 3]
        true_local = to_local_velocity(true_next - true_prev, c2p)
        loss_local = local_velocity_loss(result.local_velocity, true_local, store.is_root, store.is_static, norm)
        loss_global = global_velocity_loss(result.pos, true_next, store.is_root, store.is_leaf, store.is_static, vel_scale)
        if config.shape_loss == "full":
            loss_shape = full_shape_loss(result.pos[leaf_index], true_next[leaf_index], groups,
                                         config.shape_chunk, shape_scale, fixed_shape)
        else:
            loss_shape = group_shape_loss(result.pos, true_next, window[WITHIN_SIBLINGS].edge_index, shape_scale)
        total = total + config.w_local * loss_local + config.w_global * loss_global + config.w_shape * loss_shape
        parts["local"] = parts["local"] + loss_local.detach()
        parts["global"] = parts["global"] + loss_global.detach()
        parts["shape"] = parts["shape"] + loss_shape.detach()
        if config.w_rest > 0:  # objects the truth has still: their own velocity error, absolute
            loss_rest = rest_velocity_loss(result.pos - graph[NODE].pos, true_next - seq[:, k + 2], store.is_root,
                                           store.is_static, config.rest_threshold, vel_scale)
            total = total + config.w_rest * loss_rest
            parts["rest"] = parts["rest"] + loss_rest.detach()
        graph = result.graph
    # one host transfer for the logged parts
    values = torch.stack(list(parts.values())).tolist()
    return total, dict(zip(parts, values))


def resting_windows(window: HeteroData, seq_len: int, threshold: float) -> Tensor:
    r"""``[B]`` bool: the windows of a batch whose scene is at rest over the frames an unroll of
    ``seq_len`` steps reads, every moving leaf within ``threshold`` metres of where it starts:

    .. math::
        \max_{i \text{ moving leaf of } b} \ \max_{0 \le t \le T + 2} \lVert x_i(t) - x_i(0) \rVert < \tau
    """
    store = window[NODE]
    frames = store.pos_seq[:, : seq_len + 3]
    moved = (frames - frames[:, :1]).norm(dim=-1).amax(dim=1)  # [N]
    moved = torch.where(store.is_leaf & ~store.is_static, moved, torch.zeros_like(moved))
    batch = store.batch if "batch" in store else torch.zeros_like(moved, dtype=torch.long)
    count = _batch_size_of(window)
    farthest = moved.new_zeros(count).scatter_reduce(0, batch, moved, "amax")
    return farthest < threshold


def rest_rollout_length(max_steps: int, draw: str = "uniform", generator: torch.Generator | None = None) -> int:
    r"""One rollout length :math:`R \in \{1, \dots, R_{max}\}` of :func:`held_rest_sequence`:
    ``uniform``, or ``log``: :math:`R = \lfloor (R_{max} + 1)^u \rfloor`, :math:`u \sim U[0, 1)`, so
    :math:`P(R = k) = \ln\frac{k + 1}{k} / \ln(R_{max} + 1)` and every doubling of R is about as
    likely as the last (mean :math:`\approx R_{max} / \ln R_{max}` rather than :math:`R_{max} / 2`)."""
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    if draw == "uniform":
        return int(torch.randint(1, max_steps + 1, (1,), generator=generator))
    if draw == "log":
        u = float(torch.rand((), generator=generator, dtype=torch.float64))
        return min(max(int(math.floor((max_steps + 1) ** u)), 1), max_steps)
    raise ValueError(f"draw must be one of {REST_ROLLOUT_DRAWS}, got {draw!r}")


def held_rest_sequence(model: HRN, window: HeteroData, seq_len: int, max_steps: int, threshold: float,
                       generator: torch.Generator | None = None, draw: str = "uniform") -> Tensor:
    r"""The window's ``pos_seq`` ``[N, T+3, 3]`` with each scene at rest (:func:`resting_windows`)
    replaced by the model's own rollout from it and the order to hold still there.

    From the window's first three true frames the model runs :math:`R` steps on its own (no
    gradient, no dropout, no sleeping, no external force), :math:`R` drawn from ``1..max_steps``
    once per batch (:func:`rest_rollout_length`, by ``draw``); a resting scene's frames become

    .. math::
        \bigl(\hat x(R-2),\ \hat x(R-1),\ \hat x(R),\ \hat x(R),\ \dots,\ \hat x(R)\bigr)

    so its inputs carry whatever the model's own rollout did to it (a soft body sinking, a cloth
    creeping sideways) and every target is to stop there. Training only from the true rest state
    never shows the model the states its slow drift leads to; this does, at the cost of
    :math:`R` forward passes of the resting windows per batch (a batched window rolls only its
    resting graphs). Windows not at rest keep their frames; a batch with none at rest costs
    nothing.
    """
    store = window[NODE]
    seq = store.pos_seq
    resting = resting_windows(window, seq_len, threshold)
    if not bool(resting.any()):
        return seq
    steps = rest_rollout_length(max_steps, draw, generator)
    batch = store.batch if "batch" in store else torch.zeros(seq.size(0), dtype=torch.long, device=seq.device)
    rows = resting[batch]  # [N]: the nodes of the resting windows
    still = window
    if isinstance(window, Batch) and not bool(resting.all()):  # roll the resting graphs alone
        still = Batch.from_data_list(window.index_select(torch.nonzero(resting).flatten()))
    start = still[NODE].pos_seq
    radius = collision_radius_of(model.config, still)
    with torch.no_grad():
        graph = set_state(still, start[:, 0], start[:, 1], start[:, 2], radius=radius)
        frames = [start[:, 0], start[:, 1], start[:, 2]]
        for result in iterate(model, graph, steps, None, None, sleep=None):
            frames = [frames[1], frames[2], result.pos]
    held = torch.stack(frames + [frames[-1]] * (seq.size(1) - 3), dim=1)  # [N', T+3, 3]
    out = seq.clone()
    out[rows] = held[rows] if still is window else held
    return out


def acceleration_loss(model: GNS, window: HeteroData, config: TrainConfig,
                      generator: torch.Generator | None = None,
                      noise_generator: torch.Generator | None = None) -> tuple[Tensor, dict[str, float]]:
    r"""The GNS's one-step loss on a (batched) window: the mean squared error of the normalised
    acceleration over the moving leaves and the three axes.

    .. math::
        \mathcal{L} = \Bigl\langle \bigl((\hat x_{t+1} - \tilde x_t) - (x_{t+1} - x_t)\bigr)^2
            / \sigma_a^2 \Bigr\rangle

    :math:`\tilde x = x + n` are the inputs with per-leaf random-walk noise (``input_noise``,
    none on static leaves), :math:`\hat x_{t+1}` the step's prediction from them. With
    :math:`\tilde v_t = \tilde x_t - \tilde x_{t-1}` this is the error of the normalised
    acceleration against the GNS paper's target :math:`(x_{t+1} + n_t) - \tilde x_t - \tilde v_t`:
    the model learns to undo the velocity noise, not the position noise. The prediction runs
    through the package's step (:func:`~hrn_pyg.sim.rollout.iterate`, no sleeping).
    """
    store = window[NODE]
    if "pos_seq" not in store or store.pos_seq.size(1) < 4:
        raise ValueError("acceleration_loss: the window holds no future step")
    seq = store.pos_seq
    inputs = seq[:, :3]
    if config.input_noise > 0:
        inputs = inputs + input_noise(window, config.input_noise, noise_generator, rigid_shift=False)
    graph = set_state(window, inputs[:, 0], inputs[:, 1], inputs[:, 2], radius=None)  # iterate searches
    masks_fn = None
    if config.train_dropout > 0:
        copies = _batch_size_of(window)

        def masks_fn(t: int, g: HeteroData) -> dict[str, Tensor]:
            return model.sample_masks(copies, config.train_dropout, generator)
    forces = store.force_seq[:, :1].transpose(0, 1)
    result = next(iterate(model, graph, 1, forces, masks_fn, sleep=None))
    moving = store.is_leaf & ~store.is_static
    error = (result.pos - graph[NODE].pos) - (seq[:, 3] - seq[:, 2])
    loss = (error[moving] / model.acceleration_std).square().mean()
    return loss, {"acceleration": float(loss.detach())}


def input_noise(window: HeteroData, std: float, generator: torch.Generator | None = None,
                rigid_shift: bool = True) -> Tensor:
    r"""Random-walk noise for the three input positions of a window, ``[N, 3, 3]``.

    .. math::
        n_{t-2} = \epsilon_0, \quad n_{t-1} = \epsilon_0 + \epsilon_1, \quad
        n_t = \epsilon_0 + \epsilon_1 + \epsilon_2, \qquad \epsilon_k \sim \mathcal{N}(0, \sigma^2 / 3)

    so the noise of ``x_t`` has standard deviation :math:`\sigma` and the input velocities are
    perturbed consistently. Every leaf of a rigid object takes its root's draw (a rigid shift;
    ``rigid_shift=False``: its own, as for the GNS), a static particle none; ancestor rows are
    re-derived by ``set_state`` anyway.
    """
    store = window[NODE]
    n = store.num_nodes
    device = store.pos_seq.device
    steps = torch.randn(n, 3, 3, generator=generator, device="cpu" if generator is not None else device)
    walk = steps.to(device).cumsum(dim=1) * (std / math.sqrt(3.0))
    if rigid_shift:
        rigid = store.material[:, RIGID].bool()
        walk = torch.where(rigid[:, None, None], walk[root_of(window)], walk)
    return torch.where(store.is_static[:, None, None], torch.zeros_like(walk), walk)


# --------------------------------------------------------------------------------------------
# distributed helpers (nccl on CUDA, gloo on CPU; a no-op on one process)


def _world() -> tuple[int, int]:
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def _maybe_init_distributed(device: torch.device) -> bool:
    if int(os.environ.get("WORLD_SIZE", "1")) > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        return True
    return False


def _average_gradients(model: torch.nn.Module) -> None:
    """Average gradients over ranks (a module not run on some rank contributes zeros)."""
    _, world = _world()
    if world == 1:
        return
    for p in model.parameters():
        if p.grad is None:
            p.grad = torch.zeros_like(p)
        dist.all_reduce(p.grad)
        p.grad /= world


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


def window_draw_weights(train_set: EpisodeWindows, folders: Sequence[str],
                        folder_weights: Sequence[float]) -> Tensor | None:
    """The cumulative draw weight of ``train_set``'s windows, each window weighted by its
    folder's entry of ``folder_weights`` (``(W,)`` float64, for :func:`_draw_windows`); None when
    every weight is 1 (uniform draws)."""
    if all(w == 1.0 for w in folder_weights):
        return None
    by_folder = {Path(f).resolve(): w for f, w in zip(folders, folder_weights)}
    per_episode = torch.tensor([by_folder[Path(p).parent.resolve()] for p in train_set.paths], dtype=torch.float64)
    return torch.cumsum(per_episode[torch.as_tensor(train_set.window_episodes)], 0)


def _draw_windows(n: int, batch_size: int, seed: int, step: int, rank: int,
                  cumulative: Tensor | None = None) -> list[int]:
    """The window indices of one step: a pure function of (seed, step, rank), so a resumed run
    draws exactly what the uninterrupted one would have. Uniform over the ``n`` windows, or, with
    ``cumulative`` (the windows' cumulative weights, :func:`window_draw_weights`), each window
    with probability proportional to its weight."""
    g = torch.Generator().manual_seed(seed * 1_000_003 + step * 7919 + rank * 104_729 + 1)
    if cumulative is None:
        return torch.randint(n, (batch_size,), generator=g).tolist()
    u = torch.rand(batch_size, generator=g, dtype=torch.float64) * cumulative[-1]
    return torch.searchsorted(cumulative, u, right=True).clamp_(max=n - 1).tolist()


class StepWindows:
    """Batch sampler of a run: the window indices of steps ``start .. end-1`` (see
    :func:`_draw_windows`), so a ``DataLoader`` with workers yields what the loop would draw."""

    def __init__(self, n: int, batch_size: int, seed: int, rank: int, start: int, end: int,
                 cumulative: Tensor | None = None) -> None:
        self.n, self.batch_size, self.seed, self.rank, self.start, self.end = n, batch_size, seed, rank, start, end
        self.cumulative = cumulative

    def __iter__(self):
        for step in range(self.start, self.end):
            yield _draw_windows(self.n, self.batch_size, self.seed, step, self.rank, self.cumulative)

    def __len__(self) -> int:
        return max(self.end - self.start, 0)


def _collate(windows: list[HeteroData]) -> HeteroData:
    return Batch.from_data_list(windows)


# --------------------------------------------------------------------------------------------
# the run, stage by stage (train() below takes them in this order)


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


@dataclass(frozen=True)
class _Place:
    """Where this process trains: its device, its rank among ``world`` processes, and whether this
    call joined the process group (and so leaves it at exit)."""

    device: torch.device
    rank: int
    world: int
    joined_group: bool


def _place_process(config: TrainConfig) -> _Place:
    """Pick the device, join the process group under ``torchrun`` (one GPU per rank on CUDA) and
    set the number of threads."""
    device = resolve_device(config.device)
    joined_group = _maybe_init_distributed(device)
    rank, world = _world()
    if device.type == "cuda" and world > 1:
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", rank)) % torch.cuda.device_count())
        torch.cuda.set_device(device)
    if config.threads > 0:
        torch.set_num_threads(config.threads)
    return _Place(device, rank, world, joined_group)


def _load_splits(config: TrainConfig) -> tuple[EpisodeWindows, EpisodeWindows | None]:
    """The training and validation windows of ``data`` and ``extra_data`` (None: no validation
    episodes)."""
    # every episode stays decoded in memory: windows are drawn at random across the whole split
    train_set = EpisodeWindows(config.data_folders, "train", horizon=config.seq_end, cache_episodes=1 << 20)
    try:
        val_set = EpisodeWindows(config.data_folders, "val", horizon=config.seq_end, cache_episodes=1 << 20)
    except ValueError:
        val_set = None  # a folder without validation episodes trains without a validation score
    return train_set, val_set


def _checkpoint_to_resume(last: Path, resume: bool) -> dict[str, Any] | None:
    """The checkpoint ``last`` when resuming (an error if there is none); None for a new run."""
    if not resume:
        return None
    if not last.is_file():
        raise FileNotFoundError(f"--resume: no checkpoint at {last}")
    return load_checkpoint(last)


def _initial_model(config: TrainConfig, model_config: NetworkConfig, train_set: EpisodeWindows,
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
    """The model of checkpoint ``path``, in training mode, for ``init_from``.

    Its settings are the checkpoint's: a ``model_config`` that sets something else (anything
    that differs from the checkpoint and either differs from the defaults or is named in
    ``given``, the options set on purpose) is an error, not silently ignored;
    except the options of :data:`APPLIED_OPTIONS`, which change how the same weights are applied
    (``mirror_average``, ``mirror_planes``): set, they hold from this fine-tuning on. A
    ``model_config`` with ``pitch_aware`` from a plain checkpoint starts a pitch-aware model from
    its weights (:func:`hrn_pyg.nn.widen.widen_to_pitch_aware`, the new column's weights zero);
    that new model takes the applied options of ``model_config`` as given (e.g. one pass, where
    the checkpoint averaged over mirrors). One with ``material_heads`` from a checkpoint without
    them starts every material's head as a copy of the checkpoint's one head
    (:func:`hrn_pyg.nn.widen.with_material_heads`); one with ``collision_force`` from a checkpoint
    without it starts the collision module's weights on the force at zero
    (:func:`hrn_pyg.nn.widen.with_collision_force`).
    """
    model = load_model(path)
    if type(model.config) is not type(model_config):
        raise ValueError(f"init_from={path!r} is a {type(model).__name__}, this preset trains a "
                         f"{type(model_config).__name__.removesuffix('Config')}")
    if getattr(model_config, "pitch_aware", False) and not model.config.pitch_aware:
        applied = {k: getattr(model_config, k) for k in APPLIED_OPTIONS}
        model = widen_to_pitch_aware(model, reference_pitch=model_config.reference_pitch, **applied)
    if getattr(model_config, "material_heads", False) and not model.config.material_heads:
        model = with_material_heads(model)
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


def resolved_noise(config: TrainConfig, model: Network) -> TrainConfig:
    """``config`` with ``input_noise`` set from ``input_noise_ratio`` (times the mean per-axis
    velocity scale of ``model``'s fitted normaliser) when it is 0 and the ratio is not."""
    if config.input_noise > 0 or config.input_noise_ratio == 0:
        return config
    scale = float(model.normalizer.velocity_std.mean())
    return replace(config, input_noise=config.input_noise_ratio * scale)


def _optimiser(model: HRN, config: TrainConfig) -> tuple[torch.optim.Adam, torch.optim.lr_scheduler.LambdaLR]:
    """Adam at ``config.lr`` under the warm-up + cosine schedule of :func:`cosine_lr_factor`."""
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda s: cosine_lr_factor(s, config.steps, config.warmup))
    return optimizer, scheduler


def _restore_training_state(ckpt: dict[str, Any], optimizer: torch.optim.Optimizer,
                            scheduler: torch.optim.lr_scheduler.LambdaLR) -> int:
    """Continue the checkpoint's optimiser, learning-rate schedule and global random streams;
    returns the number of steps it had done."""
    optimizer.load_state_dict(ckpt["optimizer"])
    scheduler.load_state_dict(ckpt["scheduler"])
    set_rng_state(ckpt["rng"])
    return int(ckpt["step"])


def _weight_average(model: Network, config: TrainConfig, ckpt: dict[str, Any] | None) -> WeightAverage | None:
    """The run's weight average under ``ema_decay`` (None when off): the checkpoint's when it
    has one, else started at the model's weights (a new run, or a run that turns it on)."""
    if config.ema_decay == 0:
        return None
    average = WeightAverage(model, config.ema_decay)
    if ckpt is not None and "weight_average" in ckpt:
        average.load_state_dict(ckpt["weight_average"])
    return average


def _open_run_folder(out: Path, config: TrainConfig, model: HRN, place: _Place,
                     resumed_at: int | None) -> CSVLog | None:
    """On rank 0, write ``config.json`` and open ``metrics.csv``, dropping the rows of the steps
    after ``resumed_at`` (the steps done by the checkpoint a resumed run continues); the log, or
    None on other ranks."""
    if place.rank != 0:
        return None
    log = CSVLog(out / "metrics.csv", LOG_FIELDS)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "config.json", {"model": model.config.to_dict(), "train": asdict(config),
                                            "world_size": place.world})
    if resumed_at is not None:
        log.truncate_after(resumed_at - 1)
    return log


def _step_batches(train_set: EpisodeWindows, config: TrainConfig, place: _Place, start: int, end: int) -> DataLoader:
    """The batches of steps ``start .. end-1`` (windows drawn by :class:`StepWindows`), collated by
    ``config.workers`` background processes (0: in this one)."""
    cumulative = window_draw_weights(train_set, config.data_folders, config.folder_weights)
    return DataLoader(train_set, batch_sampler=StepWindows(len(train_set), config.batch_size, config.seed,
                                                           place.rank, start, end, cumulative),
                      collate_fn=_collate, num_workers=config.workers, pin_memory=place.device.type == "cuda",
                      # its own generator: the loader's seed draw must not shift the global
                      # random stream that dropout masks use (resume would then diverge)
                      generator=torch.Generator().manual_seed(config.seed))


def _augmentation_streams(config: TrainConfig, rank: int,
                          start: int) -> tuple[torch.Generator | None, torch.Generator | None]:
    """This rank's generators of the input noise (and the rest rollout's lengths) and of the symmetry
    draws (None where off).

    Both are streams of their own, apart from the global one that the dropout masks use, and
    both are seeded with the first step, so a resumed run draws fresh noise and symmetries.
    """
    noise = (torch.Generator().manual_seed(config.seed * 7 + rank + 3 + start)
             if config.input_noise > 0 or config.rest_rollout > 0 else None)
    turns = torch.Generator().manual_seed(config.seed * 11 + rank + 5 + start) if config.augment_symmetry else None
    return noise, turns


def _validation_ids(val_set: EpisodeWindows | None) -> list[int]:
    """The :data:`VAL_WINDOWS` validation windows scored at every evaluation, spread over the
    split (none without validation episodes)."""
    if not val_set:
        return []
    return list(range(0, len(val_set), max(1, len(val_set) // VAL_WINDOWS)))[:VAL_WINDOWS]


def _on_device(batch: HeteroData, device: torch.device, turns: torch.Generator | None) -> HeteroData:
    """A batch moved to ``device``, every window turned (and maybe mirrored) by a draw from
    ``turns`` when given."""
    batch = batch.to(device, non_blocking=True)
    if turns is not None:
        batch = apply_vertical_symmetry(batch, random_vertical_symmetries(_batch_size_of(batch), turns, device=device))
    return batch


def snapshot_path(out: str | Path, step: int) -> Path:
    """Where a run in ``out`` keeps its model after ``step`` steps (``--snapshot-every``)."""
    return Path(out) / "snapshots" / f"step_{step:05d}.pt"


class _Run:
    """The steps of one training call: the model with its optimiser and schedules, the metrics
    log, and the checkpoint ``last.pt`` that keeps them."""

    def __init__(self, config: TrainConfig, out: Path, place: _Place, model: HRN, optimizer: torch.optim.Optimizer,
                 scheduler: torch.optim.lr_scheduler.LambdaLR, log: CSVLog | None,
                 val_set: EpisodeWindows | None, average: WeightAverage | None = None) -> None:
        self.config, self.out, self.place = config, out, place
        self.model, self.optimizer, self.scheduler, self.log = model, optimizer, scheduler, log
        self.average = average
        self.val_set, self.val_ids = val_set, _validation_ids(val_set)
        self.seq_schedule = SequenceLengthSchedule(config.seq_start, config.seq_end, config.steps, config.grow_until)
        self.summary: dict[str, Any] = {}  # the last logged row
        self.t0 = time.perf_counter()

    def take_steps(self, batches: DataLoader, start: int, end: int, noise: torch.Generator | None,
                   turns: torch.Generator | None, progress: bool) -> int:
        """Take steps ``start .. end-1`` (fewer once past ``time_limit``); returns the steps done.

        At exit, also on Ctrl-C or an error, :meth:`close` keeps the finished steps (the step that
        was running when an exception came is not counted as done).
        """
        config = self.config
        bar = tqdm(zip(range(start, end), batches), initial=start, total=config.steps,
                   disable=not progress or self.place.rank != 0, desc=f"train {config.preset}", dynamic_ncols=True)
        self.model.train()
        step_index = start
        try:
            for step_index, batch in bar:
                seq_len = self.seq_schedule(step_index)
                loss, parts = self.update(_on_device(batch, self.place.device, turns), seq_len, noise, step_index)
                row = self.log_row(step_index, seq_len, loss, parts)
                bar.set_postfix(loss=f"{row['loss']:.4g}", T=seq_len)
                self.summary = row
                if (step_index + 1) % config.checkpoint_every == 0:
                    self.save(step_index + 1)
                if config.snapshot_every and (step_index + 1) % config.snapshot_every == 0:
                    self.snapshot(step_index + 1)
                if self.past_time_limit():
                    step_index += 1  # stop here, as if interrupted
                    break
            else:
                step_index = end
        finally:
            self.close(step_index)
        return step_index

    def update(self, batch: HeteroData, seq_len: int, noise: torch.Generator | None,
               step_index: int) -> tuple[Tensor, dict[str, float]]:
        """One optimiser step on the loss of a batch (gradients averaged over the ranks, then
        clipped) and one step of the learning-rate schedule; the loss and its logged parts."""
        loss, parts = window_loss(self.model, batch, seq_len, self.config, noise_generator=noise)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"loss became {float(loss)} at step {step_index}")
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        _average_gradients(self.model)
        torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.config.grad_clip)
        self.optimizer.step()
        self.scheduler.step()
        if self.average is not None:
            self.average.update()
        return loss, parts

    def log_row(self, step_index: int, seq_len: int, loss: Tensor, parts: dict[str, float]) -> dict[str, Any]:
        """The row of a finished step (with the validation loss when one is due), appended to
        ``metrics.csv`` on rank 0."""
        config = self.config
        row = {"step": step_index, "seq_len": seq_len, "lr": self.scheduler.get_last_lr()[0],
               "loss": float(loss.detach()), **parts, "seconds": round(time.perf_counter() - self.t0, 3)}
        last_step = config.stop_at or config.steps  # the kept model is scored whatever eval_every is
        if self.val_ids and ((step_index + 1) % config.eval_every == 0 or step_index + 1 == last_step):
            with self.kept_weights():
                row["val_loss"] = validation_loss(self.model, self.val_set, self.val_ids, config.seq_end, config)
        if self.log is not None:
            self.log.append(row)
        return row

    def past_time_limit(self) -> bool:
        """Whether ``time_limit`` minutes have passed since the run started (never without one)."""
        return self.config.time_limit > 0 and time.perf_counter() - self.t0 > 60.0 * self.config.time_limit

    def save(self, step_done: int) -> None:
        """Write ``last.pt`` on rank 0: the model after ``step_done`` steps, with the optimiser,
        schedule and global random state that a resumed run continues."""
        if self.place.rank != 0:
            return
        payload = model_payload(self.model, self.config, step_done)
        payload.update(optimizer=self.optimizer.state_dict(), scheduler=self.scheduler.state_dict(), rng=rng_state())
        if self.average is not None:
            payload["weight_average"] = self.average.state_dict()
        save_checkpoint(self.out / "last.pt", payload)

    def kept_weights(self) -> AbstractContextManager:
        """A block in which the model holds the weights the run keeps: the average under
        ``ema_decay``, else the trained ones."""
        return nullcontext() if self.average is None else self.average.applied()

    def snapshot(self, step_done: int) -> None:
        """Keep the model after ``step_done`` steps in ``snapshots/step_<step>.pt`` on rank 0."""
        if self.place.rank == 0:
            with self.kept_weights():
                save_checkpoint(snapshot_path(self.out, step_done), model_payload(self.model, self.config, step_done))

    def close(self, step_done: int) -> None:
        """Keep the finished steps in ``last.pt``, draw ``loss.png`` from ``metrics.csv`` and leave
        the process group if this call joined it."""
        self.save(step_done)
        if self.place.rank == 0 and (self.out / "metrics.csv").exists():
            plot_curves(self.out / "metrics.csv", self.out / "loss.png", "step",
                        ["loss", "local", "global", "shape", "energy", "rest", "acceleration", "val_loss"],
                        title=f"{self.config.preset} on {Path(self.config.data).name}")
        if self.place.joined_group:
            dist.destroy_process_group()


def train(config: TrainConfig, model_config: NetworkConfig | None = None, resume: bool = False,
          progress: bool = True, stop_after: int | None = None,
          given_model_options: Collection[str] = ()) -> dict[str, Any]:
    """Run (or continue) one training job; returns the last logged row.

    ``model_config``: an :class:`~hrn_pyg.nn.hrn.HRNConfig` for the ``hrn`` and ``ours``
    presets, a :class:`~hrn_pyg.nn.gns.GNSConfig` for ``gns`` (None: the preset's default).
    ``given_model_options``: the names of ``model_config``'s fields that were set on purpose
    (the command line's ``--model-*`` options); with ``init_from`` they count as set even where
    they equal the default (:func:`_fine_tuned_start`).

    ``stop_after`` ends this call after that many more steps (with a checkpoint), as if it had
    been interrupted: ``resume=True`` continues it. ``model.pt`` (weights, config and
    normaliser, no optimiser) is written when the last step is done (step ``config.stop_at``
    when it is set).
    """
    model_config = preset_model_config(config.preset, model_config)
    place = _place_process(config)
    out = Path(config.out)
    train_set, val_set = _load_splits(config)
    ckpt = _checkpoint_to_resume(out / "last.pt", resume)
    model = _initial_model(config, model_config, train_set, ckpt, frozenset(given_model_options))
    config = resolved_noise(config, model)
    model.to(place.device)
    optimizer, scheduler = _optimiser(model, config)
    start = 0 if ckpt is None else _restore_training_state(ckpt, optimizer, scheduler)
    average = _weight_average(model, config, ckpt)
    log = _open_run_folder(out, config, model, place, resumed_at=None if ckpt is None else start)
    run = _Run(config, out, place, model, optimizer, scheduler, log, val_set, average)
    last = config.stop_at or config.steps
    end = last if stop_after is None else min(last, start + int(stop_after))
    noise, turns = _augmentation_streams(config, place.rank, start)
    done = run.take_steps(_step_batches(train_set, config, place, start, end), start, end, noise, turns, progress)
    if place.rank == 0 and done == last:
        with run.kept_weights():
            save_checkpoint(out / "model.pt", model_payload(model, config, last))
    return run.summary


def preset_model_config(preset: str, model_config: NetworkConfig | None) -> NetworkConfig:
    """The network config a preset trains: ``model_config``, or the preset's default (GNS for
    ``gns``, HRN otherwise); a config of the other network is an error."""
    wanted = GNSConfig if preset == "gns" else HRNConfig
    if model_config is None:
        return wanted()
    if not isinstance(model_config, wanted):
        raise ValueError(f"preset {preset!r} trains from a {wanted.__name__}, got a {type(model_config).__name__}")
    return model_config


@torch.no_grad()
def validation_loss(model: HRN, dataset: EpisodeWindows, ids: list[int], seq_len: int, config: TrainConfig) -> float:
    """Mean unrolled loss on fixed validation windows (no dropout, no input noise, no rest term:
    the deterministic model's loss, comparable between runs of different settings)."""
    was_training = model.training
    model.eval()
    device = next(model.parameters()).device
    batch = Batch.from_data_list([dataset[i] for i in ids]).to(device)
    scored = replace(config, train_dropout=0.0, input_noise=0.0, w_rest=0.0, rest_rollout=0)
    loss, _ = window_loss(model, batch, seq_len, scored)
    model.train(was_training)
    return float(loss) / seq_len


# --------------------------------------------------------------------------------------------
# command line


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
