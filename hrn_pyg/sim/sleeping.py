r"""Objects at rest sleep: a step runs the network only on what moves (as Bullet and PhysX do).

An *object* is one root's tree of one batch copy (:func:`hrn_pyg.sim.step.root_of`), so the
copies of :func:`hrn_pyg.data.graph.replicate` sleep independently. Each object carries whether
it is asleep and for how many steps it has been still (:class:`SleepState`). At the start of
step :math:`t`, with :math:`\tau` = ``threshold`` and :math:`P` = ``patience``:

.. math::
    \mathrm{still}_o &\iff \max_{l \in o} \lVert x_l(t) - x_l(t-1) \rVert < \tau
        \ \wedge\ f_l(t) = 0 \ \forall l \in o \\
    \mathrm{moving}_o &\iff \mathrm{awake}_o \wedge \neg \mathrm{still}_o, \qquad
    \mathrm{pushed}_o \iff \exists l \in o: f_l(t) \ne 0 \\
    \mathrm{active} &= \text{the smallest set} \supseteq \{o : \mathrm{moving}_o \vee \mathrm{pushed}_o\}
        \text{ closed under contact: } o \in \mathrm{active},\ (o, o') \in \mathcal{E}_C
        \Rightarrow o' \in \mathrm{active} \\
    c_o &\leftarrow \begin{cases} c_o + 1 & \mathrm{awake}_o \wedge o \notin \mathrm{active} \\
        0 & \text{otherwise} \end{cases} \\
    \mathrm{asleep}_o &\leftarrow \bigl(\mathrm{asleep}_o \wedge o \notin \mathrm{active}\bigr)
        \ \vee\ \bigl(\mathrm{awake}_o \wedge o \notin \mathrm{active} \wedge c_o \ge P\bigr)
        \ \vee\ \mathrm{static}_o

Static objects never enter ``active``. A force, or a chain of contacts to a moving object (a
*simulation island*), wakes an object; woken objects take part in the same step from rest. An
object in the active set counts no still steps: when what it leans on moves away, it has
``patience`` steps to find out whether it falls before it may sleep.

:func:`sleeping_step` runs :func:`hrn_pyg.sim.step.predict` on a sub-graph
(:func:`predict_held`): the awake objects plus the asleep leaves with collision edges into them,
flagged ``is_static``. The network is local, so the awake objects see what they would see in the
whole graph; asleep objects keep ``pos`` bit for bit. With nothing asleep the step is
:func:`hrn_pyg.sim.step.step` bit for bit; with everything asleep the network does not run.

A rollout keeps its state in a :class:`Sleeper`. Callers with no state between steps (the RL
environment) use :func:`held_from_history`: an object still over the two steps of its history
is asleep (:func:`state_from_history`), then :func:`update` wakes what is reached.

The defaults (displacements per 1/30 s step; sweeps in docs/history.md): pybullet's resting
bodies jitter up to 1-10 mm per step (soft, cloth), real motion is 1 cm per step or more, and
the models let resting objects creep 0.1-1.4 mm per step; so ``threshold = 2e-3`` (6 cm/s) and
``patience = 10`` steps (1/3 s).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, replace
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
    PITCH,
    WITHIN_SIBLINGS,
    copy_object_ids,
    object_span,
    per_node_radius,
)
from hrn_pyg.data.radius import cell_keys, collision_edges
from hrn_pyg.nn.hrn import HRN, StepOptions
from hrn_pyg.nn.pitch import collision_radius_of
from hrn_pyg.sim.step import Prediction, Step, check_next_pos, object_of, predict, step
from hrn_pyg.sim.step import advance as advance_graph


@dataclass(frozen=True)
class SleepConfig:
    """When an object at rest falls asleep (the rule: the module docstring).

    Attributes:
        enabled: False runs every object at every step (the plain rollout, bit for bit).
        threshold: metres per step under which an unpushed object's leaves were still.
        patience: consecutive still steps after which an object falls asleep (>= 1).
        start_from_history: start in the state the start's three positions imply
            (:func:`state_from_history`); False starts every movable object awake.
    """

    enabled: bool = True
    threshold: float = 2e-3
    patience: int = 10
    start_from_history: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.enabled, bool):
            raise ValueError(f"SleepConfig.enabled must be a bool, got {self.enabled!r}")
        threshold = self.threshold
        if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not (
                math.isfinite(threshold) and threshold > 0):
            raise ValueError(f"SleepConfig.threshold must be a finite number > 0 (metres per step), got {threshold!r}")
        if not isinstance(self.start_from_history, bool):
            raise ValueError(f"SleepConfig.start_from_history must be a bool, got {self.start_from_history!r}")
        patience = self.patience
        if isinstance(patience, bool) or not isinstance(patience, int) or patience < 1:
            raise ValueError(f"SleepConfig.patience must be an integer >= 1 (steps), got {patience!r}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


#: what :func:`hrn_pyg.sim.rollout.rollout`, :func:`hrn_pyg.sampling.sample` and the RL environment
#: use unless told otherwise (``sleep=None`` runs every object at every step)
DEFAULT_SLEEP = SleepConfig()


#: node attributes a model step reads (:func:`~hrn_pyg.sim.step.build_inputs`, ``decode``), the
#: ones a sub-graph carries; ``batch`` and ``rest_pos`` only where the graph has them
NODE_ATTRIBUTES = ("mass", "material", "stiffness", "object", "depth", "is_leaf", "is_root", "is_static",
                   "pos", "prev_pos", "prev_prev_pos", "batch", "rest_pos")
#: largest leaves x awake-object boxes test of :func:`near_awake` (about 16 MB of booleans);
#: beyond it the grid cells are used
BOX_TEST_LIMIT = 2**24
#: the hierarchy's edge sets: within one object, so a sub-graph keeps those of its awake objects
HIERARCHY_EDGES = (CHILD_TO_PARENT, LEAF_TO_ANCESTOR, WITHIN_SIBLINGS, ANCESTOR_TO_DESCENDANT)


class Objects(NamedTuple):
    """The objects of a graph, fixed for a rollout.

    Attributes:
        of_node: ``[N]`` long, the object ``0..R-1`` of every node (in the order of the roots).
        static: ``[R]`` bool, static objects (never moved, always asleep).
        count: ``R``, the number of objects.
    """

    of_node: Tensor
    static: Tensor
    count: int


class SleepState(NamedTuple):
    """What sleeping carries from one step to the next, per object ``[R]``.

    Attributes:
        asleep: bool; asleep objects are held still and not run through the network.
        still: long; consecutive still steps so far (0 after a motion, a force, a wake-up or a
            step in contact with a moving object).
    """

    asleep: Tensor
    still: Tensor


def objects(graph: HeteroData) -> Objects:
    """The :class:`Objects` of ``graph``: one per root node, numbered in root order
    (:func:`hrn_pyg.sim.step.object_of`)."""
    of_node, count = object_of(graph)
    static = torch.zeros(count, dtype=torch.bool, device=of_node.device).index_fill(
        0, of_node[graph[NODE].is_static], True)
    return Objects(of_node=of_node, static=static, count=count)


def initial_state(objs: Objects) -> SleepState:
    """Every movable object awake with no still steps yet; static objects asleep."""
    return SleepState(asleep=objs.static.clone(), still=torch.zeros(objs.count, dtype=torch.long,
                                                                     device=objs.static.device))


def object_any(flag: Tensor, objs: Objects) -> Tensor:
    """``[N]`` bool -> ``[R]`` bool: does any node of the object have the flag."""
    out = torch.zeros(objs.count, dtype=torch.long, device=flag.device)
    return out.scatter_reduce(0, objs.of_node, flag.long(), reduce="amax").bool()


def object_max(value: Tensor, objs: Objects) -> Tensor:
    """``[N]`` float (>= 0) -> ``[R]``: the largest value over the object's nodes."""
    out = torch.zeros(objs.count, dtype=value.dtype, device=value.device)
    return out.scatter_reduce(0, objs.of_node, value, reduce="amax")


def touched_by(edge_index: Tensor, objs: Objects, source: Tensor) -> Tensor:
    r"""``[R]`` bool: objects with a collision edge from a leaf of an object in ``source`` ``[R]``.

    .. math:: \mathrm{touched}_o = \exists (j, i) \in \mathcal{E}_C : o(i) = o,\ \mathrm{source}_{o(j)}
    """
    src, dst = objs.of_node[edge_index[0]], objs.of_node[edge_index[1]]
    out = torch.zeros(objs.count, dtype=torch.long, device=source.device)
    return out.scatter_reduce(0, dst, source[src].long(), reduce="amax").bool()


def update(
    config: SleepConfig, state: SleepState, graph: HeteroData, force: Tensor, objs: Objects
) -> SleepState:
    """The sleep state of step ``t`` from the graph at ``t`` and the step's force ``[N, 3]``: the rule
    of the module docstring, the active set grown through collision edges to a fixed point."""
    store = graph[NODE]
    leaf = store.is_leaf
    disp = (store.pos - store.prev_pos).norm(dim=-1)
    moved = object_max(torch.where(leaf, disp, torch.zeros_like(disp)), objs) >= config.threshold
    pushed = object_any(leaf & force.ne(0).any(dim=-1), objs) & ~objs.static
    awake = ~state.asleep
    active = (awake & moved) | pushed
    edges = graph[COLLISION].edge_index if COLLISION in graph.edge_types else force.new_empty(2, 0, dtype=torch.long)
    movable = ~objs.static
    for _ in range(objs.count):  # links of the longest contact chain, not objects; usually 0-2
        grown = active | (movable & touched_by(edges, objs, active))
        if bool((grown == active).all()):
            break
        active = grown
    counter = torch.where(awake & ~active, state.still + 1, torch.zeros_like(state.still))
    falls = awake & ~active & (counter >= config.patience)
    asleep = (state.asleep & ~active) | falls | objs.static
    return SleepState(asleep=asleep, still=counter)


def freeze(graph: HeteroData, asleep_node: Tensor) -> tuple[Tensor, Tensor]:
    """``(prev_pos, prev_prev_pos)`` ``[N, 3]`` with the rows of asleep nodes set to ``pos``
    (zero velocity now and before, so a woken object starts from rest)."""
    store = graph[NODE]
    held = asleep_node.unsqueeze(-1)
    return torch.where(held, store.pos, store.prev_pos), torch.where(held, store.pos, store.prev_prev_pos)


def subgraph(graph: HeteroData, asleep_node: Tensor, prev_pos: Tensor, prev_prev_pos: Tensor
             ) -> tuple[HeteroData, Tensor, Tensor]:
    """The nodes a step with sleeping objects has to run, as a graph of their own.

    Nodes: every node of an awake object (``~asleep_node``), then every asleep leaf with a collision
    edge into an awake leaf, flagged ``is_static``; edges among them, renumbered. Node attributes
    (``batch`` and ``pitch`` included) keep their values; positions are those of :func:`freeze`.
    Returns ``(sub, index, awake_rows)``: ``index`` ``[n]`` the full-graph node of each sub-graph
    node, ``awake_rows`` ``[n]`` bool.

    **Shapes:** asleep_node ``(N,)`` bool; ``sub`` has ``n <= N`` nodes.
    """
    store = graph[NODE]
    n = store.num_nodes
    awake = ~asleep_node
    src, dst = graph[COLLISION].edge_index
    into_awake = awake[dst]
    source = torch.zeros(n, dtype=torch.bool, device=awake.device).index_fill(0, src[into_awake], True) & asleep_node
    index = torch.cat([torch.nonzero(awake).flatten(), torch.nonzero(source).flatten()])
    new_id = torch.full((n,), -1, dtype=torch.long, device=awake.device)
    new_id[index] = torch.arange(index.numel(), device=awake.device)
    awake_rows = awake[index]

    sub = HeteroData()
    part = sub[NODE]
    part.num_nodes = int(index.numel())
    values = {k: store[k] for k in NODE_ATTRIBUTES if k in store}
    values.update(prev_pos=prev_pos, prev_prev_pos=prev_prev_pos)
    for key, value in values.items():
        part[key] = value.index_select(0, index)
    part.is_static = part.is_static | ~awake_rows
    for edge_type in HIERARCHY_EDGES:
        edge_index = graph[edge_type].edge_index
        sub[edge_type].edge_index = new_id[edge_index[:, awake[edge_index[1]]]]
    sub[COLLISION].edge_index = new_id[torch.stack([src[into_awake], dst[into_awake]])]
    if PITCH in graph:  # the graphs' pitches, which the kept batch ids look up
        setattr(sub, PITCH, getattr(graph, PITCH))
    return sub, index, awake_rows


def holds_movable(held: Tensor, graph: HeteroData) -> bool:
    """Whether ``held`` ``[N]`` bool holds any node that is not static (one host read)."""
    return bool((held & ~graph[NODE].is_static).any())


def sleeping_step(
    model: HRN,
    graph: HeteroData,
    force: Tensor,
    masks: Mapping[str, Tensor] | None,
    state: SleepState,
    objs: Objects,
    config: SleepConfig,
    options: StepOptions = StepOptions(),
) -> tuple[Step, SleepState]:
    """One model step in which objects at rest sleep; returns the step and the new sleep state.

    ``force`` ``[N, 3]``; ``state`` from the previous step (:func:`initial_state` at the start). The
    :class:`~hrn_pyg.sim.step.Step` has zero velocities and ``asleep`` on the held nodes and the next
    graph of :func:`advance`. ``options`` are those of :func:`hrn_pyg.sim.step.step`.
    """
    state = update(config, state, graph, force, objs)
    asleep_node = state.asleep[objs.of_node]
    if not holds_movable(asleep_node, graph):  # nothing movable sleeps: the plain step
        if options.objects is None:
            options = replace(options, objects=(objs.of_node, objs.count))
        result = step(model, graph, force, masks, options)
        return result._replace(asleep=graph[NODE].is_static), state
    prediction = predict_held(model, graph, force, masks, asleep_node, options)
    if options.rules is not None:
        prediction = options.rules(graph, prediction, force, ~asleep_node)
    pos, local, velocity, since = prediction
    nxt = advance(graph, asleep_node, pos, collision_radius_of(model.config, graph) if options.collisions else None,
                  since)
    return Step(pos=pos, local_velocity=local, velocity=velocity, graph=nxt, asleep=asleep_node), state


def predict_held(
    model: HRN,
    graph: HeteroData,
    force: Tensor,
    masks: Mapping[str, Tensor] | None,
    held: Tensor | None,
    options: StepOptions = StepOptions(),
) -> Prediction:
    """:func:`hrn_pyg.sim.step.predict` with the ``held`` ``[N]`` rows held still: the network runs on
    the :func:`subgraph` of the others; held rows keep ``pos`` bit for bit with zero velocity.
    ``held=None``: the plain prediction. A ``collision_weight`` cannot come with ``held``."""
    if held is None:
        return predict(model, graph, force, masks, options)
    if options.collision_weight is not None:
        raise ValueError("predict_held: options.collision_weight weighs the whole graph's collision edges; "
                         "a step with held rows runs a sub-graph")
    store = graph[NODE]
    zero = torch.zeros_like(store.pos)
    if bool(held.all()):  # nothing to run: the scene holds still
        return Prediction(store.pos, zero, zero)
    prev_pos, prev_prev_pos = freeze(graph, held)
    sub, index, awake_rows = subgraph(graph, held, prev_pos, prev_prev_pos)
    sub_pos, sub_local, sub_velocity, sub_since = predict(model, sub, force.index_select(0, index), masks,
                                                          replace(options, objects=None, hierarchy=None))
    keep = awake_rows.unsqueeze(-1)
    pos = store.pos.index_copy(0, index, torch.where(keep, sub_pos, store.pos.index_select(0, index)))
    local = zero.index_copy(0, index, torch.where(keep, sub_local, zero.index_select(0, index)))
    velocity = zero.index_copy(0, index, torch.where(keep, sub_velocity, zero.index_select(0, index)))
    since = None if sub_since is None else store.pos.index_copy(
        0, index, torch.where(keep, sub_since, store.pos.index_select(0, index)))
    return Prediction(pos, local, velocity, since)


def held_from_history(config: SleepConfig, graph: HeteroData, objs: Objects, force: Tensor) -> Tensor:
    """``[N]`` bool: the nodes a stateless caller holds this step: those :func:`state_from_history`
    finds at rest, less those :func:`update` wakes (a force ``[N, 3]`` or a moving contact)."""
    return update(config, state_from_history(config, graph, objs), graph, force, objs).asleep[objs.of_node]


class Sleeper:
    """The sleep bookkeeping of one rollout: the scene's :class:`Objects` and the
    :class:`SleepState`; :meth:`start`, then one :func:`sleeping_step` per :meth:`step`."""

    def __init__(self, config: SleepConfig, objs: Objects, state: SleepState) -> None:
        self.config, self.objects, self.state = config, objs, state

    @classmethod
    def start(cls, config: SleepConfig, graph: HeteroData) -> Sleeper:
        """The objects of ``graph`` and their state at the start: the state its history implies
        (``config.start_from_history``), else every movable object awake."""
        objs = objects(graph)
        state = state_from_history(config, graph, objs) if config.start_from_history else initial_state(objs)
        return cls(config, objs, state)

    def step(self, model: HRN, graph: HeteroData, force: Tensor, masks: Mapping[str, Tensor] | None,
             options: StepOptions = StepOptions()) -> Step:
        """One :func:`sleeping_step` with ``options`` (a rollout's: the step's plan, inputs
        checked once at the start)."""
        result, self.state = sleeping_step(model, graph, force, masks, self.state, self.objects, self.config,
                                           options)
        return result


def state_from_history(config: SleepConfig, graph: HeteroData, objs: Objects) -> SleepState:
    """The sleep state a graph's three positions imply: an object whose leaves moved less than
    ``threshold`` in both steps ``x_{t-2} -> x_{t-1} -> x_t`` is asleep, its counter at
    ``patience``."""
    store = graph[NODE]
    leaf = store.is_leaf
    zero = torch.zeros_like(store.pos[:, 0])
    disp = torch.maximum((store.pos - store.prev_pos).norm(dim=-1), (store.prev_pos - store.prev_prev_pos).norm(dim=-1))
    still = object_max(torch.where(leaf, disp, zero), objs) < config.threshold
    asleep = still | objs.static
    return SleepState(asleep=asleep, still=torch.where(still, config.patience, 0).to(torch.long))


def advance(graph: HeteroData, asleep_node: Tensor, pos: Tensor, radius: float | Tensor | None,
            prev_pos: Tensor | None = None) -> HeteroData:
    """The graph at ``t+1`` after a sleeping step: :func:`hrn_pyg.sim.step.advance` with the asleep
    nodes held and the edges of :func:`next_collision_edges`. ``pos`` ``[N, 3]`` has ancestors
    derived; ``prev_pos``: the prediction's ``x_t`` where a ground lift moved it."""
    check_next_pos(pos)  # before the search reads it
    edges = next_collision_edges(graph, asleep_node, pos, radius)
    return advance_graph(graph, pos, radius, held=asleep_node, edges=edges, check=False, prev_pos=prev_pos)


def next_collision_edges(graph: HeteroData, asleep_node: Tensor, pos: Tensor,
                         radius: float | Tensor | None) -> Tensor:
    """The collision edges of ``pos`` (``x_{t+1}``), searched only where something moved.

    An edge between two asleep leaves cannot change and is kept; the others are searched
    (:func:`hrn_pyg.data.radius.collision_edges`) among the awake leaves and the asleep ones near
    them (:func:`near_awake`). The union is exactly the full search's set. Over half awake: the full
    search runs; none awake: the edges are kept. ``radius``: a number or one per graph ``(B,)``.

    **Shapes:** asleep_node ``(N,)`` bool, pos ``(N, 3)``; returns ``(2, |E_C|)``.
    """
    store = graph[NODE]
    leaf = store.is_leaf
    n = store.num_nodes
    if radius is None or (not isinstance(radius, Tensor) and radius <= 0):
        return torch.empty(2, 0, dtype=torch.long, device=pos.device)
    widest = radius
    if isinstance(radius, Tensor):  # each node's own radius; the box / cell tests at the largest
        radius = per_node_radius(graph, radius)
        widest = float(radius.max())
    batch = store.batch if "batch" in store else torch.zeros_like(store.object)
    awake_leaf = leaf & ~asleep_node
    awake_count = int(awake_leaf.sum())
    if awake_count == 0:  # nothing moved: every edge joins two held leaves and is the same as before
        return graph[COLLISION].edge_index
    if awake_count * 2 > int(leaf.sum()):
        index = torch.nonzero(leaf).flatten()
        return index[collision_edges(pos[index], store.object[index], _at(radius, index), batch[index])]
    old = graph[COLLISION].edge_index
    kept = old[:, asleep_node[old[0]] & asleep_node[old[1]]]
    index = torch.nonzero(leaf & (awake_leaf | near_awake(pos, batch, leaf, awake_leaf, widest, store.object))).flatten()
    found = index[collision_edges(pos[index], store.object[index], _at(radius, index), batch[index])]
    found = found[:, ~(asleep_node[found[0]] & asleep_node[found[1]])]
    edges = torch.cat([kept, found], dim=1)
    return edges[:, torch.argsort(edges[1] * n + edges[0])]


def _at(radius: float | Tensor, index: Tensor) -> float | Tensor:
    """The radius of the nodes ``index``: a number as it is, a per-node tensor's rows."""
    return radius.index_select(0, index) if isinstance(radius, Tensor) else radius


def near_awake(pos: Tensor, batch: Tensor, leaf: Tensor, awake_leaf: Tensor, radius: float,
               leaf_object: Tensor) -> Tensor:
    """``[N]`` bool: the leaves inside the bounding box, grown by ``radius``, of an awake object of
    their batch copy: a superset of those within ``radius`` of an awake leaf. Over
    :data:`BOX_TEST_LIMIT` comparisons it falls back to :func:`near_awake_cells`.

    **Shapes:** pos ``(N, 3)``, batch / leaf_object ``(N,)``, leaf / awake_leaf ``(N,)`` bool.
    """
    index = torch.nonzero(leaf).flatten()
    awake = torch.nonzero(awake_leaf).flatten()
    span = object_span(leaf_object)
    box_key, box_of = torch.unique(copy_object_ids(batch[awake], leaf_object[awake], span), return_inverse=True)
    if box_key.numel() * index.numel() > BOX_TEST_LIMIT:
        return near_awake_cells(pos, batch, leaf, awake_leaf, radius)
    spread = box_of[:, None].expand(-1, 3)
    low = pos.new_full((box_key.numel(), 3), float("inf")).scatter_reduce(0, spread, pos[awake], reduce="amin")
    high = pos.new_full((box_key.numel(), 3), float("-inf")).scatter_reduce(0, spread, pos[awake], reduce="amax")
    x = pos[index][:, None, :]  # [L, 1, 3] against [B, 3] boxes
    inside = ((x >= low - radius) & (x <= high + radius)).all(dim=-1)
    inside &= batch[index][:, None] == torch.div(box_key, span, rounding_mode="floor")[None, :]
    return torch.zeros_like(leaf).index_fill(0, index[inside.any(dim=1)], True)


def near_awake_cells(pos: Tensor, batch: Tensor, leaf: Tensor, awake_leaf: Tensor, radius: float) -> Tensor:
    r"""``[N]`` bool: the leaves in or next to a grid cell (:func:`hrn_pyg.data.radius.cell_keys`, side
    :math:`h \ge r`) holding an awake leaf of the same batch copy.

    **Shapes:** pos ``(N, 3)``, batch ``(N,)``, leaf / awake_leaf ``(N,)`` bool.
    """
    index = torch.nonzero(leaf).flatten()
    key, offset_key = cell_keys(pos[index], radius, batch[index])
    around = torch.unique((torch.unique(key[awake_leaf[index]])[:, None] + offset_key[None]).flatten())
    return torch.zeros_like(leaf).index_fill(0, index[torch.isin(key, around)], True)
