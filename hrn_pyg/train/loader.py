"""Which windows each step trains on: seeded draws per step and rank, folder weights, batches, validation ids."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch
from torch import Tensor
from torch.utils.data import DataLoader
from torch_geometric.data import Batch, HeteroData

from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.data.symmetry import apply_vertical_symmetry, random_vertical_symmetries
from hrn_pyg.train.config import TrainConfig
from hrn_pyg.train.distributed import Place
from hrn_pyg.train.loss import batch_size_of


#: validation windows scored at every evaluation
VAL_WINDOWS = 8


def window_draw_weights(train_set: EpisodeWindows, folders: Sequence[str],
                        folder_weights: Sequence[float]) -> Tensor | None:
    """The cumulative draw weight of ``train_set``'s windows, each window weighted by its
    folder's entry of ``folder_weights`` (``(W,)`` float64, for :func:`draw_windows`); None when
    every weight is 1 (uniform draws)."""
    if all(w == 1.0 for w in folder_weights):
        return None
    by_folder = {Path(f).resolve(): w for f, w in zip(folders, folder_weights)}
    per_episode = torch.tensor([by_folder[Path(p).parent.resolve()] for p in train_set.paths], dtype=torch.float64)
    return torch.cumsum(per_episode[torch.as_tensor(train_set.window_episodes)], 0)


def draw_windows(n: int, batch_size: int, seed: int, step: int, rank: int,
                  cumulative: Tensor | None = None) -> list[int]:
    """The window indices of one step, a pure function of (seed, step, rank) so a resumed run draws
    the same: uniform, or with ``cumulative`` weights (:func:`window_draw_weights`) proportional."""
    g = torch.Generator().manual_seed(seed * 1_000_003 + step * 7919 + rank * 104_729 + 1)
    if cumulative is None:
        return torch.randint(n, (batch_size,), generator=g).tolist()
    u = torch.rand(batch_size, generator=g, dtype=torch.float64) * cumulative[-1]
    return torch.searchsorted(cumulative, u, right=True).clamp_(max=n - 1).tolist()


class StepWindows:
    """Batch sampler of a run: the window indices of steps ``start .. end-1`` (see
    :func:`draw_windows`), so a ``DataLoader`` with workers yields what the loop would draw."""

    def __init__(self, n: int, batch_size: int, seed: int, rank: int, start: int, end: int,
                 cumulative: Tensor | None = None) -> None:
        self.n, self.batch_size, self.seed, self.rank, self.start, self.end = n, batch_size, seed, rank, start, end
        self.cumulative = cumulative

    def __iter__(self):
        for step in range(self.start, self.end):
            yield draw_windows(self.n, self.batch_size, self.seed, step, self.rank, self.cumulative)

    def __len__(self) -> int:
        return max(self.end - self.start, 0)


def _collate(windows: list[HeteroData]) -> HeteroData:
    return Batch.from_data_list(windows)


def load_splits(config: TrainConfig) -> tuple[EpisodeWindows, EpisodeWindows | None]:
    """The training and validation windows of ``data`` and ``extra_data`` (None: no validation
    episodes)."""
    # every episode stays decoded in memory: windows are drawn at random across the whole split
    train_set = EpisodeWindows(config.data_folders, "train", horizon=config.seq_end, cache_episodes=1 << 20)
    try:
        val_set = EpisodeWindows(config.data_folders, "val", horizon=config.seq_end, cache_episodes=1 << 20)
    except ValueError:
        val_set = None  # a folder without validation episodes trains without a validation score
    return train_set, val_set


def step_batches(train_set: EpisodeWindows, config: TrainConfig, place: Place, start: int, end: int) -> DataLoader:
    """The batches of steps ``start .. end-1`` (windows drawn by :class:`StepWindows`), collated by
    ``config.workers`` background processes (0: in this one)."""
    cumulative = window_draw_weights(train_set, config.data_folders, config.folder_weights)
    return DataLoader(train_set, batch_sampler=StepWindows(len(train_set), config.batch_size, config.seed,
                                                           place.rank, start, end, cumulative),
                      collate_fn=_collate, num_workers=config.workers, pin_memory=place.device.type == "cuda",
                      # its own generator: the loader's seed draw must not shift the global
                      # random stream that dropout masks use (resume would then diverge)
                      generator=torch.Generator().manual_seed(config.seed))


def augmentation_streams(config: TrainConfig, rank: int,
                          start: int) -> tuple[torch.Generator | None, torch.Generator | None]:
    """This rank's generators of the input noise (and rest-rollout lengths) and of the symmetry draws
    (None where off): streams of their own, seeded with the first step."""
    noise = (torch.Generator().manual_seed(config.seed * 7 + rank + 3 + start)
             if config.input_noise > 0 or config.rest_rollout > 0 else None)
    turns = torch.Generator().manual_seed(config.seed * 11 + rank + 5 + start) if config.augment_symmetry else None
    return noise, turns


def validation_ids(val_set: EpisodeWindows | None) -> list[int]:
    """The :data:`VAL_WINDOWS` validation windows scored at every evaluation, spread over the
    split (none without validation episodes)."""
    if not val_set:
        return []
    return list(range(0, len(val_set), max(1, len(val_set) // VAL_WINDOWS)))[:VAL_WINDOWS]


def on_device(batch: HeteroData, device: torch.device, turns: torch.Generator | None) -> HeteroData:
    """A batch moved to ``device``, every window turned (and maybe mirrored) by a draw from
    ``turns`` when given."""
    batch = batch.to(device, non_blocking=True)
    if turns is not None:
        batch = apply_vertical_symmetry(batch, random_vertical_symmetries(batch_size_of(batch), turns, device=device))
    return batch
