"""``hrn-pyg calibrate``'s arguments (the work: :mod:`hrn_pyg.sampling.calibrate`)."""

from __future__ import annotations

import argparse

from hrn_pyg.data.kinds import SCENES
from hrn_pyg.utils.options import add_no_progress, add_renamed

#: candidate dropout rates tried by default
DEFAULT_RATES = (0.01, 0.02, 0.05, 0.1, 0.2, 0.3)
#: validation seeds used when neither ``--episode-seeds`` nor ``--data`` is given
DEFAULT_SEEDS = (8, 18, 28)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default=None,
                        help="built-in scene the model simulates (picks the default checkpoint); may be left "
                             "out with --data, whose meta.json names the scene (a scene file's too): "
                             f"{', '.join(SCENES)}")
    parser.add_argument("--model", default=None,
                        help="checkpoint: a path or a shipped model's name (default: the shipped model of --scene)")
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--data", action="append", default=None,
                        help="episode folder from `hrn-pyg generate`: its validation episodes are the starts "
                             "(repeatable: a model of many scenes is calibrated on all of them)")
    source.add_argument("--episode-seeds", default=None, dest="seeds", metavar="SEEDS",
                        help="comma-separated validation seeds (seed %% 10 == 8) simulated fresh "
                             f"(default without --data: {','.join(map(str, DEFAULT_SEEDS))})")
    parser.add_argument("--starts", type=int, default=4,
                        help="with --data: at most this many validation episodes per folder")
    parser.add_argument("--rates", default=",".join(f"{r:g}" for r in DEFAULT_RATES),
                        help="comma-separated candidate dropout rates, each in [0, 1)")
    parser.add_argument("--module-sets", nargs="+", default=None, metavar="SET", dest="modules",
                        help="candidate module sets, each comma-separated, e.g. force force,collision "
                             "(default: all the model's dropout_modules, then each alone)")
    parser.add_argument("--k", type=int, default=16, help="sampled futures per candidate and start")
    parser.add_argument("--members", type=int, default=16, help="ground-truth ensemble members per start")
    parser.add_argument("--horizon", type=int, default=20, dest="steps", help="predicted steps; scored at the last")
    parser.add_argument("--position-std", type=float, default=None,
                        help="ensemble start perturbation in metres (default: PerturbationConfig's, "
                             "hrn_pyg.sampling.ensemble)")
    parser.add_argument("--sample-seed", type=int, default=0, help="seeds the dropout masks")
    parser.add_argument("--ensemble-cache", default=None, metavar="DIR",
                        help="keep each start's pybullet ensemble here and read it back when the same scene, "
                             "seed, members, horizon and perturbation are asked for again (a later calibration "
                             "of another model skips the simulation)")
    target = parser.add_mutually_exclusive_group()
    target.add_argument("--out", default=None, help="calibrated checkpoint to write (default: <model>.calibrated.pt)")
    target.add_argument("--in-place", action="store_true", help="write the choice into --model itself")
    parser.add_argument("--device", default=None,
                        help="torch device, e.g. cpu, cuda (default: cuda if available, else cpu)")
    parser.add_argument("--no-physics-check", action="store_true",
                        help="rank candidates by spread alone; by default a rate with a future that fails the "
                             "physics report (a blow-up, energy gained, bodies deep in each other) is rejected")
    add_no_progress(parser)
    add_renamed(parser, "--steps", "--horizon")
    add_renamed(parser, "--seeds", "--episode-seeds")
    add_renamed(parser, "--modules", "--module-sets")
