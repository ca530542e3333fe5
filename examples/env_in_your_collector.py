"""The learned-physics environment inside your own TorchRL collector loop.

By default it uses the point-mass development dynamics (instant, no checkpoint). With
``--model hrn_pyg/checkpoints/cube_push.pt`` the environment steps the learned, stochastic HRN:
each step samples 5 futures with Monte Carlo dropout and relaxes the reward over them.

    python examples/env_in_your_collector.py [--fast] [--model PATH]
"""

from __future__ import annotations

import argparse

import torch
from torchrl.collectors import Collector
from torchrl.envs.utils import check_env_specs

from hrn_pyg.rl import HRNEnv


def main(fast: bool = False, model: str | None = None) -> None:
    torch.manual_seed(0)
    dynamics = None
    if model:
        from hrn_pyg.rl.hrn_dynamics import HRNDynamics

        dynamics = HRNDynamics.from_checkpoint(model, "cube_push")
    env = HRNEnv("cube_push", dynamics, batch_size=4, seed=0, dropout_rate=0.1)
    check_env_specs(env)
    frames = 16 if fast else 200
    collector = Collector(env, policy=None, frames_per_batch=frames // 2, total_frames=frames)
    for i, batch in enumerate(collector):  # a random policy: replace it with yours
        rewards = batch["next", "reward"]
        episodes = int(batch["next", "done"].sum())
        print(f"batch {i}: {batch.numel()} frames, reward sum {float(rewards.sum()):.1f}, episodes ended {episodes}")
    collector.shutdown()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fast", action="store_true", help="the short run CI uses")
    parser.add_argument("--model", default=None, help="a trained cube_push HRN checkpoint")
    args = parser.parse_args()
    main(args.fast, args.model)
