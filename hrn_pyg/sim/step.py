"""One learned step of the HRN, written once: every rollout, sampler and environment calls it.

Three stages, each testable on its own (after GNS's ``learned_simulator.py``):

1. :func:`build_inputs`: state features and edge offsets, normalised with the model's
   :class:`~hrn_pyg.nn.normalizer.Normalizer`;
2. :func:`run_network`: the :class:`~hrn_pyg.nn.hrn.HRN` pass, optionally with dropout masks;
3. :func:`decode`: local velocities (parent frame, roots global) summed down the tree,
   integration ``x_{t+1} = x_t + v_{t+1}`` of the leaves, ancestors re-derived; static
   particles never move.

:func:`predict` is the only place the stages are chained; :func:`step` adds :func:`advance`,
the next graph. What a caller knows ahead travels as one :class:`~hrn_pyg.nn.hrn.StepOptions`.
Differentiable in the positions (the edge sets are not) and vectorised over particles.
"""

from __future__ import annotations

import copy
import dataclasses
import warnings
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.data.graph import (
    ANCESTOR_TO_DESCENDANT,
    CHILD_TO_PARENT,
    COLLISION,
    LEAF_TO_ANCESTOR,
    NODE,
    RIGID,
    WITHIN_SIBLINGS,
    leaf_collision_edges,
    leaf_to_ancestor_mean,
    node_pitch,
)
from hrn_pyg.nn.gns import GNS
from hrn_pyg.nn.hrn import (
    HRN,
    HierarchyConstants,
    HRNInputs,
    StepOptions,
    check_hierarchy,
    state_features,
    within_siblings_of,
)
from hrn_pyg.nn.hrn import hierarchy_constants as nn_hierarchy_constants
from hrn_pyg.nn.pitch import collision_radius_of, is_pitch_aware, node_radius, pitch_column, pitch_scale
from hrn_pyg.nn.rigid import fit_rigid_motion
from hrn_pyg.nn.state import to_global_velocity, to_local_velocity
from hrn_pyg.sim.copy_groups import copy_groups, group_inputs
from hrn_pyg.utils.checks import check_finite

#: ``masks_fn(step_index, graph) -> {module: [B, H] mask} | None``, called once per step
MasksFn = Callable[[int, HeteroData], Mapping[str, Tensor] | None]
#: ``search(graph, pos) -> [2, E_C]``: the collision edges of ``graph``'s leaves at ``pos``
CollisionSearch = Callable[[HeteroData, Tensor], Tensor]


class Prediction(NamedTuple):
    """What the network predicts for one step (:func:`predict`), each ``[N, 3]``.

    Attributes:
        pos: positions at ``t+1`` (leaves integrated, ancestors derived).
        local_velocity: velocity in the parent's frame (roots global).
        velocity: global velocity (local summed down the tree).
        prev_pos: ``x_t`` as the next graph holds it: ``pos`` moved by a ground lift that is not a
            motion (``HRNConfig.ground_lift_velocity`` False); None: the graph's ``pos``.
    """

    pos: Tensor
    local_velocity: Tensor
    velocity: Tensor
    prev_pos: Tensor | None = None


def non_finite_copies(pos: Tensor, copy: Tensor, count: int) -> Tensor:
    """``[count]`` bool: the batch copies (``copy`` ``[N]`` long, each row's) with a row of ``pos``
    ``[N, 3]`` that is not finite; no data-dependent size (a fixed-shape step may call it)."""
    bad_row = (~torch.isfinite(pos).all(dim=-1)).to(pos.dtype)
    return torch.zeros(count, dtype=pos.dtype, device=pos.device).index_add(0, copy, bad_row) > 0


def held_at_current(graph: HeteroData, prediction: Prediction, held: Tensor) -> Prediction:
    """``prediction`` with the rows of ``held`` ``[N]`` bool kept at :math:`x_t` (the graph's
    ``pos``) with zero velocity; their ``prev_pos`` too, where the prediction carries one."""
    held = held.unsqueeze(-1)
    pos = graph[NODE].pos
    zero = torch.zeros_like(pos)
    since = None if prediction.prev_pos is None else torch.where(held, pos, prediction.prev_pos)
    return Prediction(torch.where(held, pos, prediction.pos), torch.where(held, zero, prediction.local_velocity),
                      torch.where(held, zero, prediction.velocity), since)


class Step(NamedTuple):
    """Result of one model step.

    Attributes:
        pos, local_velocity, velocity: ``[N, 3]``, as in :class:`Prediction`.
        graph: the graph at ``t+1`` (:func:`advance`).
        asleep: ``[N]`` bool, nodes held still this step (:mod:`hrn_pyg.sim.sleeping`); None when
            sleeping is off.
        failed: ``[R]`` bool, batch copies that have failed (a non-finite prediction, held since)
            by this step (:class:`~hrn_pyg.sim.rules.StepRules`); None when failing is an error.
    """

    pos: Tensor
    local_velocity: Tensor
    velocity: Tensor
    graph: HeteroData
    asleep: Tensor | None = None
    failed: Tensor | None = None


def require_state(graph: HeteroData, check: bool = True) -> None:
    """The three positions a step reads are present (and finite, unless ``check=False``)."""
    store = graph[NODE]
    for name in ("pos", "prev_pos", "prev_prev_pos"):
        if name not in store:
            raise ValueError(f"graph['{NODE}'] has no '{name}': set the state first (hrn_pyg.data.graph.set_state)")
        if check:
            check_finite(f"graph['{NODE}'].{name}", store[name])


def node_force(graph: HeteroData, force: Tensor | None, check: bool = True) -> Tensor:
    """The step's external force ``[N, 3]``: ``force`` with ancestor rows zeroed, or the graph's
    own ``force`` (zero if absent) when ``force`` is None."""
    store = graph[NODE]
    if force is None:
        force = store.force if "force" in store else torch.zeros_like(store.pos)
        if check:
            check_finite(f"graph['{NODE}'].force", force)
        return force
    if force.shape != store.pos.shape:
        raise ValueError(f"force must be [N, 3] = {tuple(store.pos.shape)}, got {tuple(force.shape)}")
    if check:
        check_finite("force", force)
    return torch.where(store.is_leaf.unsqueeze(-1), force, torch.zeros_like(force))


def _with_legacy(options: StepOptions, legacy: Mapping[str, Any], where: str) -> StepOptions:
    """``options`` with the deprecated one-keyword options (fields of
    :class:`~hrn_pyg.nn.hrn.StepOptions`) folded in, with a DeprecationWarning; TypeError for a
    keyword that is no option or ``options`` of another type."""
    if not isinstance(options, StepOptions):
        raise TypeError(f"{where}: options must be a StepOptions, got {type(options).__name__}")
    if not legacy:
        return options
    unknown = sorted(set(legacy) - {f.name for f in dataclasses.fields(StepOptions)})
    if unknown:
        raise TypeError(f"{where}() got an unexpected keyword argument {unknown[0]!r}")
    names = ", ".join(f"{k}=" for k in legacy)
    warnings.warn(f"{where}({names}) is deprecated: pass options=StepOptions({names}...) "
                  "(hrn_pyg.nn.hrn.StepOptions)", DeprecationWarning, stacklevel=3)
    return dataclasses.replace(options, **legacy)


def build_inputs(
    model: HRN,
    graph: HeteroData,
    force: Tensor | None = None,
    options: StepOptions = StepOptions(),
    **legacy: Any,
) -> HRNInputs:
    r"""Stage 1: normalised network inputs of the graph's current state.

    States :math:`s(t)` from :math:`v_t = x_t - x_{t-1}` and :math:`z_t`, :math:`s(t-1)` from
    :math:`v_{t-1}` and :math:`z_{t-1}`, plus the static attributes; positions over the length
    scale; force over its scale. ``force`` ``[N, 3]`` overrides ``graph['particle'].force``. A
    pitch-aware model (:mod:`hrn_pyg.nn.pitch`) reads node :math:`i` at :math:`s_i = p_i / p_{ref}`:
    positions divided by :math:`s_i`, ground-contact radius :math:`r_c s_i`, last column
    :math:`\log_2 s_i`. ``options.check=False`` skips the finite checks (host reads).
    """
    options = _with_legacy(options, legacy, "build_inputs")
    check = options.check
    require_state(graph, check)
    store = graph[NODE]
    norm, config = model.normalizer, model.config
    pos, prev, prev2 = store.pos, store.prev_pos, store.prev_prev_pos
    static = (store.mass, store.material, store.stiffness, store.depth, store.is_leaf, store.is_root)
    ground = config.collision_radius if config.ground_contact else None
    pitch = scale = None
    if is_pitch_aware(config):
        node_scale = pitch_scale(graph, config.reference_pitch)  # [N] float64
        pitch = pitch_column(node_scale, pos.dtype)
        scale = node_scale.to(pos.dtype).unsqueeze(-1)  # [N, 1]
        if config.ground_contact:
            ground = node_radius(config, node_scale, pos.dtype)
    state = state_features(norm, pos - prev, pos[:, 2:], *static, ground_radius=ground, pitch=pitch)
    prev_state = state_features(norm, prev - prev2, prev[:, 2:], *static, ground_radius=ground, pitch=pitch)

    def geometric(x: Tensor) -> Tensor:  # positions as the edge modules read them
        x = norm.length(x)
        return x if scale is None else x / scale

    rest_pos = None
    if config.rest_offsets:
        # a graph without a recorded rest shape takes its current shape as the rest shape
        rest = store.rest_pos if "rest_pos" in store else pos
        known = options.hierarchy
        if (getattr(config, "corotated_rest", False) and "rest_pos" in store
                and (known is None or known.rest_offset is None)  # constants given: nothing turns
                and bool(_deformable_leaves(graph).any())):  # a rigid-only (sub-)graph: nothing to turn
            rest = corotated_rest_positions(graph, rest, pos, options.objects)
        rest_pos = geometric(rest)
    batch = store.batch if "batch" in store else torch.zeros(pos.size(0), dtype=torch.long, device=pos.device)
    empty = torch.empty(2, 0, dtype=torch.long, device=pos.device)
    collision = graph[COLLISION].edge_index if COLLISION in graph.edge_types else empty
    within_siblings = graph[WITHIN_SIBLINGS].edge_index
    if not getattr(config, "rigid_leaf_siblings", True):
        known = options.hierarchy
        if known is not None and known.within_siblings is not None:
            within_siblings = known.within_siblings  # selected once for the rollout
        else:
            within_siblings = within_siblings_of(within_siblings, store.is_leaf & store.material[:, RIGID].bool())
    inputs = HRNInputs(
        state=state,
        prev_state=prev_state,
        pos=geometric(pos),
        force=norm.force(node_force(graph, force, check)),
        is_static=store.is_static,
        is_root=store.is_root,
        batch=batch,
        collision=collision,
        leaf_to_ancestor=graph[LEAF_TO_ANCESTOR].edge_index,
        within_siblings=within_siblings,
        ancestor_to_descendant=graph[ANCESTOR_TO_DESCENDANT].edge_index,
        rest_pos=rest_pos,
        options=options,
    )
    if options.hierarchy is not None:
        check_hierarchy(options.hierarchy, inputs)
        inputs = inputs._replace(hierarchy=options.hierarchy)
    return inputs


def hierarchy_constants(model: HRN, graph: HeteroData) -> HierarchyConstants | None:
    """The :class:`~hrn_pyg.nn.hrn.HierarchyConstants` of ``graph`` for ``model`` (None for another
    network), valid for every graph sharing its hierarchy and rest shape. Without a recorded rest
    shape, or with a moving soft body or cloth under ``corotated_rest``, only the degrees."""
    if not isinstance(model, HRN):
        return None
    inputs = build_inputs(model, graph, options=StepOptions(check=False, force_active=False))
    constant_rest = model.config.rest_offsets and "rest_pos" in graph[NODE]
    if constant_rest and getattr(model.config, "corotated_rest", False):
        constant_rest = not bool(_deformable_leaves(graph).any())
    return nn_hierarchy_constants(inputs, constant_rest)


def _deformable_leaves(graph: HeteroData) -> Tensor:
    """``[N]`` bool: the moving leaves of soft bodies and cloth."""
    store = graph[NODE]
    return store.is_leaf & ~store.is_static & ~store.material[:, RIGID].bool()


def corotated_rest_positions(graph: HeteroData, rest: Tensor, pos: Tensor,
                             objects: tuple[Tensor, int] | None = None) -> Tensor:
    r"""The rest shape ``rest`` ``[N, 3]`` with every soft body and cloth turned onto its current
    leaves ``pos`` ``[N, 3]`` (:attr:`~hrn_pyg.nn.hrn.HRNConfig.corotated_rest`).

    .. math::
        \bar x'_i = R_o (\bar x_i - \bar c_o) + c_o, \qquad
        R_o = \arg\min_{R \in SO(3)} \sum_{l \in o} m_l \lVert R (\bar x_l - \bar c_o) - (x_l - c_o) \rVert^2

    for every leaf :math:`i` of a soft or cloth object :math:`o` (:math:`\bar c_o, c_o` its
    mass-weighted rest and current centres; :func:`~hrn_pyg.nn.rigid.fit_rigid_motion`); ancestors
    re-derived, rigid and static rows kept. ``objects``: :func:`object_of` of ``graph``, if known.
    """
    store = graph[NODE]
    deformable = _deformable_leaves(graph)
    weight = torch.where(deformable, store.mass[:, 0], torch.zeros_like(store.mass[:, 0]))
    group, count = object_of(graph) if objects is None else objects
    turned = fit_rigid_motion(rest, pos, weight, group, count)
    return leaf_to_ancestor_mean(torch.where(deformable.unsqueeze(-1), turned, rest), graph)


def run_network(model: HRN, inputs: HRNInputs, masks: Mapping[str, Tensor] | None = None) -> Tensor:
    """Stage 2: the HRN's normalised output ``[N, 3]`` (change of local velocity). Many copies on the
    CPU run as cache-sized groups (:mod:`hrn_pyg.sim.copy_groups`), with the same answer."""
    groups = copy_groups(inputs) if isinstance(model, HRN) else None
    if groups is not None:
        parts = group_inputs(inputs, dict(masks or {}), groups, passes=model.mask_rows(1))
        if parts is not None:
            return torch.cat([model(part, part_masks) for part, part_masks in parts], dim=0)
    return model(inputs, masks)


def decode(
    model: HRN, graph: HeteroData, out: Tensor, objects: tuple[Tensor, int] | None = None
) -> Prediction:
    r"""Stage 3: normalised output -> the :class:`Prediction`, each ``[N, 3]``.

    .. math::
        v^{loc}_i(t+1) &= v^{loc}_i(t) + \mu_{r(i)} + \sigma_{r(i)} \odot \hat u_i \\
        v_i(t+1) &= v^{loc}_i(t+1) + \sum_{a \in \mathrm{anc}(i)} v^{loc}_a(t+1) \\
        x_l(t+1) &= x_l(t) + v_l(t+1) \ \text{(leaves)}, \qquad
        x_a(t+1) = \textstyle\sum_{l} m_l x_l(t+1) / m_a \ \text{(ancestors)}

    Static particles do not move. A :class:`~hrn_pyg.nn.gns.GNS` predicts accelerations instead
    (:func:`integrate_acceleration`). Then, per the config: ``rigid_fit``
    (:func:`rigid_leaf_positions`) and ``ground_projection`` (:func:`ground_projected_positions`).
    ``objects``: :func:`object_of` of ``graph``, if known (else one host read).
    """
    store = graph[NODE]
    c2p = graph[CHILD_TO_PARENT].edge_index
    if isinstance(model, GNS):
        pos, local, velocity = integrate_acceleration(model, graph, out)
    else:
        local_now = to_local_velocity(store.pos - store.prev_pos, c2p)
        local = local_now + model.normalizer.denormalize_target(out, store.is_root)
        local = torch.where(store.is_static.unsqueeze(-1), torch.zeros_like(local), local)
        velocity = to_global_velocity(local, graph[LEAF_TO_ANCESTOR].edge_index)
        pos = leaf_to_ancestor_mean(store.pos + velocity, graph)
    if model.config.rigid_fit:
        from_rest = getattr(model.config, "rigid_fit_rest", False)
        pos = leaf_to_ancestor_mean(rigid_leaf_positions(graph, pos, objects, from_rest), graph)
        rigid = store.material[:, RIGID].bool().unsqueeze(-1)
        velocity = torch.where(rigid, pos - store.pos, velocity)
        local = torch.where(rigid, to_local_velocity(velocity, c2p), local)
    if getattr(model.config, "ground_projection", False):
        config = model.config
        return _lifted_above_ground(graph, Prediction(pos, local, velocity), objects,
                                    getattr(config, "ground_projection_rigid", True),
                                    getattr(config, "rigid_ground_depth", 0.0),
                                    getattr(config, "rigid_ground_speed", 0.0),
                                    getattr(config, "ground_lift_velocity", True),
                                    getattr(config, "rigid_ground_lift", 0.0))
    return Prediction(pos, local, velocity)


def _lifted_above_ground(graph: HeteroData, prediction: Prediction, objects: tuple[Tensor, int] | None,
                         rigid: bool = True, rigid_depth: float = 0.0, rigid_speed: float = 0.0,
                         lift_velocity: bool = True, rigid_lift: float = 0.0) -> Prediction:
    """``decode``'s prediction after :func:`ground_projected_positions`: with ``lift_velocity`` the
    lift is part of the velocity, else it moves ``x_t`` too (``prev_pos``)."""
    pos, local, velocity = prediction.pos, prediction.local_velocity, prediction.velocity
    group, count = object_of(graph) if objects is None else objects
    lifted = leaf_to_ancestor_mean(ground_projected_positions(graph, pos, (group, count), rigid, rigid_depth,
                                                              rigid_speed, rigid_lift), graph)
    if not lift_velocity:  # rows not lifted add an exact zero: their x_t stays bit for bit
        return Prediction(lifted, local, velocity, graph[NODE].pos + (lifted - pos))
    moved = (lifted != pos).any(-1)
    touched = torch.zeros(count, dtype=torch.long, device=pos.device).index_add_(0, group, moved.long()) > 0
    velocity = torch.where(moved.unsqueeze(-1), lifted - graph[NODE].pos, velocity)
    local = torch.where(touched[group].unsqueeze(-1), to_local_velocity(velocity, graph[CHILD_TO_PARENT].edge_index), local)
    return Prediction(lifted, local, velocity)


def ground_projected_positions(graph: HeteroData, pos: Tensor, objects: tuple[Tensor, int] | None = None,
                               rigid: bool = True, rigid_depth: float = 0.0, rigid_speed: float = 0.0,
                               rigid_lift: float = 0.0) -> Tensor:
    r"""``pos`` ``[N, 3]`` with every moving leaf on or above the ground plane :math:`z = 0`
    (a rigid object's leaves: on or above :math:`z = -\delta p`).

    .. math::
        d_i = \max(0, -z_i - \delta_i p_i), \qquad
        z_i \leftarrow z_i + \begin{cases} \max_{j \in o(i)} d_j & i \text{ a leaf of a rigid object } o(i) \\
                                         d_i & i \text{ a leaf of a soft body or cloth} \end{cases}

    Other rows are returned bit for bit (ancestors need re-deriving). :math:`\delta_i` is
    ``rigid_depth`` on rigid leaves and 0 elsewhere, :math:`p_i` the node's pitch
    (:func:`~hrn_pyg.data.graph.node_pitch`). With ``rigid_speed`` :math:`s > 0` a rigid object is
    lifted only while its leaves moved at most :math:`s\, p_j` this step; with ``rigid_lift``
    :math:`c > 0` a rigid object rises at most :math:`c\, p_i` in one step (one sunk deep climbs out
    over several steps instead of jumping, which would add :math:`m g` times the jump to its
    energy); ``rigid=False`` lifts only soft and cloth leaves. ``objects``: :func:`object_of` of
    ``graph``, if known.
    """
    store = graph[NODE]
    moving_leaf = store.is_leaf & ~store.is_static
    rigid_leaf = moving_leaf & store.material[:, RIGID].bool()
    under = -pos[:, 2]
    pitch = node_pitch(graph).to(pos.dtype) if rigid and (rigid_depth > 0 or rigid_speed > 0 or rigid_lift > 0) else None
    if rigid and rigid_depth > 0:
        under = torch.where(rigid_leaf, under - rigid_depth * pitch, under)
    depth = torch.where(moving_leaf, under.clamp_min(0.0), torch.zeros_like(pos[:, 2]))
    group, count = object_of(graph) if objects is None else objects
    deepest = torch.zeros(count, dtype=pos.dtype, device=pos.device).scatter_reduce(
        0, group, torch.where(rigid_leaf, depth, torch.zeros_like(depth)), "amax")
    if rigid and rigid_speed > 0:  # a rigid object moving faster than that in the step stays where it is
        moved = torch.where(rigid_leaf, (pos - store.pos).norm(dim=-1), torch.zeros_like(depth))
        fast = moved > rigid_speed * pitch
        fastest = torch.zeros(count, dtype=torch.bool, device=pos.device).scatter_reduce(0, group, fast, "amax")
        deepest = torch.where(fastest, torch.zeros_like(deepest), deepest)
    rigid_rise = deepest[group] if rigid else torch.zeros_like(depth)
    if rigid and rigid_lift > 0:
        rigid_rise = torch.minimum(rigid_rise, rigid_lift * pitch)
    lift = torch.where(rigid_leaf, rigid_rise, depth)
    return torch.where((lift > 0).unsqueeze(-1), pos + lift.unsqueeze(-1) * pos.new_tensor([0.0, 0.0, 1.0]), pos)


def integrate_acceleration(model: GNS, graph: HeteroData, out: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    r"""Stage 3 of a :class:`~hrn_pyg.nn.gns.GNS`: semi-implicit Euler, ``(pos_{t+1}, local_velocity,
    velocity)``, each ``[N, 3]``.

    .. math::
        v_l(t+1) = x_l(t) - x_l(t-1) + \mu_a + \sigma_a \odot \hat a_l, \qquad
        x_l(t+1) = x_l(t) + v_l(t+1)

    (zero on static leaves); ancestors are mass-weighted means of their leaves.
    """
    store = graph[NODE]
    leaf_velocity = store.pos - store.prev_pos + model.denormalize_acceleration(out)
    moving_leaf = (store.is_leaf & ~store.is_static).unsqueeze(-1)
    velocity = leaf_to_ancestor_mean(torch.where(moving_leaf, leaf_velocity, torch.zeros_like(leaf_velocity)), graph)
    pos = leaf_to_ancestor_mean(store.pos + velocity, graph)
    return pos, to_local_velocity(velocity, graph[CHILD_TO_PARENT].edge_index), velocity


def rigid_leaf_positions(
    graph: HeteroData, pred_pos: Tensor, objects: tuple[Tensor, int] | None = None, from_rest: bool = False
) -> Tensor:
    """``pred_pos`` ``[N, 3]`` with each rigid object's leaves replaced by the best rigid motion of
    their current positions (:func:`hrn_pyg.nn.rigid.fit_rigid_motion`), or of the rest shape with
    ``from_rest``; other rows unchanged (ancestors need re-deriving). One fit per object
    (:func:`object_of`); static rows weigh 0. ``objects``: :func:`object_of` of ``graph``, if known."""
    store = graph[NODE]
    rigid_leaf = store.is_leaf & store.material[:, RIGID].bool() & ~store.is_static
    weight = torch.where(rigid_leaf, store.mass[:, 0], torch.zeros_like(store.mass[:, 0]))
    group, count = object_of(graph) if objects is None else objects
    reference = store.rest_pos if from_rest and "rest_pos" in store else store.pos
    fitted = fit_rigid_motion(reference, pred_pos, weight, group, count)
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
    """``[N]`` long: the root node of every node's tree (a node without ancestors is its own)."""
    store = graph[NODE]
    node, ancestor = graph[LEAF_TO_ANCESTOR].edge_index
    index = torch.arange(store.num_nodes, device=node.device)
    candidate = torch.where(store.is_root[ancestor], ancestor, torch.full_like(ancestor, -1))
    roots = torch.full_like(index, -1).scatter_reduce(0, node, candidate, reduce="amax")
    return torch.where(store.is_root | (roots < 0), index, roots)


def target_output(model: HRN, graph: HeteroData, next_pos: Tensor) -> Tensor:
    """Inverse of :func:`decode`: the normalised output ``[N, 3]`` that would produce ``next_pos``
    ``[N, 3]`` (ancestors derived; a GNS: the normalised accelerations). A regression target."""
    store = graph[NODE]
    if isinstance(model, GNS):  # the leaves' normalised accelerations, zero on ancestor rows
        acceleration = model.normalize_acceleration(next_pos - 2.0 * store.pos + store.prev_pos)
        return torch.where(store.is_leaf.unsqueeze(-1), acceleration, torch.zeros_like(acceleration))
    c2p = graph[CHILD_TO_PARENT].edge_index
    delta = to_local_velocity(next_pos - store.pos, c2p) - to_local_velocity(store.pos - store.prev_pos, c2p)
    return model.normalizer.normalize_target(delta, store.is_root)


def predict(
    model: HRN,
    graph: HeteroData,
    force: Tensor | None = None,
    masks: Mapping[str, Tensor] | None = None,
    options: StepOptions = StepOptions(),
    **legacy: Any,
) -> Prediction:
    """The three stages of a step: :func:`build_inputs`, :func:`run_network`, :func:`decode`.

    Args:
        model: the HRN.
        graph: current state (``pos``, ``prev_pos``, ``prev_prev_pos``; collision edges of ``pos``).
        force: ``[N, 3]`` external force during ``t -> t+1``; None: ``graph['particle'].force``.
        masks: dropout masks ``{module: [B, H]}``; None is the deterministic model.
        options: what the caller knows ahead (:class:`~hrn_pyg.nn.hrn.StepOptions`).
        legacy: the options one keyword each, deprecated.
    """
    options = _with_legacy(options, legacy, "predict")
    inputs = build_inputs(model, graph, force, options)
    return decode(model, graph, run_network(model, inputs, masks), options.objects)


def step(
    model: HRN,
    graph: HeteroData,
    force: Tensor | None = None,
    masks: Mapping[str, Tensor] | None = None,
    options: StepOptions = StepOptions(),
    *,
    search: CollisionSearch | None = None,
    **legacy: Any,
) -> Step:
    """One model step: :func:`predict`, ``options.rules`` (:func:`~hrn_pyg.sim.rules.step_rules`),
    then :func:`advance` to ``t+1``. ``search(graph, pos)`` (optional) gives the collision edges at
    ``pos`` (a rollout's :class:`~hrn_pyg.data.candidates.VerletSearch`); None searches, and
    ``options.collisions`` False gives none. New positions are always checked for NaN / inf."""
    options = _with_legacy(options, legacy, "step")
    prediction = predict(model, graph, force, masks, options)
    if options.rules is not None:
        prediction = options.rules(graph, prediction, node_force(graph, force, check=False), None)
    pos, local, velocity, since = prediction
    if options.collisions and search is not None:
        check_next_pos(pos)
        nxt = advance(graph, pos, None, edges=search(graph, pos), check=False, prev_pos=since)
    else:
        nxt = advance(graph, pos, collision_radius_of(model.config, graph) if options.collisions else None,
                      prev_pos=since)
    return Step(pos=pos, local_velocity=local, velocity=velocity, graph=nxt)


def advance(
    graph: HeteroData,
    pos: Tensor,
    radius: float | Tensor | None,
    held: Tensor | None = None,
    edges: Tensor | None = None,
    check: bool = True,
    prev_pos: Tensor | None = None,
) -> HeteroData:
    """The graph at ``t+1``: a shallow copy with ``prev_prev_pos, prev_pos, pos = x_{t-1}, x_t,
    x_{t+1}``, force zero and the collision edges of ``x_{t+1}``; rows moved, not recomputed.

    ``held`` ``[N]`` bool: nodes held still (:mod:`hrn_pyg.sim.sleeping`), whose ``prev_prev_pos``
    becomes ``x_t``. ``edges``: the collision edges of ``x_{t+1}`` if known, else all leaves are
    searched at ``radius`` (:func:`~hrn_pyg.nn.pitch.collision_radius_of`). ``check=False``: ``pos``
    is checked (:func:`check_next_pos`). ``prev_pos``: ``x_t`` when it is not ``pos``.

    **Shapes:** pos ``(N, 3)``; returns a graph with ``collision`` ``(2, |E_C|)``.
    """
    if check:
        check_next_pos(pos)
    store = graph[NODE]
    out = copy.copy(graph)
    part = out[NODE]
    part.prev_prev_pos = store.prev_pos if held is None else torch.where(held.unsqueeze(-1), store.pos, store.prev_pos)
    part.prev_pos = store.pos if prev_pos is None else prev_pos
    part.pos = pos
    part.force = torch.zeros_like(pos)
    out[COLLISION].edge_index = leaf_collision_edges(out, pos, radius) if edges is None else edges
    return out




#: the name a non-finite prediction is reported under
NEXT_POS = "advance: pos"


def check_next_pos(pos: Tensor) -> None:
    """Raise ValueError if a step's new positions ``[N, 3]`` hold NaN or inf (a host read)."""
    check_finite(NEXT_POS, pos)
