"""K plausible futures of one scene by Monte Carlo graph-convolutional dropout (seed paper, 3.2).

The K trajectories are K copies of the scene in one batched graph
(:func:`hrn_pyg.data.graph.replicate`) rolled out by the one rollout loop
(:func:`hrn_pyg.sim.rollout.rollout`). Each step draws a fresh ``[K, H]`` mask per masked
module; nodes and edges look up their copy's row, so one trajectory applies one mask everywhere
in a step. No Python loop over samples.
"""

from __future__ import annotations

import copy
import warnings
from collections.abc import Mapping

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.data.effects import SceneEffects
from hrn_pyg.data.graph import NODE, replicate
from hrn_pyg.nn.hrn import HRN
from hrn_pyg.nn.mlp import dropout_mask
from hrn_pyg.sim.fixed_shape import FixedShapeConfig, fixed_shape_rollout
from hrn_pyg.sim.rollout import iterate
from hrn_pyg.sim.sleeping import DEFAULT_SLEEP, SleepConfig
from hrn_pyg.sim.step import MasksFn
from hrn_pyg.utils.checks import check_count, check_rate

#: the state a scene must carry to be rolled out (``x_{t-2}, x_{t-1}, x_t``)
STATE_FIELDS = ("prev_prev_pos", "prev_pos", "pos")
#: per-window attributes of a dataset window that the copies do not need (dropped before
#: replicating, so K copies do not collate K copies of the whole ground-truth sequence)
WINDOW_ONLY_FIELDS = ("pos_seq", "force_seq")


def check_sampling_args(k: int, steps: int, rate: float) -> None:
    """Raise ValueError unless ``k >= 1``, ``steps >= 1`` and ``0 <= rate < 1``."""
    check_count(k, "k")
    check_count(steps, "steps")
    check_rate(rate)


def _check_state(graph: HeteroData) -> None:
    if not isinstance(graph, HeteroData) or NODE not in graph.node_types:
        raise ValueError(f"initial_state must be a HeteroData with a '{NODE}' node type")
    store = graph[NODE]
    for name in STATE_FIELDS:
        if name not in store:
            raise ValueError(f"initial_state['{NODE}'] has no '{name}' (set it with hrn_pyg.data.graph.set_state)")
        value = store[name]
        if value.dim() != 2 or value.shape != (store.num_nodes, 3):
            raise ValueError(f"initial_state '{name}' must be [{store.num_nodes}, 3], got {tuple(value.shape)}")
        if not bool(torch.isfinite(value).all()):
            raise ValueError(f"initial_state '{name}' contains NaN or infinite values")
    if "batch" in store and bool((store.batch != 0).any()):
        raise ValueError("initial_state must be one scene, not a batch of several graphs")


def _check_modules(model: HRN, modules: tuple[str, ...] | None) -> tuple[str, ...]:
    allowed = tuple(model.config.dropout_modules)
    if modules is None:
        return allowed
    modules = tuple(modules)
    unknown = [m for m in modules if m not in allowed]
    if unknown:
        raise ValueError(
            f"modules {unknown} do not accept dropout masks in this model (its dropout_modules are {allowed})"
        )
    return modules


def model_device(model: HRN) -> torch.device:
    """The device the model's weights (and so its inputs) live on."""
    return model.normalizer.velocity_std.device


def draw_masks(model: HRN, k: int, rate: float, generator: torch.Generator | None = None) -> dict[str, Tensor]:
    """:meth:`HRN.sample_masks` from a generator on any device (a CPU generator draws on the CPU, the
    same numbers as for a CPU model), the masks moved to the model's device.

    **Shapes:** ``{module: (k, hidden)}`` (``G k`` rows for a mirror-averaged model).
    """
    device = model_device(model)
    if generator is None or generator.device == device:
        return model.sample_masks(k, rate, generator)
    hidden, rows = model.config.hidden, model.mask_rows(k)
    return {name: dropout_mask(rows, hidden, rate, generator, generator.device).to(device)
            for name in model.config.dropout_modules}


def make_masks_fn(
    model: HRN,
    k: int,
    rate: float,
    generator: torch.Generator | None = None,
    modules: tuple[str, ...] | None = None,
) -> MasksFn | None:
    r"""A ``masks_fn(t, graph)`` for :func:`hrn_pyg.sim.rollout.rollout` drawing, each call and for
    every module in ``modules`` (default ``config.dropout_modules``), one inverted-dropout mask per
    trajectory copy from ``generator`` (:func:`draw_masks`):

    .. math:: m^{(t)}_{b,h} = \mathbb{1}[u^{(t)}_{b,h} \ge p] / (1 - p), \qquad u \sim U[0, 1)

    Rate 0 returns None (the deterministic model). **Shapes:** ``{module: (k, hidden)}``.
    """
    check_sampling_args(k, 1, rate)
    modules = _check_modules(model, modules)
    if float(rate) == 0.0 or not modules:
        return None

    def masks_fn(t: int, graph: HeteroData) -> Mapping[str, Tensor]:
        masks = draw_masks(model, k, float(rate), generator)
        return {name: masks[name] for name in modules}

    return masks_fn


def copies_forces(forces: Tensor | None, graph: HeteroData, steps: int, k: int) -> Tensor | None:
    """``[steps, N or L, 3]`` forces of one scene -> ``[steps, k N, 3]`` for the k copies."""
    if forces is None:
        return None
    store = graph[NODE]
    n, leaves = store.num_nodes, int(store.is_leaf.sum())
    if forces.dim() != 3 or forces.shape[0] < steps or forces.shape[2] != 3 or forces.shape[1] not in (n, leaves):
        raise ValueError(f"forces must be [steps>={steps}, {n} nodes or {leaves} leaves, 3], got {tuple(forces.shape)}")
    if not bool(torch.isfinite(forces).all()):
        raise ValueError("forces contains NaN or infinite values")
    forces = forces[:steps].to(device=store.pos.device, dtype=store.pos.dtype)
    if forces.shape[1] == leaves:
        full = forces.new_zeros(steps, n, 3)
        full[:, store.is_leaf] = forces
        forces = full
    forces = torch.where(store.is_leaf[None, :, None], forces, torch.zeros_like(forces))
    return forces.repeat(1, k, 1)  # copy b holds nodes b N .. (b + 1) N - 1


def sample(
    model: HRN,
    initial_state: HeteroData,
    k: int,
    steps: int,
    rate: float,
    forces: Tensor | None = None,
    generator: torch.Generator | None = None,
    modules: tuple[str, ...] | None = None,
    sleep: SleepConfig | None = DEFAULT_SLEEP,
    effects: SceneEffects | None = None,
    fixed_shape: FixedShapeConfig | None = None,
    seed: int | None = None,
) -> Tensor:
    r"""Sample ``k`` futures of one scene with Monte Carlo graph-convolutional dropout.

    The scene is replicated ``k`` times into one batched graph; at step ``t`` copy ``b`` runs with
    its own mask :math:`m^{(t)}_b` (:func:`make_masks_fn`) on every node and edge:

    .. math::
        x^{(b)}_{t+1} = f_\theta\bigl(x^{(b)}_{t}, x^{(b)}_{t-1}, x^{(b)}_{t-2}, F_t;\ m^{(t)}_b\bigr),
        \qquad b = 1..k

    Without gradients, on the model's device (the caller's graph is not changed); a seeded
    ``generator`` or ``seed`` repeats exactly.

    Args:
        model: a trained :class:`~hrn_pyg.nn.hrn.HRN` with a fitted normaliser.
        initial_state: one scene's graph with ``prev_prev_pos``, ``prev_pos``, ``pos``.
        k: number of sampled trajectories, >= 1.
        steps: predicted steps, >= 1.
        rate: dropout rate in [0, 1); 0: every copy is the deterministic rollout.
        forces: force per step on each node ``[steps, N, 3]`` or leaf ``[steps, L, 3]``; None: none.
        generator: source of the masks (None: torch's global generator; :func:`draw_masks`).
        modules: modules to mask (default and superset: ``config.dropout_modules``).
        sleep: objects at rest sleep, each copy's on its own (:mod:`hrn_pyg.sim.sleeping`);
            None runs every object at every step.
        effects: what the scene needs simulated (:class:`~hrn_pyg.data.effects.SceneEffects`);
            None: what the data show.
        seed: seeds the masks with a CPU generator (the same futures on any device); not with
            ``generator``.
        fixed_shape: fixed-shape steps (:mod:`hrn_pyg.sim.fixed_shape`); needs ``sleep=None``.

    A future that stops being finite is held (:mod:`hrn_pyg.sim.rules`), NaN from then on, with a
    RuntimeWarning; the model's rules after the network apply to every future.

    Returns:
        Leaf positions ``[k, steps, L, 3]`` at ``t+1 .. t+steps`` (ancestors are mass-weighted
        means: :func:`hrn_pyg.data.graph.object_centres` gives the roots).

    **Shapes:** initial state over ``N`` nodes, ``L`` of them leaves; output ``(k, steps, L, 3)``.
    """
    check_sampling_args(k, steps, rate)
    if seed is not None:
        if generator is not None:
            raise ValueError("sample: pass seed= or generator=, not both")
        generator = torch.Generator().manual_seed(int(seed))
    if fixed_shape is not None and sleep is not None and sleep.enabled:
        raise ValueError("fixed_shape steps run every object: pass sleep=None with them")
    _check_state(initial_state)
    modules = _check_modules(model, modules)
    graph = copy.copy(initial_state)  # new stores: deleting and moving below leave the caller's
    for name in WINDOW_ONLY_FIELDS:
        if name in graph[NODE]:
            del graph[NODE][name]
    graph = graph.to(model_device(model))
    store = graph[NODE]
    forces_of_copies = copies_forces(forces, graph, steps, k)
    n = store.num_nodes
    leaf_index = torch.nonzero(store.is_leaf).flatten()
    batched = replicate(graph, k)
    masks_fn = make_masks_fn(model, k, rate, generator, modules)
    if fixed_shape is not None:
        result = fixed_shape_rollout(model, batched, steps, forces_of_copies, masks_fn, effects, fixed_shape,
                                     hold_failed=True)
        pos, failed_at = result.pos, result.failed_at
    else:
        with torch.no_grad():
            pos, failed_at = _rollout_holding_failed(model, batched, steps, forces_of_copies, masks_fn, sleep,
                                                     effects, k)
    futures = pos.reshape(steps, k, n, 3).index_select(2, leaf_index).transpose(0, 1).contiguous()
    if failed_at is not None and bool((failed_at < steps).any()):
        futures = mark_failed(futures, failed_at)
    return futures


#: what a failed future holds from the step it failed on
FAILED = float("nan")


def _rollout_holding_failed(model: HRN, batched: HeteroData, steps: int, forces: Tensor | None,
                            masks_fn: MasksFn | None, sleep: SleepConfig | None, effects: SceneEffects | None,
                            k: int) -> tuple[Tensor, Tensor]:
    """The rollout of the ``k`` copies with failed copies held (:mod:`hrn_pyg.sim.rules`):
    positions ``[steps, k N, 3]`` and ``[k]`` long, the step each copy failed at (``steps``: never)."""
    out, failed_at = [], torch.full((k,), steps, dtype=torch.long, device=batched[NODE].pos.device)
    for t, result in enumerate(iterate(model, batched, steps, forces, masks_fn, sleep, effects, hold_failed=True)):
        out.append(result.pos)
        if result.failed is not None:
            newly = result.failed[:k] & (failed_at == steps)
            failed_at = torch.where(newly, torch.full_like(failed_at, t), failed_at)
    return torch.stack(out), failed_at


def mark_failed(futures: Tensor, failed_at: Tensor) -> Tensor:
    """``futures`` ``[k, steps, L, 3]`` with every future that failed (``failed_at`` ``[k]``: the
    step of its first non-finite prediction, ``steps`` if none) set to NaN from that step on, and
    one warning line saying how many failed."""
    k, steps = futures.shape[:2]
    bad = failed_at < steps
    count = int(bad.sum())
    at = ", ".join(str(int(t) + 1) for t in failed_at[bad].tolist())
    warnings.warn(f"{count} of {k} sampled futures failed (not finite from step {at}); the others are "
                  "complete, the failed ones NaN from then on", RuntimeWarning, stacklevel=3)
    after = torch.arange(steps, device=futures.device)[None, :] >= failed_at[:, None]  # [k, steps]
    return torch.where(after[:, :, None, None], torch.full_like(futures, FAILED), futures)
