"""``hrn-pyg demo``'s arguments (the work: :mod:`hrn_pyg.demo`)."""

from __future__ import annotations

import argparse

from hrn_pyg.utils.options import add_no_progress


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="runs/demo", help="output folder")
    parser.add_argument("--k", type=int, default=16, help="sampled futures per scene")
    parser.add_argument("--device", default=None,
                        help="torch device, e.g. cpu, cuda, cuda:1 (default: cuda if available, else cpu)")
    add_no_progress(parser)
