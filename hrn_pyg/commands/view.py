"""``hrn-pyg view``'s arguments (the work: :mod:`hrn_pyg.export.view`)."""

from __future__ import annotations

import argparse

#: the page's name beside the result
VIEWER_NAME = "viewer.html"
#: where the page is served unless told otherwise: this machine only
DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765
#: playback rate of the page's play button (frames per second)
DEFAULT_FPS = 10.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("result", help="a folder written by `hrn-pyg sample` (or its samples.npz)")
    parser.add_argument("--out", default=None, help=f"the page (default: {VIEWER_NAME} beside the result)")
    parser.add_argument("--fps", type=float, default=DEFAULT_FPS, help="frames per second of the play button")
    parser.add_argument("--host", default=DEFAULT_HOST, help="address to serve on")
    parser.add_argument("--port", type=int, default=DEFAULT_PORT, help="port to serve on (0: any free port)")
    parser.add_argument("--no-serve", action="store_true", help="write the page and stop (open it from disk)")
