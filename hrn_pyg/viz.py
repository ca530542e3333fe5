"""Pictures of particle scenes: rollouts side by side (Fig. 5), sampled futures (Fig. 6), GIFs.

Every function takes leaf positions ``[T, L, 3]`` and writes its file atomically (matplotlib
``Agg``). The ground ``z = 0`` is a light grid under the particles; static objects are light
grey; axis limits come from the reference rollout plus a margin, each axis to scale (sample
pictures also cover the quantiles :data:`SAMPLES_BULK` to ``1 - SAMPLES_BULK`` of the samples),
and a panel says what fraction of its points fell outside.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Sequence

import numpy as np

from hrn_pyg.utils.files import atomic_path

#: Colours per object (a colour-blind-safe palette); object ``o`` takes ``PALETTE[o % 8]``.
PALETTE = ("#0072B2", "#E69F00", "#009E73", "#CC79A7", "#D55E00", "#56B4E9", "#F0E442", "#000000")
#: static objects (never move) in light grey, so the moving ones stand out against them
STATIC_COLOR = "#c4c4c4"
#: the ground truth in the sample pictures: dark, over the light samples
TRUTH_COLOR = "0.1"
#: colour of the ground grid lines at z = 0
GROUND_COLOR = "0.75"
#: ground grid lines per horizontal axis
GROUND_LINES = 7
#: smallest axis length (m): a scene flat along one axis still gets a readable box
MIN_EXTENT = 0.15
#: margin (m) around the ground truth in pictures of sampled futures: room for a plausible spread
SAMPLES_PAD = 0.1
#: the sample pictures' limits also cover the central part of the samples: per axis and per time
#: step, the quantiles ``q`` and ``1 - q`` of the sample points (a few wild samples do not count;
#: a future that splits, as on the wedge, keeps both branches in view at every step)
SAMPLES_BULK = 0.02
#: camera: elevation and azimuth (degrees)
VIEW = (18, -72)
#: how far the 3-D box is zoomed into its panel (matplotlib leaves a wide margin at 1)
ZOOM = 1.1


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend (files only, no display), imported on first use."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def object_colors(leaf_object: np.ndarray, static: np.ndarray | None = None) -> np.ndarray:
    """An RGB hex colour per leaf from its object id; leaves flagged ``static`` light grey.

    Shapes: ``leaf_object [L]``, ``static [L]`` bool (optional) ``-> [L]``.
    """
    leaf_object = np.asarray(leaf_object)
    colors = np.array([PALETTE[int(o) % len(PALETTE)] for o in leaf_object], dtype=object)
    if static is not None:
        static = np.asarray(static, dtype=bool)
        if static.shape != leaf_object.shape:
            raise ValueError(f"static must be [{leaf_object.shape[0]}] like leaf_object, got {static.shape}")
        colors[static] = STATIC_COLOR
    return colors.astype(str)


def scene_limits(*positions: np.ndarray, pad: float = 0.05) -> np.ndarray:
    """Axis limits ``[3, 2]`` covering every finite point given plus ``pad`` metres (and z = 0), each
    axis at least :data:`MIN_EXTENT` long, drawn to scale."""
    pts = np.concatenate([np.asarray(p, dtype=float).reshape(-1, 3) for p in positions], axis=0)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) == 0:
        raise ValueError("scene_limits: no finite positions given")
    lo, hi = pts.min(axis=0) - pad, pts.max(axis=0) + pad
    lo[2] = min(lo[2], 0.0)
    grow = np.maximum(MIN_EXTENT - (hi - lo), 0.0) / 2
    return np.stack([lo - grow, hi + grow], axis=1)


def _inside(pos: np.ndarray, limits: np.ndarray) -> np.ndarray:
    """Which points ``[P, 3]`` lie within ``limits [3, 2]`` (and are finite). Shapes: ``-> [P]``."""
    with np.errstate(invalid="ignore"):
        return ((pos >= limits[:, 0]) & (pos <= limits[:, 1])).all(axis=1)


def _bulk(samples: np.ndarray) -> np.ndarray:
    """Corners ``[2, 3]`` of the central part of the samples: per axis the quantiles
    :data:`SAMPLES_BULK` and ``1 - SAMPLES_BULK`` of each time step, united over the steps.
    Shapes: ``samples [K, T, L, 3]`` (or ``[..., 3]``) ``-> [2, 3]``."""
    samples = np.asarray(samples, dtype=float)
    steps = [samples[:, t] for t in range(samples.shape[1])] if samples.ndim == 4 else [samples]
    corners = []
    for step in steps:
        pts = step.reshape(-1, 3)
        pts = pts[np.isfinite(pts).all(axis=1)]
        if len(pts):
            corners.append(np.quantile(pts, [SAMPLES_BULK, 1.0 - SAMPLES_BULK], axis=0))
    if not corners:
        return np.zeros((0, 3))
    return np.stack([np.min([c[0] for c in corners], axis=0), np.max([c[1] for c in corners], axis=0)])


def _axes(fig, rows: int, cols: int, index: int, limits: np.ndarray, view: tuple[float, float] = VIEW):
    """A 3-D panel with the box to scale, no ticks or panes, the ground grid drawn first;
    ``view`` is the camera's (elevation, azimuth) in degrees."""
    ax = fig.add_subplot(rows, cols, index, projection="3d")
    ax.computed_zorder = False  # draw in call order: ground, static, samples, truth on top
    ax.set_xlim(*limits[0]); ax.set_ylim(*limits[1]); ax.set_zlim(*limits[2])
    ax.set_box_aspect(tuple(limits[:, 1] - limits[:, 0]), zoom=ZOOM)
    ax.view_init(elev=view[0], azim=view[1])
    ax.set_axis_off()
    for value in np.linspace(limits[0, 0], limits[0, 1], GROUND_LINES):
        ax.plot([value, value], limits[1], [0.0, 0.0], color=GROUND_COLOR, lw=0.5)
    for value in np.linspace(limits[1, 0], limits[1, 1], GROUND_LINES):
        ax.plot(limits[0], [value, value], [0.0, 0.0], color=GROUND_COLOR, lw=0.5)
    return ax


def _draw(ax, pos: np.ndarray, colors, limits: np.ndarray, size: float = 6.0, alpha: float = 1.0) -> int:
    """Scatter the points of ``pos [P, 3]`` inside ``limits``; returns how many were left out."""
    keep = _inside(pos, limits)
    colors = np.asarray(colors)
    if colors.ndim == 1 and colors.shape[0] == pos.shape[0]:
        colors = colors[keep]
    elif colors.ndim == 0:
        colors = str(colors)
    if keep.any():
        ax.scatter(pos[keep, 0], pos[keep, 1], pos[keep, 2], c=colors, s=size, alpha=alpha,
                   depthshade=False, linewidths=0)
    return int((~keep).sum())


def _note_out_of_view(ax, left_out: int, total: int) -> None:
    if left_out:
        share = 100 * left_out / total
        ax.text2D(0.5, 0.02, f"{share:.0f}% of points out of view" if share >= 1 else "<1% of points out of view",
                  transform=ax.transAxes, ha="center", fontsize=6, color="0.3")


def _static_mask(colors, n_leaves: int, static: np.ndarray | None) -> np.ndarray:
    """Leaves drawn as static scenery: ``static`` if given, else those coloured :data:`STATIC_COLOR`."""
    if static is not None:
        return np.asarray(static, dtype=bool)
    colors = np.asarray(colors)
    if colors.ndim == 1 and colors.shape[0] == n_leaves:
        return colors == STATIC_COLOR
    return np.zeros(n_leaves, dtype=bool)


def save_figure(fig, path: str | os.PathLike, dpi: float | None = None) -> None:
    """Write a matplotlib figure atomically (format from the suffix, PNG by default), then close it."""
    plt = pyplot()
    suffix = os.path.splitext(str(path))[1]
    with atomic_path(path, suffix=suffix) as tmp:
        fig.savefig(tmp, format=suffix[1:] or "png", dpi=dpi)
    plt.close(fig)


def rollout_grid(rows: dict[str, np.ndarray], times: Sequence[int], colors, path: str | os.PathLike,
                 title: str = "") -> None:
    """One row per named rollout (ground truth first), one column per time (Fig. 5); limits from the
    first row, other rows' points outside them counted in the panel.

    Shapes: each ``rows[name]`` is ``[T, L, 3]``; ``colors`` is ``[L]``.
    """
    plt = pyplot()
    reference = next(iter(rows.values()))
    limits = scene_limits(reference[list(times)])
    fig = plt.figure(figsize=(1.9 * len(times), 1.9 * len(rows)), dpi=100)
    for r, (name, pos) in enumerate(rows.items()):
        for c, t in enumerate(times):
            ax = _axes(fig, len(rows), len(times), r * len(times) + c + 1, limits)
            _note_out_of_view(ax, _draw(ax, pos[t], colors, limits), pos.shape[1])
            if r == 0:
                ax.set_title(f"t+{t}" if t else "t", fontsize=9)
            if c == 0:
                ax.text2D(-0.05, 0.5, name, transform=ax.transAxes, rotation=90, va="center",
                          ha="right", fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.subplots_adjust(left=0.04, right=0.99, bottom=0.01, top=0.9, wspace=0.0, hspace=0.0)
    save_figure(fig, path)


def _overlay(ax, truth_t: np.ndarray, samples_t: np.ndarray, colors, static: np.ndarray,
             limits: np.ndarray) -> None:
    """Static scenery light grey, each sample light in its object colours, the truth dark.

    Shapes: ``truth_t [L, 3]``, ``samples_t [K, L, 3]``, ``static [L]``.
    """
    moving = ~static
    colors = np.asarray(colors)
    sample_colors = colors[moving] if colors.ndim == 1 and colors.shape[0] == len(static) else colors
    _draw(ax, truth_t[static], STATIC_COLOR, limits, size=3.0, alpha=0.6)
    left_out = 0
    for k in range(samples_t.shape[0]):  # a handful of samples, not a loop over particles
        left_out += _draw(ax, samples_t[k][moving], sample_colors, limits, size=4.0, alpha=0.18)
    _draw(ax, truth_t[moving], TRUTH_COLOR, limits, size=4.0, alpha=0.9)
    _note_out_of_view(ax, left_out, samples_t.shape[0] * int(moving.sum()))


def _samples_legend(fig, colors, static: np.ndarray) -> None:
    """A legend of the sample pictures: the ground truth dark, the sampled futures light (in
    the first moving object's colour), static objects grey."""
    from matplotlib.lines import Line2D

    colors = np.asarray(colors)
    moving = colors[~static] if colors.ndim == 1 and colors.shape[0] == len(static) else colors.reshape(-1)
    light = str(moving[0]) if moving.size else PALETTE[0]
    handles = [Line2D([], [], ls="", marker="o", ms=5, color=TRUTH_COLOR, label="ground truth"),
               Line2D([], [], ls="", marker="o", ms=5, color=light, alpha=0.35, label="sampled futures")]
    if static.any():
        handles.append(Line2D([], [], ls="", marker="o", ms=5, color=STATIC_COLOR, label="static"))
    fig.legend(handles=handles, loc="lower right", fontsize=7, frameon=False, ncol=len(handles))


def figure_inches(size: tuple[int, int] | None, default: tuple[float, float], dpi: float) -> tuple[float, float]:
    """A figure's size in inches: ``size`` (width, height) in pixels at ``dpi``, or ``default``."""
    return default if size is None else (size[0] / dpi, size[1] / dpi)


def samples_figure(truth: np.ndarray, samples: np.ndarray, times: Sequence[int], colors,
                   path: str | os.PathLike, title: str = "", static: np.ndarray | None = None,
                   size: tuple[int, int] | None = None, view: tuple[float, float] = VIEW,
                   legend: bool = True) -> None:
    """Ground truth dark, each sampled future light, per time column (Fig. 6); static leaves drawn
    once, grey. Limits: the truth and the samples' bulk plus :data:`SAMPLES_PAD`.

    Shapes: ``truth`` ``[T, L, 3]``, ``samples`` ``[K, T, L, 3]``, ``colors`` ``[L]``,
    ``static`` ``[L]`` bool.
    """
    plt = pyplot()
    static = _static_mask(colors, truth.shape[1], static)
    limits = scene_limits(truth[list(times)], _bulk(samples[:, list(times)][:, :, ~static]), pad=SAMPLES_PAD)
    extent = limits[:, 1] - limits[:, 0]
    width = 2.2 * float(np.clip(extent[0] / max(extent[1], extent[2]) * 0.7, 1.0, 1.6))
    fig = plt.figure(figsize=figure_inches(size, (width * len(times), 2.4), 100), dpi=100)
    for c, t in enumerate(times):
        ax = _axes(fig, 1, len(times), c + 1, limits, view)
        _overlay(ax, truth[t], samples[:, t], colors, static, limits)
        ax.set_title(f"t+{t}" if t else "t", fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    if legend:
        _samples_legend(fig, colors, static)
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.8, wspace=0.0)
    save_figure(fig, path)


def write_gif(frames: dict[str, np.ndarray], colors, path: str | os.PathLike, fps: float = 10,
              samples: np.ndarray | None = None, static: np.ndarray | None = None,
              size: tuple[int, int] | None = None, view: tuple[float, float] = VIEW, legend: bool = True) -> None:
    """An animated GIF (or an H.264 ``.mp4`` through imageio-ffmpeg) with one panel per named rollout
    and optional sample clouds in the first; ``size`` is a frame's (width, height) in pixels.
    Limits as in :func:`samples_figure`.

    Shapes: each ``frames[name]`` ``[T, L, 3]``; ``samples`` ``[K, T, L, 3]``; ``static`` ``[L]``
    bool (default: leaves coloured :data:`STATIC_COLOR`).
    """
    import imageio.v2 as imageio

    plt = pyplot()
    arrays = list(frames.values())
    static = _static_mask(colors, arrays[0].shape[1], static)
    if samples is None:
        limits = scene_limits(arrays[0])
    else:
        limits = scene_limits(arrays[0], _bulk(samples[:, :, ~static]), pad=SAMPLES_PAD)
    T = min(a.shape[0] for a in arrays)
    images = []
    for t in range(T):  # one picture per time step
        fig = plt.figure(figsize=figure_inches(size, (3.2 * len(frames), 2.6), 80), dpi=80)
        for c, (name, pos) in enumerate(frames.items()):
            ax = _axes(fig, 1, len(frames), c + 1, limits, view)
            if samples is not None and c == 0:
                _overlay(ax, pos[t], samples[:, t], colors, static, limits)
            else:
                _note_out_of_view(ax, _draw(ax, pos[t], colors, limits), pos.shape[1])
            ax.set_title(f"{name}  t+{t}", fontsize=8)
        fig.subplots_adjust(left=0, right=1, bottom=0, top=0.9, wspace=0)
        if legend and samples is not None:
            _samples_legend(fig, colors, static)
        fig.canvas.draw()
        images.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
        plt.close(fig)
    if str(path).endswith(".mp4"):
        import imageio_ffmpeg

        height, width = (d - d % 2 for d in images[0].shape[:2])  # H.264 in yuv420p wants even sides
        with atomic_path(path, suffix=".mp4") as tmp:
            writer = imageio_ffmpeg.write_frames(str(tmp), (width, height), fps=fps, codec="libx264",
                                                 macro_block_size=1, output_params=["-f", "mp4"])
            writer.send(None)  # start the encoder
            for image in images:
                writer.send(np.ascontiguousarray(image[:height, :width]))
            writer.close()
        return
    with atomic_path(path, suffix=".gif") as tmp:
        imageio.mimsave(tmp, images, format="GIF", duration=1.0 / fps, loop=0)


def plot_curves(csv_path: str | os.PathLike, png_path: str | os.PathLike, x: str, ys: list[str],
                title: str = "", logy: bool = True) -> None:
    """Draw columns ``ys`` of a CSV against column ``x`` into a PNG (written atomically)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with open(csv_path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=110)
    for y in ys:
        pts = [(float(r[x]), float(r[y])) for r in rows if r.get(y) not in (None, "")]
        if pts:
            ax.plot(*zip(*pts), label=y, lw=1.2)
    ax.set_xlabel(x)
    if logy:
        ax.set_yscale("log")
    ax.set_title(title)
    ax.legend(frameon=False, fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, png_path)
