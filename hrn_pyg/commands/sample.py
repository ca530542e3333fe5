"""``hrn-pyg sample``'s arguments (the work: :mod:`hrn_pyg.sampling.cli`)."""

from __future__ import annotations

import argparse

from hrn_pyg.data.kinds import HISTORY, SCENES
from hrn_pyg.utils.options import add_no_progress, add_renamed, add_strict

#: sampling rate of a model that names none (config ``dropout_rate`` 0: never calibrated)
UNCALIBRATED_RATE = 0.3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    scene = parser.add_mutually_exclusive_group(required=True)
    scene.add_argument("--scene",
                       help=f"a built-in scene (picks the default checkpoint): {', '.join(SCENES)}")
    scene.add_argument("--scene-file", default=None,
                       help="a scene file (TOML, docs/own_objects.md); needs --model")
    parser.add_argument("--k", type=int, default=16, help="sampled futures")
    parser.add_argument("--rate", type=float, default=None,
                        help="dropout rate at test time (default: the model's calibrated rate, "
                             f"or {UNCALIBRATED_RATE} for an uncalibrated model)")
    parser.add_argument("--modules", default=None,
                        help="comma-separated modules to mask (default: the model's dropout_modules)")
    parser.add_argument("--model", default=None,
                        help="checkpoint: a path or a shipped model's name, e.g. shapes (`hrn-pyg models`; "
                             "default: the shipped model of --scene)")
    add_strict(parser)
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--data", default=None, help="episode folder: use a window of its --split")
    source.add_argument("--episode-seed", type=int, default=9, dest="seed",
                        help="without --data: simulate a fresh episode with this seed")
    parser.add_argument("--window", type=int, default=0, help="window index within --data's --split")
    parser.add_argument("--split", default="test", choices=("test", "val", "all"),
                        help="the split of --data the window is taken from (all: every episode)")
    parser.add_argument("--start", type=int, default=HISTORY, help="start step of a fresh episode")
    parser.add_argument("--horizon", type=int, default=None, dest="steps",
                        help="predicted steps (default: 30; with --data: 1)")
    parser.add_argument("--sample-seed", type=int, default=0, help="seeds the dropout masks")
    parser.add_argument("--out", default=None, help="output folder (default: runs/sample/<scene>)")
    parser.add_argument("--device", default=None,
                        help="torch device, e.g. cpu, cuda, cuda:1 (default: cuda if available, else cpu)")
    parser.add_argument("--no-sleep", action="store_true",
                        help="run every object at every step (default: objects at rest sleep, hrn_pyg.sim.sleeping)")
    parser.add_argument("--fixed-shape", action="store_true",
                        help="fixed-shape steps (hrn_pyg.sim.fixed_shape): no host read inside the network's part "
                             "of a step (rules that read the contacts run after it), the same futures as "
                             "--no-sleep, which it implies")
    parser.add_argument("--cuda-graph", action="store_true",
                        help="with --fixed-shape on CUDA: record each kind of step as a CUDA graph")
    parser.add_argument("--compile", action="store_true",
                        help="run the network through torch.compile (Module.compile): a compile of "
                             "tens of seconds first, then fused steps while the graph's shapes hold; with "
                             "--fixed-shape each kind of step is compiled (FixedShapeConfig.compile; a model's "
                             "rules that read the contacts run after the compiled part)")
    pictures = parser.add_argument_group("pictures and exports")
    pictures.add_argument("--frames", default=None,
                          help="steps drawn as the PNG's columns, comma-separated, e.g. 0,10,30 (default: 0, "
                               "a quarter, half, three quarters and all of the horizon)")
    pictures.add_argument("--size", default=None,
                          help="WIDTHxHEIGHT in pixels of the PNG and of each animation frame, e.g. 1600x400 "
                               "(default: 220 x 240 a column; 256 x 208 a frame)")
    pictures.add_argument("--fps", type=float, default=10.0, help="frames per second of the GIF and the MP4")
    pictures.add_argument("--camera", default="18,-72",
                          help="the pictures' camera: elevation,azimuth in degrees")
    pictures.add_argument("--mp4", action="store_true",
                          help="also write samples.mp4 (needs imageio-ffmpeg: pip install 'hrn_pyg[viewer]')")
    pictures.add_argument("--export", default=None,
                          help="also write the futures as the scene's meshes: any of glb, ply, obj, vtk, "
                               "comma-separated (hrn_pyg.export; --rate 0 --k 1 exports a deterministic rollout)")
    add_no_progress(parser)
    add_renamed(parser, "--steps", "--horizon")
    add_renamed(parser, "--seed", "--episode-seed")
