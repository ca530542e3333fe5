"""Lossless, compact transport of episode folders to a lent GPU machine (64 MiB per call).

``pack``: every ``episode_*.npz`` of a folder into one ``<scene>.pack.npz`` whose leaf positions
are stored as LZMA-compressed time differences of their float32 bit patterns (exact: integer
differences of the bits, summed back on arrival); rest phases compress to almost nothing.
``unpack``: the folder again, each episode written with :func:`hrn_pyg.data.io.save_episode`.
No pickle anywhere (``allow_pickle=False``).

Usage: ``python benchmarks/device/pack.py pack data/soft_bounce OUT.pack.npz`` /
``python benchmarks/device/pack.py unpack OUT.pack.npz data/soft_bounce``.
"""

from __future__ import annotations

import lzma
import sys
from pathlib import Path

import numpy as np

from hrn_pyg.data.io import load_episode, save_episode


def pack(folder: str, out: str) -> None:
    arrays: dict[str, np.ndarray] = {}
    for path in sorted(Path(folder).glob("episode_*.npz")):
        ep = load_episode(path)
        tag = path.stem
        bits = np.ascontiguousarray(ep["positions"], dtype=np.float32).view(np.int32)
        delta = np.diff(bits, axis=0, prepend=np.zeros_like(bits[:1]))
        arrays[f"{tag}/positions_lzma"] = np.frombuffer(lzma.compress(delta.tobytes()), dtype=np.uint8)
        arrays[f"{tag}/positions_shape"] = np.asarray(bits.shape, dtype=np.int64)
        for key, value in ep.items():
            if key != "positions":
                arrays[f"{tag}/{key}"] = np.asarray(value)
    np.savez_compressed(out, **arrays)


def unpack(packed: str, folder: str) -> None:
    data = np.load(packed, allow_pickle=False)
    tags = sorted({name.split("/")[0] for name in data.files})
    Path(folder).mkdir(parents=True, exist_ok=True)
    for tag in tags:
        shape = tuple(int(s) for s in data[f"{tag}/positions_shape"])
        delta = np.frombuffer(lzma.decompress(data[f"{tag}/positions_lzma"].tobytes()), dtype=np.int32)
        bits = np.cumsum(delta.reshape(shape), axis=0, dtype=np.int32)
        episode = {name.split("/", 1)[1]: data[name] for name in data.files
                   if name.startswith(tag + "/") and "positions_" not in name}
        episode["positions"] = bits.view(np.float32)
        save_episode(Path(folder) / f"{tag}.npz", episode)


if __name__ == "__main__":
    command, src, dst = sys.argv[1:4]
    {"pack": pack, "unpack": unpack}[command](src, dst)
