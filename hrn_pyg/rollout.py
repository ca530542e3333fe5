"""The one rollout loop of hrn_pyg, used by training, evaluation, sampling and the environment.

A model step has three named stages, each a function testable on its own (after GNS's
``learned_simulator.py``):

1. :func:`build_inputs`: per-particle state features and edge offsets, normalised with the
   model's :class:`~hrn_pyg.nn.normalizer.Normalizer` (no absolute horizontal position enters);
2. :func:`run_network`: the :class:`~hrn_pyg.nn.hrn.HRN` pass, optionally with dropout masks;
3. :func:`decode`: inverse normalisation to local velocities (parent frame, roots global), one
   scatter down the tree to global velocities, integration ``x_{t+1} = x_t + v_{t+1}`` of the
   leaves, ancestor positions re-derived from the leaves; static particles never move.

:func:`step` chains them and also returns the next graph (positions shifted, collision edges
recomputed at the new positions); :func:`unroll` and :func:`rollout` feed predictions back,
letting objects at rest sleep unless told not to (``sleep=``, :mod:`hrn_pyg.sleeping`).
Everything is differentiable in the positions (the edge sets are not), and vectorised over
particles.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Mapping
from typing import NamedTuple

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.data.graph import (
    ANCESTOR_TO_DESCENDANT,
    CHILD_TO_PARENT,
    COLLISION,
    LEAF_TO_ANCESTOR,
    MATERIALS,
    NODE,
    WITHIN_SIBLINGS,
    leaf_collision_edges,
    leaf_to_ancestor_mean,
    set_state,
)
from hrn_pyg.effects import SceneEffects, plan_effects
from hrn_pyg.nn.hrn import HRN, HRNInputs, state_features
from hrn_pyg.nn.rigid import fit_rigid_motion
from hrn_pyg.nn.state import to_global_velocity, to_local_velocity
from hrn_pyg.sleep_config import DEFAULT_SLEEP, SleepConfig


#: column of the rigid material in ``graph['particle'].material``
RIGID = MATERIALS.index("rigid")

#: ``masks_fn(step_index, graph) -> {module: [B, H] mask} | None``, called once per step
MasksFn = Callable[[int, HeteroData], Mapping[str, Tensor] | None]


class Step(NamedTuple):
    """Result of one model step.

    Attributes:
        pos: ``[N, 3]`` positions at ``t+1`` (leaves integrated, ancestors derived).
        local_velocity: ``[N, 3]`` predicted velocity in the parent's frame (roots global).
        velocity: ``[N, 3]`` predicted global velocity (local summed down the tree).
        graph: the graph at ``t+1``: ``prev_prev_pos, prev_pos, pos = x_{t-1}, x_t, x_{t+1}``,
            force zero, collision edges of ``x_{t+1}`` (an asleep node's three positions are
            all its held position).
        asleep: ``[N]`` bool, the nodes held still in this step because their object was asleep
            (:mod:`hrn_pyg.sleeping`); None when sleeping is off.
    """

    pos: Tensor
    local_velocity: Tensor
    velocity: Tensor
    graph: HeteroData
    asleep: Tensor | None = None


def _check_finite(name: str, value: Tensor) -> None:
    if not bool(torch.isfinite(value).all()):
        raise ValueError(f"{name} contains NaN or infinite values")


def _require_state(graph: HeteroData, check: bool = True) -> None:
    """The three positions a step reads are present (and finite, unless ``check=False``)."""
    store = graph[NODE]
    for name in ("pos", "prev_pos", "prev_prev_pos"):
        if name not in store:
            raise ValueError(f"graph['{NODE}'] has no '{name}': set the state first (hrn_pyg.data.graph.set_state)")
        if check:
            _check_finite(f"graph['{NODE}'].{name}", store[name])


def _node_force(graph: HeteroData, force: Tensor | None, check: bool = True) -> Tensor:
    store = graph[NODE]
    if force is None:
        force = store.force if "force" in store else torch.zeros_like(store.pos)
        if check:
            _check_finite(f"graph['{NODE}'].force", force)
        return force
    if force.shape != store.pos.shape:
        raise ValueError(f"force must be [N, 3] = {tuple(store.pos.shape)}, got {tuple(force.shape)}")
    if check:
        _check_finite("force", force)
    return torch.where(store.is_leaf.unsqueeze(-1), force, torch.zeros_like(force))


def build_inputs(
    model: HRN,
    graph: HeteroData,
    force: Tensor | None = None,
    force_active: bool | None = None,
    check: bool = True,
) -> HRNInputs:
    r"""Stage 1: normalised network inputs of the graph's current state.

    States :math:`s(t)` from :math:`v_t = x_t - x_{t-1}` and :math:`z_t`, :math:`s(t-1)` from
    :math:`v_{t-1} = x_{t-1} - x_{t-2}` and :math:`z_{t-1}`, plus the static attributes;
    positions divided by the length scale (edges only see differences); force divided by its
    scale. ``force`` ``[N, 3]`` overrides ``graph['particle'].force`` (zero on ancestors); the
    collision edges are read from the graph as they are. ``force_active`` (optional) says
    whether the force is nonzero, so the network need not ask (:mod:`hrn_pyg.effects`).
    ``check=False`` skips the finite checks of the positions and the force (each a host read
    on a GPU): for a caller that has checked them already, as :func:`unroll` does.
    """
    _require_state(graph, check)
    store = graph[NODE]
    norm, config = model.normalizer, model.config
    pos, prev, prev2 = store.pos, store.prev_pos, store.prev_prev_pos
    static = (store.mass, store.material, store.stiffness, store.depth, store.is_leaf, store.is_root)
    ground = config.collision_radius if config.ground_contact else None
    state = state_features(norm, pos - prev, pos[:, 2:], *static, ground_radius=ground)
    prev_state = state_features(norm, prev - prev2, prev[:, 2:], *static, ground_radius=ground)
    rest_pos = None
    if config.rest_offsets:
        # a graph without a recorded rest shape takes its current shape as the rest shape
        rest_pos = norm.length(store.rest_pos if "rest_pos" in store else pos)
    batch = store.batch if "batch" in store else torch.zeros(pos.size(0), dtype=torch.long, device=pos.device)
    empty = torch.empty(2, 0, dtype=torch.long, device=pos.device)
    collision = graph[COLLISION].edge_index if COLLISION in graph.edge_types else empty
    return HRNInputs(
        state=state,
        prev_state=prev_state,
        pos=norm.length(pos),
        force=norm.force(_node_force(graph, force, check)),
        is_static=store.is_static,
        is_root=store.is_root,
        batch=batch,
        collision=collision,
        leaf_to_ancestor=graph[LEAF_TO_ANCESTOR].edge_index,
        within_siblings=graph[WITHIN_SIBLINGS].edge_index,
        ancestor_to_descendant=graph[ANCESTOR_TO_DESCENDANT].edge_index,
        rest_pos=rest_pos,
        force_active=force_active,
    )


def run_network(model: HRN, inputs: HRNInputs, masks: Mapping[str, Tensor] | None = None) -> Tensor:
    """Stage 2: the HRN's normalised output ``[N, 3]`` (change of local velocity)."""
    return model(inputs, masks)


def decode(
    model: HRN, graph: HeteroData, out: Tensor, objects: tuple[Tensor, int] | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    r"""Stage 3: normalised output -> ``(pos_{t+1}, local_velocity, velocity)``, each ``[N, 3]``.

    .. math::
        v^{loc}_i(t+1) &= v^{loc}_i(t) + \mu_{r(i)} + \sigma_{r(i)} \odot \hat u_i \\
        v_i(t+1) &= v^{loc}_i(t+1) + \sum_{a \in \mathrm{anc}(i)} v^{loc}_a(t+1) \\
        x_l(t+1) &= x_l(t) + v_l(t+1) \ \text{(leaves)}, \qquad
        x_a(t+1) = \textstyle\sum_{l} m_l x_l(t+1) / m_a \ \text{(ancestors)}

    Static particles get zero velocity, so their positions are returned unchanged. With
    ``model.config.rigid_fit`` the leaves of every rigid object then move by the one rigid
    transform that fits their predicted motion best (:func:`rigid_leaf_positions`), and that
    object's velocities are the fitted ones; ``objects`` is :func:`object_of` of ``graph`` when
    the caller has it (a rollout computes it once), else it is computed here (one host read).
    """
    store = graph[NODE]
    c2p = graph[CHILD_TO_PARENT].edge_index
    local_now = to_local_velocity(store.pos - store.prev_pos, c2p)
    local = local_now + model.normalizer.denormalize_target(out, store.is_root)
    local = torch.where(store.is_static.unsqueeze(-1), torch.zeros_like(local), local)
    velocity = to_global_velocity(local, graph[LEAF_TO_ANCESTOR].edge_index)
    pos = leaf_to_ancestor_mean(store.pos + velocity, graph)
    if model.config.rigid_fit:
        pos = leaf_to_ancestor_mean(rigid_leaf_positions(graph, pos, objects), graph)
        rigid = store.material[:, RIGID].bool().unsqueeze(-1)
        velocity = torch.where(rigid, pos - store.pos, velocity)
        local = torch.where(rigid, to_local_velocity(velocity, c2p), local)
    return pos, local, velocity


def rigid_leaf_positions(
    graph: HeteroData, pred_pos: Tensor, objects: tuple[Tensor, int] | None = None
) -> Tensor:
    """``pred_pos`` ``[N, 3]`` with the leaves of each rigid object replaced by the best rigid
    motion of their current positions (:func:`hrn_pyg.nn.rigid.fit_rigid_motion`); other rows are
    returned unchanged (ancestor rows still need re-deriving).

    An object (of one batch copy) is identified by its root node (:func:`object_of`, one fit per
    object rather than per node); rows other than rigid leaves enter the fit with zero weight,
    and so do static rows (a sleeping object's leaf in a sub-graph, :mod:`hrn_pyg.sleeping`, is
    rigid and static). ``objects``: :func:`object_of` of ``graph``, if the caller has it.
    """
    store = graph[NODE]
    rigid_leaf = store.is_leaf & store.material[:, RIGID].bool() & ~store.is_static
    weight = torch.where(rigid_leaf, store.mass[:, 0], torch.zeros_like(store.mass[:, 0]))
    group, count = object_of(graph) if objects is None else objects
    fitted = fit_rigid_motion(store.pos, pred_pos, weight, group, count)
    return torch.where(rigid_leaf.unsqueeze(-1), fitted, pred_pos)


def object_of(graph: HeteroData) -> tuple[Tensor, int]:
    """``([N] long, R)``: every node's object ``0..R-1``, numbered in the order of the objects'
    root nodes (:func:`root_of`; a node without ancestors in the graph is an object of its own),
    and the number of objects ``R`` (one host read)."""
    root = root_of(graph)
    is_own_root = root == torch.arange(root.numel(), device=root.device)
    rank = torch.cumsum(is_own_root.long(), 0) - 1
    return rank[root], int(is_own_root.sum())


def root_of(graph: HeteroData) -> Tensor:
    """``[N]`` long: the root node of every node's tree (a root is its own, and so is a node
    without ancestors in the graph, e.g. a sleeping object's leaf in a sub-graph of
    :mod:`hrn_pyg.sleeping`)."""
    store = graph[NODE]
    node, ancestor = graph[LEAF_TO_ANCESTOR].edge_index
    index = torch.arange(store.num_nodes, device=node.device)
    candidate = torch.where(store.is_root[ancestor], ancestor, torch.full_like(ancestor, -1))
    roots = torch.full_like(index, -1).scatter_reduce(0, node, candidate, reduce="amax")
    return torch.where(store.is_root | (roots < 0), index, roots)


def target_output(model: HRN, graph: HeteroData, next_pos: Tensor) -> Tensor:
    """Inverse of :func:`decode`: the normalised network output that would produce ``next_pos``.

    ``next_pos`` ``[N, 3]`` must have ancestors derived from its leaves. Useful as a regression
    target and to test the decoder; ``[N, 3]``.
    """
    store = graph[NODE]
    c2p = graph[CHILD_TO_PARENT].edge_index
    delta = to_local_velocity(next_pos - store.pos, c2p) - to_local_velocity(store.pos - store.prev_pos, c2p)
    return model.normalizer.normalize_target(delta, store.is_root)


def step(
    model: HRN,
    graph: HeteroData,
    force: Tensor | None = None,
    masks: Mapping[str, Tensor] | None = None,
    *,
    force_active: bool | None = None,
    collisions: bool = True,
    objects: tuple[Tensor, int] | None = None,
    check: bool = True,
) -> Step:
    """One model step: build inputs, run the network, decode, and advance the graph.

    Args:
        model: the HRN (its config gives the collision radius of the next graph).
        graph: current state (``pos``, ``prev_pos``, ``prev_prev_pos``; collision edges of ``pos``).
        force: ``[N, 3]`` external force during ``t -> t+1``; None uses ``graph['particle'].force``
            (zero if absent).
        masks: dropout masks ``{module: [B, H]}``; None is the deterministic model.
        force_active, collisions: the step's part of an :class:`~hrn_pyg.effects.EffectPlan`:
            whether the force is nonzero (None: the network checks), and whether the next
            graph gets a collision search (False: no collision edges).
        objects: :func:`object_of` of ``graph`` if the caller has it (None: computed here).
        check: check the graph's positions and the force for NaN / inf first (``False``: the
            caller has; the new positions are always checked).
    """
    inputs = build_inputs(model, graph, force, force_active, check)
    out = run_network(model, inputs, masks)
    pos, local, velocity = decode(model, graph, out, objects)
    nxt = advance(graph, pos, model.config.collision_radius if collisions else None)
    return Step(pos=pos, local_velocity=local, velocity=velocity, graph=nxt)


def advance(
    graph: HeteroData,
    pos: Tensor,
    radius: float | None,
    held: Tensor | None = None,
    edges: Tensor | None = None,
) -> HeteroData:
    """The graph at ``t+1``: a shallow copy of ``graph`` (at ``t``) with ``prev_prev_pos, prev_pos,
    pos = x_{t-1}, x_t, x_{t+1}``, force zero and the collision edges of ``x_{t+1}``.

    What :func:`hrn_pyg.data.graph.set_state` gives for a graph whose ancestor rows are already
    derived (every graph of a rollout, and ``pos`` from :func:`decode`), without re-deriving
    them: the rows are moved, not recomputed, so they stay bit for bit. ``held`` ``[N]`` bool
    (optional): nodes held still in this step (:mod:`hrn_pyg.sleeping`), whose
    ``prev_prev_pos`` becomes ``x_t`` so they start from rest when they wake. ``edges``
    ``(2, |E_C|)`` (optional): the collision edges of ``x_{t+1}`` when the caller has them
    (the sleeping step searches only where something moved); else all leaves are searched.

    **Shapes:** pos ``(N, 3)``; returns a graph with ``collision`` ``(2, |E_C|)``.
    """
    _check_finite("advance: pos", pos)
    store = graph[NODE]
    out = copy.copy(graph)
    part = out[NODE]
    part.prev_prev_pos = store.prev_pos if held is None else torch.where(held.unsqueeze(-1), store.pos, store.prev_pos)
    part.prev_pos = store.pos
    part.pos = pos
    part.force = torch.zeros_like(pos)
    out[COLLISION].edge_index = leaf_collision_edges(out, pos, radius) if edges is None else edges
    return out


def _check_forces(graph: HeteroData, steps: int, forces: Tensor | None) -> None:
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    n = graph[NODE].num_nodes
    if forces is not None and (forces.dim() != 3 or forces.shape[0] < steps or forces.shape[1:] != (n, 3)):
        raise ValueError(f"forces must be [steps>={steps}, {n}, 3], got {tuple(forces.shape)}")
    if forces is not None:
        _check_finite("forces", forces[:steps])


def unroll(
    model: HRN,
    graph: HeteroData,
    steps: int,
    forces: Tensor | None = None,
    masks_fn: MasksFn | None = None,
    sleep: SleepConfig | None = DEFAULT_SLEEP,
    effects: SceneEffects | None = None,
) -> list[Step]:
    """Feed the model its own predictions for ``steps`` steps; every :class:`Step` is kept.

    The initial graph's collision edges are recomputed with the model's radius first, so the
    first step sees the same kind of edges as the later ones. ``forces`` ``[steps, N, 3]`` is the
    external force of each step; None means no external force at any step (the graph's
    ``force`` attribute is not reused). ``masks_fn(t, graph)`` gives the dropout masks of step
    ``t`` (None: deterministic); it always sees the whole graph. ``sleep`` lets objects at rest
    sleep (:mod:`hrn_pyg.sleeping`; an object the start's history shows at rest starts asleep,
    ``SleepConfig.start_from_history``), on by default
    (:data:`~hrn_pyg.sleep_config.DEFAULT_SLEEP`); ``sleep=None`` or ``enabled=False`` runs
    every object at every step (the network alone: what training and ``hrn-pyg evaluate`` use).
    ``effects`` is what the scene declares it needs (:class:`~hrn_pyg.effects.SceneEffects`;
    None: what the data show): before the first step it becomes an
    :class:`~hrn_pyg.effects.EffectPlan`, so no step asks the device whether its force is zero,
    and a scene in which nothing can touch gets no collision search at all.
    """
    _check_forces(graph, steps, forces)
    plan = plan_effects(graph, steps, forces, effects)
    store = graph[NODE]
    radius = model.config.collision_radius if plan.collisions else None
    _require_state(graph)  # once here, so no step has to
    graph = set_state(graph, store.prev_prev_pos, store.prev_pos, store.pos, radius=radius)
    # the tree does not change during a rollout: its objects are found once (one host read)
    objects = object_of(graph) if model.config.rigid_fit else None
    sleeping = sleep is not None and sleep.enabled
    if sleeping:
        from hrn_pyg import sleeping as sleep_module  # imports this module

        objs = sleep_module.objects(graph)
        objects = (objs.of_node, objs.count)
        sleep_state = (sleep_module.state_from_history(sleep, graph, objs) if sleep.start_from_history
                       else sleep_module.initial_state(objs))
    out: list[Step] = []
    for t in range(steps):  # time steps; each step is vectorised over particles
        force = forces[t] if forces is not None else torch.zeros_like(store.pos)
        masks = masks_fn(t, graph) if masks_fn is not None else None
        active = plan.force_active[t]
        if sleeping:
            result, sleep_state = sleep_module.sleeping_step(model, graph, force, masks, sleep_state, objs, sleep,
                                                             force_active=active, collisions=plan.collisions,
                                                             check=False)
        else:
            result = step(model, graph, force, masks, force_active=active, collisions=plan.collisions,
                          objects=objects, check=False)
        out.append(result)
        graph = result.graph
    return out


def rollout(
    model: HRN,
    graph: HeteroData,
    steps: int,
    forces: Tensor | None = None,
    masks_fn: MasksFn | None = None,
    sleep: SleepConfig | None = DEFAULT_SLEEP,
    effects: SceneEffects | None = None,
) -> Tensor:
    """Positions of all nodes over ``steps`` predicted steps, ``[steps, N, 3]`` (``x_{t+1..t+steps}``).

    See :func:`unroll` for the arguments.
    """
    return torch.stack([s.pos for s in unroll(model, graph, steps, forces, masks_fn, sleep, effects)])
