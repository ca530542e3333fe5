"""``hrn-pyg evaluate``'s arguments (the work: :mod:`hrn_pyg.evaluate`)."""

from __future__ import annotations

import argparse

from hrn_pyg.utils.options import add_no_progress, add_strict

#: Long horizons of the second table (read at the episode's end where an episode is shorter).
DEFAULT_LONG_HORIZONS = (50, 100)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, help="episode folder; its test split is used")
    parser.add_argument("--model", action="append", required=True, metavar="NAME=PATH",
                        help="a checkpoint to score, e.g. --model hrn=runs/hrn/model.pt, or a shipped "
                             "model by name: --model shapes or --model ours=shapes (repeatable)")
    add_strict(parser, "data")
    parser.add_argument("--rigid-fit", action="append", default=[], metavar="NAME",
                        help="score model NAME with the rigid fit applied to its rigid objects after the "
                             "network, e.g. a GNS trained without it: --model gns_rigid=runs/gns/model.pt "
                             "--rigid-fit gns_rigid (repeatable)")
    parser.add_argument("--out", default=None,
                        help="folder for table.md, results.json and the figure (default: runs/evaluate/<data's name>)")
    parser.add_argument("--horizons", default="5,15", help="comma-separated steps ahead")
    parser.add_argument("--long-horizons", default=",".join(map(str, DEFAULT_LONG_HORIZONS)),
                        help="comma-separated steps ahead of the long-rollout table, one rollout per "
                             "episode from its start; read at the episode's end when shorter "
                             "('' for the rest metrics only)")
    parser.add_argument("--device", default=None,
                        help="torch device, e.g. cpu, cuda, cuda:1 (default: cuda if available, else cpu)")
    parser.add_argument("--stride", type=int, default=10, help="steps between window starts in an episode")
    parser.add_argument("--limit", type=int, default=None, help="score at most this many trajectories")
    parser.add_argument("--split", default="test", choices=("test", "val", "all"),
                        help="held-out split to score (val for model selection, test for reporting; all: "
                             "every episode, for a dataset not split by seed such as a scene file's)")
    parser.add_argument("--no-figure", action="store_true", help="draw no rollout figure")
    add_no_progress(parser)
