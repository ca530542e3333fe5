"""``hrn-pyg view RESULT``: ground truth and every sampled future in 3D, in the browser.

``RESULT`` is a folder of ``hrn-pyg sample`` (or its ``samples.npz``). The viewer page
(:mod:`hrn_pyg.export.viewer`, one self-contained HTML file) is written beside it as
``viewer.html`` (or ``--out``) and the folder served on ``--host`` (127.0.0.1) and ``--port``
until interrupted; ``--no-serve`` writes the page only. The scene's meshes are shown where the
result has them, else the leaves.
"""

from __future__ import annotations

import argparse
import functools
import http.server
import os
from pathlib import Path

import numpy as np

from hrn_pyg.commands.view import DEFAULT_HOST, DEFAULT_PORT, VIEWER_NAME, add_arguments  # noqa: F401  here too
from hrn_pyg.export.files import sample_trajectories
from hrn_pyg.export.scene_meshes import SceneMeshes
from hrn_pyg.export.viewer import write_viewer


def result_file(result: str | os.PathLike) -> Path:
    """``samples.npz`` of a result folder, or the file itself; FileNotFoundError naming it otherwise."""
    path = Path(result)
    if path.is_dir():
        path = path / "samples.npz"
    if not path.is_file():
        raise FileNotFoundError(f"no result at {result} (a folder of `hrn-pyg sample` or its samples.npz)")
    return path


def load_result(result: str | os.PathLike) -> tuple[dict[str, np.ndarray], SceneMeshes | None, float | None]:
    """The named trajectories of a result (``truth``, ``future_00`` ...), its scene meshes (None
    for an older file without them) and its ``dt``."""
    path = result_file(result)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a samples file ({exc})") from None
    if "truth" not in arrays or "samples" not in arrays:
        raise ValueError(f"{path}: not a samples file (it needs truth and samples)")
    truth, samples = arrays["truth"], arrays["samples"]
    if truth.ndim != 3 or samples.ndim != 4 or samples.shape[2:] != truth.shape[1:]:
        raise ValueError(f"{path}: truth [T+1, L, 3] and samples [K, T, L, 3] do not match: "
                         f"{list(truth.shape)}, {list(samples.shape)}")
    futures = np.concatenate([np.broadcast_to(truth[:1], (len(samples), 1) + truth.shape[1:]), samples], axis=1)
    meshes = SceneMeshes.from_arrays(arrays) if "mesh_vertices" in arrays else None
    dt = float(arrays["dt"]) if "dt" in arrays else None
    return sample_trajectories(truth, futures), meshes, dt


def serve(folder: str | os.PathLike, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT) -> http.server.ThreadingHTTPServer:
    """An HTTP server of ``folder``'s files on ``host:port`` (port 0: a free one), not yet
    started: call ``serve_forever()`` (here or in a thread) and ``shutdown()``."""
    handler = functools.partial(_QuietHandler, directory=str(folder))
    return http.server.ThreadingHTTPServer((host, int(port)), handler)


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format: str, *args) -> None:  # one line a request would drown the URL
        pass


def run(args: argparse.Namespace) -> int:
    if args.fps <= 0:
        raise ValueError(f"--fps must be > 0, got {args.fps}")
    if not 0 <= args.port <= 65535:
        raise ValueError(f"--port must be in [0, 65535], got {args.port}")
    trajectories, meshes, dt = load_result(args.result)
    out = Path(args.out) if args.out else result_file(args.result).parent / VIEWER_NAME
    write_viewer(out, trajectories, meshes, dt=dt, fps=args.fps,
                 title=f"{result_file(args.result).parent.resolve().name}: ground truth (dark) and {len(trajectories) - 1} futures (light); "
                       "click a legend entry to hide it")
    print(f"wrote {out} (opens from disk too)")
    if args.no_serve:
        return 0
    try:
        server = serve(out.parent, args.host, args.port)
    except OSError as exc:
        raise ValueError(f"cannot serve on {args.host}:{args.port}: {exc.strerror or exc}") from None
    host, port = server.server_address[:2]
    print(f"serving http://{host}:{port}/{out.name}  (Ctrl-C stops)", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
    return 0
