"""Draw ``docs/figures/data_<scene>.png``: each scene's leaves at three moments, coloured by
their hierarchy cluster one level below the object's root.

Run: ``python docs/figures/make_data_figures.py [--scenes soft_bounce ...] [--seed 0]``.
The wedge figure adds a panel with the ball's final position over many seeds.
"""

from __future__ import annotations

import argparse
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.scene_file import SCENES  # noqa: E402
from hrn_pyg.viz import save_figure  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
#: Seeds for the wedge's "where does the ball end" panel.
WEDGE_SEEDS = 16


def first_level_cluster(parent: np.ndarray, num_leaves: int) -> np.ndarray:
    """Index of each leaf's ancestor one level below its root (the root itself if none).

    **Shapes** ``parent [N]`` -> ``[L]`` node indices.
    """
    node = np.arange(num_leaves)
    # climb until the parent is a root; the tree is shallow (< 10 levels), so loop over depth
    while True:
        up = parent[node]
        is_top = (up < 0) | (parent[np.maximum(up, 0)] < 0)
        if np.all(is_top | (up < 0)):
            return np.where(up < 0, node, np.where(parent[np.maximum(up, 0)] < 0, node, up))
        node = np.where(is_top, node, up)


def moments(scene: str, positions: np.ndarray) -> list[int]:
    """Three telling steps: start, middle, end; for soft_bounce the flight apex and the step of
    largest deformation (pairwise distances furthest from rest)."""
    steps = len(positions) - 1
    if scene == "soft_bounce":
        x = positions.astype(np.float64)
        rest = np.linalg.norm(x[0][:, None] - x[0][None], axis=-1)
        strain = np.array([np.abs(np.linalg.norm(xt[:, None] - xt[None], axis=-1) - rest).max()
                           for xt in x])
        apex = int(np.argmax(x[:, :, 2].mean(axis=1)))
        after = apex + int(np.argmax(strain[apex:]))
        return [0, apex, after]
    return [0, steps // 2, steps]


def draw(scene: str, seed: int, out: str) -> str:
    ep = simulate_episode(scene, seed)
    pos, parent = ep["positions"], ep["hierarchy_parent"]
    num_leaves = pos.shape[1]
    cluster = first_level_cluster(parent, num_leaves)
    _, colour_index = np.unique(cluster, return_inverse=True)
    colours = plt.get_cmap("tab20")(colour_index % 20)
    static = ep["object_material"][ep["leaf_object"]] == 3
    colours[static] = (0.6, 0.6, 0.6, 1.0)
    picks = moments(scene, pos)
    extra = scene == "wedge"
    fig = plt.figure(figsize=(3.0 * (3 + extra), 3.0), dpi=80)
    shown = pos[picks].reshape(-1, 3)
    lo, hi = shown.min(axis=0), shown.max(axis=0)
    centre, half = (lo + hi) / 2, min(max((hi - lo).max() / 2, 0.15), 0.6)
    for k, t in enumerate(picks):
        ax = fig.add_subplot(1, 3 + extra, k + 1, projection="3d")
        x = pos[t]
        ax.scatter(x[:, 0], x[:, 1], x[:, 2], c=colours, s=6, depthshade=False)
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(0, 2 * half)
        ax.set_title(f"{scene}  t={t * float(ep['dt']):.2f}s", fontsize=8)
        ax.tick_params(labelsize=5)
        ax.view_init(elev=18, azim=-60)
    if extra:
        ax = fig.add_subplot(1, 4, 4)
        finals = []
        for s in range(WEDGE_SEEDS):
            e = simulate_episode("wedge", s)
            ball = e["leaf_object"] == 0
            finals.append(e["positions"][-1][ball].mean(axis=0))
        finals = np.array(finals)
        wedge = ep["positions"][0][static]
        ax.scatter(wedge[:, 0], wedge[:, 2], c="0.6", s=4)
        ax.scatter(finals[:, 0], finals[:, 2], c=np.where(finals[:, 0] < 0, "C0", "C3"), s=20)
        ax.set_title(f"ball end (x, z), {WEDGE_SEEDS} seeds", fontsize=8)
        ax.tick_params(labelsize=6)
        ax.set_aspect("equal")
    fig.tight_layout()
    path = os.path.join(out, f"data_{scene}.png")
    save_figure(fig, path)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="*", default=list(SCENES))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=HERE)
    args = parser.parse_args()
    for scene in args.scenes:
        print(draw(scene, args.seed, args.out))


if __name__ == "__main__":
    main()
