"""Pictures of particle scenes: rollouts side by side (Fig. 5), sampled futures (Fig. 6), GIFs.

Every function takes leaf positions as arrays ``[T, L, 3]`` (time, leaf, xyz) and writes its
file atomically. Matplotlib runs on the ``Agg`` backend, so no screen is needed.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from hrn_pyg.utils.files import atomic_path

#: Colours per object (a colour-blind-safe palette); object ``o`` takes ``PALETTE[o % 8]``.
PALETTE = ("#0072B2", "#E69F00", "#009E73", "#CC79A7", "#D55E00", "#56B4E9", "#F0E442", "#000000")


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def object_colors(leaf_object: np.ndarray) -> np.ndarray:
    """An RGB hex colour per leaf from its object id. Shapes: ``[L] -> [L]``."""
    return np.array([PALETTE[int(o) % len(PALETTE)] for o in np.asarray(leaf_object)])


def scene_limits(*positions: np.ndarray, pad: float = 0.05) -> np.ndarray:
    """Common axis limits ``[3, 2]`` covering every array given (ground z = 0 always shown)."""
    pts = np.concatenate([np.asarray(p).reshape(-1, 3) for p in positions], axis=0)
    pts = pts[np.isfinite(pts).all(axis=1)]
    lo, hi = pts.min(axis=0) - pad, pts.max(axis=0) + pad
    lo[2] = min(lo[2], 0.0)
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2
    return np.stack([centre - half, centre + half], axis=1)


def _draw(ax, pos: np.ndarray, colors, limits: np.ndarray, size: float = 6.0, alpha: float = 1.0):
    ax.scatter(pos[:, 0], pos[:, 1], pos[:, 2], c=colors, s=size, alpha=alpha, depthshade=False,
               linewidths=0)
    ax.set_xlim(*limits[0]); ax.set_ylim(*limits[1]); ax.set_zlim(*limits[2])
    ax.view_init(elev=18, azim=-60)
    ax.set_xticks([]); ax.set_yticks([]); ax.set_zticks([])
    # draw the ground as a light square
    xs = np.array([limits[0, 0], limits[0, 1]])
    ys = np.array([limits[1, 0], limits[1, 1]])
    X, Y = np.meshgrid(xs, ys)
    ax.plot_surface(X, Y, np.zeros_like(X), color="0.85", alpha=0.3, linewidth=0)


def _save(fig, path: str | os.PathLike) -> None:
    plt = _plt()
    with atomic_path(path, suffix=os.path.splitext(str(path))[1]) as tmp:
        fig.savefig(tmp, format=os.path.splitext(str(path))[1][1:] or "png")
    plt.close(fig)


def rollout_grid(rows: dict[str, np.ndarray], times: Sequence[int], colors, path: str | os.PathLike,
                 title: str = "") -> None:
    """One row per named rollout (e.g. ground truth, HRN, ours), one column per time (Fig. 5).

    Shapes: each ``rows[name]`` is ``[T, L, 3]``; ``colors`` is ``[L]``.
    """
    plt = _plt()
    limits = scene_limits(*[r[list(times)] for r in rows.values()])
    fig = plt.figure(figsize=(1.9 * len(times), 1.9 * len(rows)), dpi=100)
    for r, (name, pos) in enumerate(rows.items()):
        for c, t in enumerate(times):
            ax = fig.add_subplot(len(rows), len(times), r * len(times) + c + 1, projection="3d")
            _draw(ax, pos[t], colors, limits)
            if r == 0:
                ax.set_title(f"t+{t}" if t else "t", fontsize=9)
            if c == 0:
                ax.text2D(-0.05, 0.5, name, transform=ax.transAxes, rotation=90, va="center",
                          ha="right", fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.subplots_adjust(left=0.04, right=0.99, bottom=0.01, top=0.9, wspace=0.0, hspace=0.0)
    _save(fig, path)


def samples_figure(truth: np.ndarray, samples: np.ndarray, times: Sequence[int], colors,
                   path: str | os.PathLike, title: str = "") -> None:
    """Ground truth dark, each sampled future light, overlaid per time column (Fig. 6).

    Shapes: ``truth`` ``[T, L, 3]``, ``samples`` ``[K, T, L, 3]``, ``colors`` ``[L]``.
    """
    plt = _plt()
    limits = scene_limits(truth[list(times)], samples[:, list(times)])
    fig = plt.figure(figsize=(2.2 * len(times), 2.4), dpi=100)
    for c, t in enumerate(times):
        ax = fig.add_subplot(1, len(times), c + 1, projection="3d")
        for k in range(samples.shape[0]):  # loop over a handful of samples, not particles
            _draw(ax, samples[k, t], colors, limits, size=3.0, alpha=0.12)
        _draw(ax, truth[t], "0.15", limits, size=4.0, alpha=0.9)
        ax.set_title(f"t+{t}" if t else "t", fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.85, wspace=0.0)
    _save(fig, path)


def write_gif(frames: dict[str, np.ndarray], colors, path: str | os.PathLike, fps: int = 10,
              samples: np.ndarray | None = None) -> None:
    """An animated GIF with one panel per named rollout; optional light sample clouds on top.

    Shapes: each ``frames[name]`` ``[T, L, 3]``; ``samples`` ``[K, T, L, 3]`` drawn in the first
    panel.
    """
    import imageio.v2 as imageio

    plt = _plt()
    arrays = list(frames.values())
    limits = scene_limits(*arrays, *([samples] if samples is not None else []))
    T = min(a.shape[0] for a in arrays)
    images = []
    for t in range(T):  # one picture per time step
        fig = plt.figure(figsize=(2.6 * len(frames), 2.6), dpi=80)
        for c, (name, pos) in enumerate(frames.items()):
            ax = fig.add_subplot(1, len(frames), c + 1, projection="3d")
            if samples is not None and c == 0:
                for k in range(samples.shape[0]):
                    _draw(ax, samples[k, t], colors, limits, size=3.0, alpha=0.12)
                _draw(ax, pos[t], "0.15", limits, size=4.0)
            else:
                _draw(ax, pos[t], colors, limits)
            ax.set_title(f"{name}  t+{t}", fontsize=8)
        fig.subplots_adjust(left=0, right=1, bottom=0, top=0.9, wspace=0)
        fig.canvas.draw()
        images.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
        plt.close(fig)
    with atomic_path(path, suffix=".gif") as tmp:
        imageio.mimsave(tmp, images, format="GIF", duration=1.0 / fps, loop=0)
