"""``hrn-pyg models``'s arguments (the work: :mod:`hrn_pyg.checkpoints.cli`)."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", nargs="?", default=None,
                        help="one model's details: every dataset, its domain, file and test errors "
                             "(default: a table of all)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table (default: a table)")
