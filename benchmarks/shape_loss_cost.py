"""What the rigid bodies' shape pairs cost a training step, and what skipping them saves.

Under the rigid fit (``HRNConfig.rigid_fit``) a rigid body's leaves move by one rigid motion of
their current positions, so the fully connected shape loss of its pairs is a constant of the
step's input: :func:`hrn_pyg.losses.full_shape_loss` counts those pairs but does not compute
them (``fixed``), and the gradient is the same. This script times one training step
(:func:`hrn_pyg.train.window_loss` and its backward pass, a batch of ``--batch-size`` windows
drawn from the ``--data`` folders, unrolled ``--seq-len`` steps) both ways, alternating the two
on the same batches, and checks that the gradients agree.

Run: ``python -m benchmarks.shape_loss_cost --model shapes --data data/shapes_drop
--data data/shapes_soft [--batch-size 8] [--seq-len 16] [--steps 6]
[--out benchmarks/results/shape_loss_cost.json]``. One torch thread; medians over the steps.
Prints a markdown table and writes JSON atomically.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import torch
from torch_geometric.data import Batch

import hrn_pyg.train.loss as train_module
from hrn_pyg.checkpoints import load_model
from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.losses import full_shape_loss
from hrn_pyg.train import TrainConfig, window_loss
from hrn_pyg.utils.files import atomic_write_json


def every_pair(*args, fixed=None):
    """The full shape loss with the rigid bodies' pairs computed (``fixed`` ignored)."""
    return full_shape_loss(*args)


def timed_step(model, batch, seq_len: int, config: TrainConfig, shape_loss) -> tuple[float, list[torch.Tensor]]:
    """Seconds of one loss and backward pass with ``shape_loss`` as the full shape loss, and the gradients."""
    train_module.full_shape_loss = shape_loss
    try:
        model.zero_grad()
        start = time.perf_counter()
        total, _ = window_loss(model, batch, seq_len, config, noise_generator=torch.Generator().manual_seed(0))
        total.backward()
        seconds = time.perf_counter() - start
    finally:
        train_module.full_shape_loss = full_shape_loss
    return seconds, [p.grad.clone() for p in model.parameters() if p.grad is not None]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="shapes", help="a shipped model's name or a checkpoint (its config is timed)")
    parser.add_argument("--data", action="append", required=True, help="an episode folder (repeatable)")
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--seq-len", type=int, default=16)
    parser.add_argument("--steps", type=int, default=6, help="timed batches")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="benchmarks/results/shape_loss_cost.json")
    args = parser.parse_args()
    if args.steps < 1 or args.batch_size < 1 or args.seq_len < 1:
        raise SystemExit("--steps, --batch-size and --seq-len must be >= 1")
    torch.set_num_threads(1)
    model = load_model(args.model).train()
    if not getattr(model.config, "rigid_fit", False):
        raise SystemExit(f"{args.model} has no rigid fit: its rigid pairs are computed either way")
    sets = [EpisodeWindows(folder, "train", horizon=args.seq_len + 1) for folder in args.data]
    config = TrainConfig(data="unused", out="unused", input_noise=3e-4)
    gen = torch.Generator().manual_seed(args.seed)
    rows = []
    for i in range(args.steps + 1):  # the first is a warm-up
        windows = []
        for _ in range(args.batch_size):
            dataset = sets[int(torch.randint(len(sets), (1,), generator=gen))]
            windows.append(dataset[int(torch.randint(len(dataset), (1,), generator=gen))])
        batch = Batch.from_data_list(windows)
        skip_s, skip_grads = timed_step(model, batch, args.seq_len, config, full_shape_loss)
        every_s, every_grads = timed_step(model, batch, args.seq_len, config, every_pair)
        worst = max(float((a - b).abs().max() / (b.abs().max() + 1e-12)) for a, b in zip(skip_grads, every_grads))
        if i > 0:
            rows.append({"skip_s": skip_s, "every_pair_s": every_s, "max_relative_gradient_difference": worst})
        print(f"batch {i}: skipping {skip_s:.2f} s, every pair {every_s:.2f} s, gradients apart {worst:.1e}",
              flush=True)
    skip = statistics.median(r["skip_s"] for r in rows)
    every = statistics.median(r["every_pair_s"] for r in rows)
    print()
    print("| step (loss + backward) | median s | ratio |")
    print("|---|---|---|")
    print(f"| rigid pairs computed | {every:.2f} | 1.00 |")
    print(f"| rigid pairs skipped (the package) | {skip:.2f} | {skip / every:.2f} |")
    print(f"\nlargest gradient difference, relative to the parameter's largest gradient: "
          f"{max(r['max_relative_gradient_difference'] for r in rows):.1e}")
    atomic_write_json(args.out, {
        "model": args.model, "data": args.data, "batch_size": args.batch_size, "seq_len": args.seq_len,
        "steps": rows, "median_skip_s": skip, "median_every_pair_s": every, "ratio": skip / every,
        "threads": 1, "torch": torch.__version__, "machine": platform.machine(), "processor": platform.processor(),
    })


if __name__ == "__main__":
    main()
