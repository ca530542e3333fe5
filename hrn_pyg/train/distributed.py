"""Data-parallel training under ``torchrun``: the process group, this process's place, gradient averaging."""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist

from hrn_pyg.train.config import TrainConfig
from hrn_pyg.utils.device import resolve_device


def rank_and_world() -> tuple[int, int]:
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def maybe_init_distributed(device: torch.device) -> bool:
    if int(os.environ.get("WORLD_SIZE", "1")) > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        return True
    return False


def average_gradients(model: torch.nn.Module) -> None:
    """Average gradients over ranks (a module not run on some rank contributes zeros)."""
    _, world = rank_and_world()
    if world == 1:
        return
    for p in model.parameters():
        if p.grad is None:
            p.grad = torch.zeros_like(p)
        dist.all_reduce(p.grad)
        p.grad /= world


@dataclass(frozen=True)
class Place:
    """Where this process trains: its device, its rank among ``world`` processes, and whether this
    call joined the process group (and so leaves it at exit)."""

    device: torch.device
    rank: int
    world: int
    joined_group: bool


def place_process(config: TrainConfig) -> Place:
    """Pick the device, join the process group under ``torchrun`` (one GPU per rank on CUDA) and
    set the number of threads."""
    device = resolve_device(config.device)
    joined_group = maybe_init_distributed(device)
    rank, world = rank_and_world()
    if device.type == "cuda" and world > 1:
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", rank)) % torch.cuda.device_count())
        torch.cuda.set_device(device)
    if config.threads > 0:
        torch.set_num_threads(config.threads)
    return Place(device, rank, world, joined_group)
