"""The training loop: one run from its first step to ``model.pt``, resumable, logged to ``metrics.csv``."""

from __future__ import annotations

import time
from collections.abc import Collection
from contextlib import AbstractContextManager, nullcontext
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor
from torch.utils.data import DataLoader
from torch_geometric.data import HeteroData

from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.nn.gns import GNSConfig
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.nn.networks import Network, NetworkConfig
from hrn_pyg.train.checkpointing import (
    checkpoint_to_resume,
    initial_model,
    model_payload,
    restore_training_state,
    snapshot_path,
    weight_average,
)
from hrn_pyg.train.config import TrainConfig
from hrn_pyg.train.distributed import Place, average_gradients, place_process
from hrn_pyg.train.loader import augmentation_streams, load_splits, on_device, step_batches, validation_ids
from hrn_pyg.train.loss import validation_loss, window_loss
from hrn_pyg.utils.checkpoint import rng_state, save_checkpoint
from hrn_pyg.utils.files import atomic_write_json
from hrn_pyg.utils.metrics import CSVLog
from hrn_pyg.utils.options import progress_bar
from hrn_pyg.utils.schedules import SequenceLengthSchedule, cosine_lr_factor
from hrn_pyg.utils.weight_average import WeightAverage
from hrn_pyg.viz import plot_curves


#: columns of ``metrics.csv`` (read by name; ``rest`` is empty unless ``w_rest`` > 0; ``acceleration``
#: is the ``gns`` preset's loss, the HRN terms are empty there)
LOG_FIELDS = ["step", "seq_len", "lr", "loss", "local", "global", "shape", "rest", "val_loss", "seconds", "acceleration"]


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


def _open_run_folder(out: Path, config: TrainConfig, model: HRN, place: Place,
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


class _Run:
    """The steps of one training call: the model with its optimiser and schedules, the metrics
    log, and the checkpoint ``last.pt`` that keeps them."""

    def __init__(self, config: TrainConfig, out: Path, place: Place, model: HRN, optimizer: torch.optim.Optimizer,
                 scheduler: torch.optim.lr_scheduler.LambdaLR, log: CSVLog | None,
                 val_set: EpisodeWindows | None, average: WeightAverage | None = None) -> None:
        self.config, self.out, self.place = config, out, place
        self.model, self.optimizer, self.scheduler, self.log = model, optimizer, scheduler, log
        self.average = average
        self.val_set, self.val_ids = val_set, validation_ids(val_set)
        self.seq_schedule = SequenceLengthSchedule(config.seq_start, config.seq_end, config.steps, config.grow_until)
        self.summary: dict[str, Any] = {}  # the last logged row
        self.t0 = time.perf_counter()

    def take_steps(self, batches: DataLoader, start: int, end: int, noise: torch.Generator | None,
                   turns: torch.Generator | None, progress: bool) -> int:
        """Take steps ``start .. end-1`` (fewer past ``time_limit``); returns the steps done. :meth:`close`
        keeps the finished steps at exit, also on Ctrl-C or an error."""
        config = self.config
        bar = progress_bar(config.steps, f"train {config.preset}", "step", initial=start,
                           enabled=progress and self.place.rank == 0)
        self.model.train()
        step_index = start
        try:
            for step_index, batch in zip(range(start, end), batches):
                seq_len = self.seq_schedule(step_index)
                loss, parts = self.update(on_device(batch, self.place.device, turns), seq_len, noise, step_index)
                row = self.log_row(step_index, seq_len, loss, parts)
                bar.update(1)
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
            bar.close()
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
        average_gradients(self.model)
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

    ``model_config``: :class:`~hrn_pyg.nn.hrn.HRNConfig` (``hrn``, ``ours``) or
    :class:`~hrn_pyg.nn.gns.GNSConfig` (``gns``); None: the preset's. ``given_model_options``: the
    fields set on purpose (``--model-*``), which win over ``init_from``'s
    (:func:`_fine_tuned_start`). ``stop_after`` ends the call after that many more steps, with a
    checkpoint (``resume=True`` continues). ``model.pt`` is written when the last step is done.
    """
    model_config = preset_model_config(config.preset, model_config)
    place = place_process(config)
    out = Path(config.out)
    train_set, val_set = load_splits(config)
    ckpt = checkpoint_to_resume(out / "last.pt", resume)
    model = initial_model(config, model_config, train_set, ckpt, frozenset(given_model_options))
    config = resolved_noise(config, model)
    model.to(place.device)
    optimizer, scheduler = _optimiser(model, config)
    start = 0 if ckpt is None else restore_training_state(ckpt, optimizer, scheduler)
    average = weight_average(model, config, ckpt)
    log = _open_run_folder(out, config, model, place, resumed_at=None if ckpt is None else start)
    run = _Run(config, out, place, model, optimizer, scheduler, log, val_set, average)
    last = config.stop_at or config.steps
    end = last if stop_after is None else min(last, start + int(stop_after))
    noise, turns = augmentation_streams(config, place.rank, start)
    done = run.take_steps(step_batches(train_set, config, place, start, end), start, end, noise, turns, progress)
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
