"""What more than one benchmark measures with: scenes, timed episodes and timed rollouts, and the
scores of sampled futures that only the benchmarks report (best of k, coverage, ridge sides).

The one helper module of ``benchmarks/`` (and of the experiments that time a model against
pybullet, ``experiments/``): a script imports from here, never from another script. Run the
scripts from the checkout as modules, ``python -m benchmarks.<name>``.
"""

from __future__ import annotations

import math
import statistics
import time

import numpy as np
import torch
from torch import Tensor
from torch_geometric.data import HeteroData

import hrn_pyg
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import NODE, object_span
from hrn_pyg.data.graph import object_centres as graph_object_centres
from hrn_pyg.checkpoints import load_model, resolve_model
from hrn_pyg.data.scene_file import builtin_scene, make_scene
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sampling.metrics import paired
from hrn_pyg.sim.fixed_shape import FixedShapeConfig, FixedShapeSimulator


DEFAULT_MESHES = ("pybullet_data:duck_vhacd.obj", "pybullet_data:torus/torus_textured.obj")


#: grid spacing and layer height of the starting arrangement (m); with sizes up to
#: :data:`MAX_SIZE` and yaw-only turns no two bounding boxes overlap
SPACING = 0.4


MAX_SIZE = 0.25


def pile_scene_text(count: int, material: str, meshes: tuple[str, ...], pitch: float, steps: int) -> str:
    """A scene file of ``count`` objects on a grid of layers that fall into a pile."""
    side = max(1, math.ceil(math.sqrt(count / 2)))  # two layers or more
    lines = [f"steps = {steps}", f"pitch = {pitch}", "rolling_friction = 0.03", ""]
    mesh_list = "[" + ", ".join(f'"{m}"' for m in meshes) + "]"
    for i in range(count):
        layer, cell = divmod(i, side * side)
        row, col = divmod(cell, side)
        x = (col - (side - 1) / 2) * SPACING
        y = (row - (side - 1) / 2) * SPACING
        z = 0.15 + layer * SPACING
        lines += ["[[objects]]", f"mesh = {mesh_list}", f'material = "{material}"',
                  f"size = {{ min = 0.15, max = {MAX_SIZE} }}", "mass = { min = 0.3, max = 1.5 }",
                  f"position = [{x:.3f}, {y:.3f}, {z:.3f}]", "yaw = { min = 0, max = 360 }"]
        if material == "soft":
            lines.append("stiffness = { min = 0.4, max = 0.7 }")
        lines.append("")
    return "\n".join(lines)


def time_pybullet(spec, seed: int) -> tuple[dict, float]:
    """One episode and pybullet's median seconds per model step."""
    durations: list[float] = []

    def timed(sim) -> None:
        step = sim.step

        def wrapped(*args, **kwargs):
            start = time.perf_counter()
            out = step(*args, **kwargs)
            durations.append(time.perf_counter() - start)
            return out

        sim.step = wrapped

    episode = simulate_episode(spec, seed, after_reset=timed)
    return episode, statistics.median(durations)


def rollout_seconds(model, state, steps: int) -> tuple[float, torch.Tensor]:
    """Seconds per step of one ``steps``-step rollout (sleeping off) and its positions."""
    with torch.no_grad():
        start = time.perf_counter()
        pos = hrn_pyg.rollout(model, state, steps, sleep=None)
        return (time.perf_counter() - start) / steps, pos


def time_rollout(model, state, steps: int, repeats: int) -> tuple[float, torch.Tensor]:
    """Median seconds per step of ``repeats`` rollouts of ``steps`` steps (after a warm-up)
    and the last one's positions."""
    rollout_seconds(model, state, 2)
    timed = [rollout_seconds(model, state, steps) for _ in range(repeats)]
    return statistics.median(s for s, _ in timed), timed[-1][1]


def compiled_rollout(model, state, steps: int, reset: bool = True):
    """A compiled fixed-shape simulator of ``model`` on ``state``, the seconds of its first
    (compiling) rollout, and a function that times one more rollout as :func:`rollout_seconds`.
    ``reset`` drops what was compiled before, as a new process would start (the simulators of
    one round must then be made after it: each has steps of its own)."""
    if reset:
        torch._dynamo.reset()
    simulator = FixedShapeSimulator(model, state, FixedShapeConfig(compile=True))
    leaf = state[NODE].is_leaf
    with torch.no_grad():
        start = time.perf_counter()
        simulator.rollout(steps)
        first = time.perf_counter() - start

    def timed() -> tuple[float, torch.Tensor]:
        with torch.no_grad():
            start = time.perf_counter()
            pos = simulator.rollout(steps).pos
            return (time.perf_counter() - start) / steps, pos[:, leaf]  # leaves, as rollout_seconds

    return first, timed


def lattice(n: int) -> np.ndarray:
    """``[n^3, 3]`` integer lattice coordinates of an ``n x n x n`` block."""
    g = np.arange(n)
    return np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)


def octree_parent(idx: np.ndarray, leaf_object: np.ndarray) -> np.ndarray:
    """Parent array (leaves first, then ancestors; roots -1) of an octree over lattice leaves.

    Level ``k`` groups the leaves whose coordinates agree after dropping ``k`` low bits, per
    object; a level with one group per object is the roots. Leaf groups hold at most 8 leaves and
    every ancestor at most 8 children (branching 8, leaf group 8).
    """
    n_leaves = len(idx)
    n_objects = len(np.unique(leaf_object))
    levels = []  # per level: node id of each leaf's ancestor at that level
    next_id, shift = n_leaves, 0
    while not levels or levels[-1].max() + 1 - levels[-1].min() > n_objects:  # about log2 n levels
        shift += 1
        _, group = np.unique(np.column_stack([leaf_object, idx >> shift]), axis=0, return_inverse=True)
        group = group.reshape(-1)
        levels.append(next_id + group)
        next_id += int(group.max()) + 1
    parent = np.full(next_id, -1, dtype=np.int64)
    parent[np.arange(n_leaves)] = levels[0]
    for below, above in zip(levels[:-1], levels[1:]):
        parent[below] = above  # every leaf names the same pair for its two ancestors
    return parent


def cubes_scene(n: int, objects: int, pitch: float, per_row: int | None = None):
    """Leaf positions ``[L, 3]``, leaf object ``[L]`` and parent ``[N]`` of ``objects`` cubes of
    ``n^3`` leaves at ``pitch``, on a grid with neighbouring faces one pitch apart."""
    per_row = per_row or max(1, math.ceil(math.sqrt(objects)))
    block = lattice(n)
    step = n * pitch  # (n - 1) pitch of cube plus one pitch of gap
    pos, obj, idx = [], [], []
    for o in range(objects):  # a handful of objects
        offset = np.array([(o % per_row) * step, (o // per_row) * step, 0.5])
        pos.append(block * pitch + offset)
        obj.append(np.full(len(block), o))
        idx.append(block)
    leaf_object = np.concatenate(obj)
    return np.concatenate(pos), leaf_object, octree_parent(np.concatenate(idx), leaf_object)


#: the horizons the accuracy-against-time sweep scores (model steps)
HORIZONS = (5, 15)


#: window starts this many steps apart in a test episode (evaluate's default)
STRIDE = 10


def pybullet_ms_per_step(scene: str, pitch: float, repeats: int, steps: int = 20) -> tuple[float, int]:
    """Median wall time (ms) of one model step of pybullet itself, and the leaf count."""
    times, leaves = [], 0
    for r in range(repeats):
        sim = make_scene(builtin_scene(scene, pitch=pitch), r)
        try:
            leaves = len(sim.reset())
            start = time.perf_counter()
            for t in range(steps):  # model steps, each `substeps` physics steps
                sim.step(*sim.scripted_action(t))
            times.append((time.perf_counter() - start) / steps)
        finally:
            sim.close()
    return 1e3 * statistics.median(times), leaves


#: the dropout rate timed (the paper's soft-cube test rate); rate 0 would skip the masks
SAMPLING_RATE = 0.3


#: the scene and pybullet seed of the sampling benchmarks
SAMPLING_SCENE, SAMPLING_SEED = "soft_bounce", 0


def model_for(scene: str, path: str | None, random_init: bool, fit_on: HeteroData,
              device: torch.device | str | None = None) -> HRN:
    """The scene's checkpoint, or (``random_init``, for checking a pipeline only) an untrained
    :class:`HRN` with seed 0 whose normaliser is fitted on ``fit_on``; on ``device`` (None: the
    CPU)."""
    if not random_init:
        return load_model(resolve_model(scene, path), device)
    torch.manual_seed(0)
    model = HRN(HRNConfig())
    fit_normalizer([fit_on], model.normalizer)
    model.eval()
    return model if device is None else model.to(device)


def sampling_setup(steps: int) -> tuple[HRN, object, torch.Tensor]:
    """An untrained :class:`HRN` (seed 0, normaliser fitted on the window), a ``steps``-step
    window of :data:`SAMPLING_SCENE` and its forces ``[steps, N, 3]``."""
    episode = simulate_episode(SAMPLING_SCENE, SAMPLING_SEED, steps=steps + 4)
    window = episode_state(episode, start=2, steps=steps)
    torch.manual_seed(0)
    model = HRN(HRNConfig())
    fit_normalizer([window], model.normalizer)
    model.eval()
    forces = window[NODE].force_seq.transpose(0, 1).contiguous()  # [steps, N, 3]
    return model, window, forces


# --------------------------------------------------------------------------------------------
# scores of sampled futures beside hrn_pyg.sampling.metrics (energy_score, root_spread)

#: the two sides of the wedge's ridge, in the order :func:`side_fractions` returns them
SIDES = ("below", "above")


def best_of_k_error(samples: Tensor, truth: Tensor) -> Tensor:
    r"""Mean particle distance of the closest sample, averaged over the ground-truth members.

    .. math::
        \mathrm{BoK} = \frac{1}{M} \sum_{m=1}^{M} \min_{k} \frac{1}{L} \sum_{l=1}^{L}
            \lVert X_{k,l} - y_{m,l} \rVert

    **Shapes:** samples ``(K, *, L, 3)``, truth ``(M, *, L, 3)``; returns ``(*)``.
    """
    samples, truth = paired(samples, truth)
    if samples.dim() < 3 or samples.shape[-1] != 3:
        raise ValueError(f"samples must be [K, ..., L, 3], got {tuple(samples.shape)}")
    error = (samples.unsqueeze(1) - truth.unsqueeze(0)).norm(dim=-1).mean(dim=-1)  # [K, M, *]
    return error.min(dim=0).values.mean(dim=0)


def coverage(samples: Tensor, truth: Tensor, per: str = "coordinate") -> Tensor:
    r"""Fraction of the ground truth inside the samples' per-coordinate range
    :math:`[\ell_d, u_d] = [\min_k X_{k,d}, \max_k X_{k,d}]`: ``per="coordinate"``
    :math:`\frac{1}{MD} \sum_{m,d} \mathbb{1}[\ell_d \le y_{m,d} \le u_d]`, ``per="member"``
    :math:`\frac{1}{M} \sum_m \prod_d \mathbb{1}[\ell_d \le y_{m,d} \le u_d]`.

    **Shapes:** samples ``(K, *, D)``, truth ``(M, *, D)``; returns ``(*)``.
    """
    if per not in ("coordinate", "member"):
        raise ValueError(f"per must be 'coordinate' or 'member', got {per!r}")
    samples, truth = paired(samples, truth)
    low, high = samples.min(dim=0).values, samples.max(dim=0).values
    inside = (truth >= low) & (truth <= high)  # [M, *, D]
    if per == "member":
        return inside.all(dim=-1).to(samples.dtype).mean(dim=0)
    return inside.to(samples.dtype).mean(dim=(0, -1))


def object_centres(positions: Tensor, leaf_object: Tensor, leaf_mass: Tensor) -> Tensor:
    r"""Mass-weighted centre of each object's leaves: the position of its hierarchy root.

    .. math:: r_o = \sum_{l \in o} m_l x_l \Big/ \sum_{l \in o} m_l

    **Shapes:** positions ``(*, L, 3)``, leaf_object ``(L,)`` in ``0..O-1``, leaf_mass ``(L,)``;
    returns ``(*, O, 3)``.
    """
    positions = torch.as_tensor(positions)
    leaf_object = torch.as_tensor(leaf_object, device=positions.device).long()
    leaf_mass = torch.as_tensor(leaf_mass, device=positions.device).to(positions.dtype)
    if positions.dim() < 2 or positions.shape[-1] != 3:
        raise ValueError(f"positions must be [..., L, 3], got {tuple(positions.shape)}")
    n_leaves = positions.shape[-2]
    if leaf_object.shape != (n_leaves,) or leaf_mass.shape != (n_leaves,):
        raise ValueError(f"leaf_object and leaf_mass must be [{n_leaves}], got {tuple(leaf_object.shape)}, {tuple(leaf_mass.shape)}")
    if bool((leaf_mass <= 0).any()) or bool((leaf_object < 0).any()):
        raise ValueError("leaf_mass must be > 0 and leaf_object >= 0")
    return graph_object_centres(positions, leaf_object, object_span(leaf_object), leaf_mass)


def side_fractions(coordinate: Tensor, ridge: float = 0.0) -> Tensor:
    r"""Fraction of trajectories ending on each side (:data:`SIDES`) of the ridge at ``r``:
    :math:`\bigl(\frac{1}{K}\#\{c_k < r\},\ \frac{1}{K}\#\{c_k \ge r\}\bigr)` of the ball's final
    ``coordinate``.

    **Shapes:** coordinate ``(K,)``; returns ``(2,)``.
    """
    coordinate = torch.as_tensor(coordinate)
    if coordinate.dim() != 1 or coordinate.numel() < 1:
        raise ValueError(f"coordinate must be [K>=1], got {tuple(coordinate.shape)}")
    if not bool(torch.isfinite(coordinate).all()):
        raise ValueError("coordinate contains NaN or infinite values")
    below = (coordinate < ridge).to(torch.float64).mean()
    return torch.stack([below, 1.0 - below])
