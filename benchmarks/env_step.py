"""What sleeping buys the RL environment: time of one batched environment step, on and off.

:class:`hrn_pyg.rl.hrn_dynamics.HRNDynamics` with the shipped task model (``tower``: the
ball is pushed, the three cubes start at rest in pybullet's start scenes and sleep until the
ball reaches them; ``cube_push``: both cubes are pushed at every step, so nothing sleeps and the
bookkeeping is pure cost). One episode's worth of steps (the task's ``max_steps``) from
``--envs`` reset states, ``k`` samples each at the task's dropout rate and at rate 0, random
forces on the controlled objects (uniform in the task's force box, seeded), the same forces and
masks for both settings; sleeping on and off interleaved, median over ``--repeats``, one torch
thread. Reported: ms per environment step, the ratio, and the largest difference between the two
settings' next states (sleeping holds resting objects where the network would let them creep).

Run: ``python -m benchmarks.env_step [--tasks tower,cube_push] [--envs 16] [--repeats 5]``;
prints a table and writes ``benchmarks/results/env_step.json``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import torch

from hrn_pyg.rl.hrn_dynamics import HRNDynamics
from hrn_pyg.rl.tasks import get_task
from hrn_pyg.sim.sleeping import DEFAULT_SLEEP
from hrn_pyg.utils.files import atomic_write_json


def episode(dynamics: HRNDynamics, states: torch.Tensor, forces: torch.Tensor, k: int, rate: float) -> torch.Tensor:
    """Roll ``forces`` ``[T, B, O, 3]`` through the dynamics (first sample kept); final states."""
    gen = torch.Generator().manual_seed(0)
    for f in forces:  # environment steps
        states = dynamics.sample_next(states, f, k, rate, gen)[:, 0]
    return states


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default="tower,cube_push")
    parser.add_argument("--envs", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default="benchmarks/results/env_step.json")
    args = parser.parse_args(argv)
    if args.repeats < 3:
        raise SystemExit("--repeats must be >= 3")
    torch.set_num_threads(args.threads)
    rows = []
    for name in (t for t in args.tasks.split(",") if t):
        task = get_task(name)
        path = f"hrn_pyg/checkpoints/{name}.pt"
        on = HRNDynamics.from_checkpoint(path, task, sleep=DEFAULT_SLEEP)
        off = HRNDynamics(on.model, task, sleep=None)
        states = on.reset_states(args.envs, torch.Generator().manual_seed(1))
        gen = torch.Generator().manual_seed(2)
        forces = torch.zeros(task.max_steps, args.envs, task.num_objects, 3)
        for o in task.controlled_objects:
            for axis in task.force_axes:
                forces[..., o, axis] = (torch.rand(task.max_steps, args.envs, generator=gen) * 2 - 1) * task.max_force
        for rate in (task.dropout_rate, 0.0):
            times: dict[str, list[float]] = {"all_awake": [], "sleeping": []}
            with torch.no_grad():
                final = {"all_awake": episode(off, states, forces, task.num_samples, rate),  # warm-up
                         "sleeping": episode(on, states, forces, task.num_samples, rate)}
                for _ in range(args.repeats):  # interleaved
                    for key, dyn in (("all_awake", off), ("sleeping", on)):
                        start = time.perf_counter()
                        episode(dyn, states, forces, task.num_samples, rate)
                        times[key].append((time.perf_counter() - start) / task.max_steps)
            ms = {key: 1e3 * statistics.median(v) for key, v in times.items()}
            row = {"task": name, "rate": rate, "k": task.num_samples, "envs": args.envs, "steps": task.max_steps,
                   "ms_per_env_step": ms, "ms_runs": {k: [1e3 * t for t in v] for k, v in times.items()},
                   "all_awake_over_sleeping": ms["all_awake"] / ms["sleeping"],
                   "max_state_difference_m": float((final["all_awake"] - final["sleeping"])[:, :-1].abs().max())}
            rows.append(row)
            print(f"{name} rate {rate}: all awake {ms['all_awake']:.2f} ms, sleeping {ms['sleeping']:.2f} ms "
                  f"(x{row['all_awake_over_sleeping']:.2f}), largest state difference "
                  f"{1e3 * row['max_state_difference_m']:.2f} mm after {task.max_steps} steps", flush=True)
    result = {"what": "HRNDynamics.sample_next per environment step, sleeping on vs off",
              "statistic": f"median of {args.repeats} interleaved episodes / steps",
              "machine": {"cpu": platform.machine(), "cpus": os.cpu_count(), "torch": torch.__version__,
                          "torch_threads": args.threads, "load_average_1m": os.getloadavg()[0]},
              "rows": rows}
    atomic_write_json(args.out, result)
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
