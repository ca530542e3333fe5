"""``hrn-pyg check-data``'s arguments (the work: :mod:`hrn_pyg.data.check`)."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("folder", help="a folder of episode_<seed>.npz files")
