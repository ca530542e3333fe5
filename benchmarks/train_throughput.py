"""How fast does the model train? Training windows per second against device and batch size.

One training step is what ``hrn-pyg train`` does: assemble a batch of windows
(``Batch.from_data_list``), move it to the device, unroll ``T`` steps with the loss of the chosen
preset, backward, clip, Adam step. Two rates are reported per setting: *step* (model work only,
the batch already on the device) and *with batching* (the batch assembled on the CPU in the
training process and moved each step, as ``--workers 0`` trains).

The model is randomly initialised with its normaliser fitted on the windows: a step's cost does
not depend on the weights. Windows come from an episode folder (``hrn-pyg generate`` output), so
the script needs no pybullet and runs as it is on a GPU machine.

Run: ``python -m benchmarks.train_throughput --data data/soft_bounce [--devices cpu,cuda]
[--batch-sizes 4,32,128] [--seq-len 1,6] [--steps 10] [--threads 1]
[--out benchmarks/results/train_throughput.json]``. Median over the timed steps, one process;
devices that are not present are skipped and say so. Prints a markdown table, writes JSON
atomically.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
from dataclasses import replace

import torch
from torch_geometric.data import Batch

from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.train import TrainConfig, window_loss
from hrn_pyg.utils.files import atomic_write_json

#: windows the normaliser is fitted on
FIT_WINDOWS = 64


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x.strip()]


def time_setting(dataset: EpisodeWindows, model_config: HRNConfig, device: torch.device, batch_size: int,
                 seq_len: int, steps: int, warmup: int, preset: str) -> dict[str, float]:
    """Median seconds per training step, without and with batch assembly, on ``device``."""
    torch.manual_seed(0)
    model = HRN(model_config)
    picks = torch.randperm(len(dataset), generator=torch.Generator().manual_seed(0))
    fit_normalizer((dataset[int(i)] for i in picks[:FIT_WINDOWS]), model.normalizer)
    model.to(device).train()
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4)
    config = replace(TrainConfig.for_preset(preset), seq_end=max(seq_len, 1), seq_start=1)
    gen = torch.Generator().manual_seed(1)

    def draw() -> Batch:
        ids = torch.randint(len(dataset), (batch_size,), generator=gen).tolist()
        return Batch.from_data_list([dataset[i] for i in ids])

    def train_step(batch: Batch) -> None:
        loss, _ = window_loss(model, batch, seq_len, config)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimizer.step()

    fixed = draw().to(device)
    model_only, with_batching = [], []
    for i in range(warmup + steps):
        _sync(device)
        t0 = time.perf_counter()
        train_step(fixed)
        _sync(device)
        t1 = time.perf_counter()
        train_step(draw().to(device))
        _sync(device)
        t2 = time.perf_counter()
        if i >= warmup:
            model_only.append(t1 - t0)
            with_batching.append(t2 - t1)
    step_s, full_s = statistics.median(model_only), statistics.median(with_batching)
    return {"step_s": step_s, "full_s": full_s,
            "windows_per_s": batch_size / step_s, "windows_per_s_with_batching": batch_size / full_s}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="data/soft_bounce", help="episode folder")
    parser.add_argument("--devices", default="cpu,cuda")
    parser.add_argument("--batch-sizes", default="4,32,128")
    parser.add_argument("--seq-len", default="1,6", help="unroll lengths T to time")
    parser.add_argument("--steps", type=int, default=10, help="timed steps per setting")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--cpu-max-batch", type=int, default=32,
                        help="largest batch timed on the CPU (bigger ones take minutes)")
    parser.add_argument("--preset", default="ours", choices=("hrn", "ours"))
    parser.add_argument("--out", default="benchmarks/results/train_throughput.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    dataset = EpisodeWindows(args.data, "train", horizon=max(_ints(args.seq_len)), cache_episodes=1 << 20)
    model_config = HRNConfig()
    rows, skipped = [], []
    for name in [d for d in args.devices.split(",") if d]:
        if name.startswith("cuda") and not torch.cuda.is_available():
            skipped.append(f"{name}: torch.cuda.is_available() is False")
            continue
        device = torch.device(name)
        for batch_size in _ints(args.batch_sizes):
            if device.type == "cpu" and batch_size > args.cpu_max_batch:
                skipped.append(f"{name} batch {batch_size}: above --cpu-max-batch {args.cpu_max_batch}")
                continue
            for seq_len in _ints(args.seq_len):
                r = time_setting(dataset, model_config, device, batch_size, seq_len, args.steps, args.warmup,
                                 args.preset)
                rows.append({"device": name, "batch_size": batch_size, "seq_len": seq_len, **r})
                print(f"{name:>6} batch {batch_size:>4} T={seq_len}: {r['windows_per_s']:8.1f} windows/s "
                      f"({r['windows_per_s_with_batching']:.1f} with batching)", flush=True)

    device_name = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    print("\n| device | batch | T | step (ms) | windows/s | windows/s with batching |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['device']} | {r['batch_size']} | {r['seq_len']} | {1e3 * r['step_s']:.1f} | "
              f"{r['windows_per_s']:.1f} | {r['windows_per_s_with_batching']:.1f} |")
    for s in skipped:
        print(f"skipped: {s}")
    atomic_write_json(args.out, {
        "data": args.data, "preset": args.preset, "threads": args.threads, "steps": args.steps,
        "torch": torch.__version__, "cuda_device": device_name, "cpu": platform.processor() or platform.machine(),
        "rows": rows, "skipped": skipped,
    })
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
