"""``hrn-pyg generate``'s arguments (the work: :mod:`hrn_pyg.data.generate`)."""

from __future__ import annotations

import argparse

from hrn_pyg.data.kinds import SCENES
from hrn_pyg.utils.options import add_no_progress, add_renamed


def add_arguments(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--scene", help=f"a built-in scene: {', '.join(SCENES)}")
    source.add_argument("--scene-file", help="a scene file (TOML: objects from meshes, materials, pushes)")
    parser.add_argument("--episodes", type=int, required=True, help="episodes in the dataset")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--workers", type=int, default=1, help="worker processes")
    parser.add_argument("--shard", default="0/1", help="i/N: this machine's share of the episodes")
    parser.add_argument("--episode-steps", type=int, default=None, dest="steps",
                        help="model steps per episode (default: the scene's)")
    parser.add_argument("--first-seed", type=int, default=0, dest="seed_offset", metavar="SEED",
                        help="seed of episode 0 (episode i: first seed + i)")
    parser.add_argument("--substeps", type=int, default=None, help="physics steps per model step (default: the scene's)")
    parser.add_argument("--physics-hz", type=float, default=None, help="physics rate in Hz (default: the scene's)")
    parser.add_argument("--pitch", type=float, default=None, help="voxel size of the leaves in m (default: the scene's)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", dest="overrides",
                        help="any other setting of the scene (its file's top level or [settings]), VALUE as "
                             "JSON, e.g. offset_range=[-0.003,0.003] (repeatable)")
    parser.add_argument("--engine", default=None,
                        help="the engine that simulates the scene: pybullet or mujoco (default: the scene file's "
                             "engine, else pybullet)")
    add_no_progress(parser)
    add_renamed(parser, "--steps", "--episode-steps")
    add_renamed(parser, "--seed-offset", "--first-seed")
