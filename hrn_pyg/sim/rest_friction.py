r"""Static friction: a supported object that has all but stopped stays where it is.

The network predicts a step's motion from the last two positions. At rest its answer is not quite
zero: a resting object keeps a small steady velocity, tens of micrometres a step, and over 1000
steps creeps centimetres where pybullet's object does not move. A real object in contact is held
by static friction: Coulomb friction takes up to :math:`\mu g \Delta t^2` off a sliding object's
step each step (5 mm at :math:`\mu = 0.5`, :math:`\Delta t = 1/30` s), so a supported object whose
steps are far shorter than that has stopped.

**Rule.** With :math:`h` the pitch, :math:`\varepsilon` = ``HRNConfig.rest_friction`` pitches, an
object :math:`o` that is not static is held at :math:`x_t` (its step is zero) when

.. math::
    \mathrm{supported}_o \ \wedge\ \max_{l \in o} \max\bigl(\lVert x_l(t+1) - x_l(t) \rVert,\
        \lVert x_l(t) - x_l(t-1) \rVert\bigr) < \varepsilon\, h

where :math:`x(t+1)` is the prediction after the energy limit (the clearance comes after this
rule, so a push out of another body is never taken back) and :math:`\mathrm{supported}_o`: a
collision edge joins a leaf of :math:`o` to a leaf of another object, or its lowest leaf is less
than one pitch above the ground :math:`z = 0`. An object pushed in the step (a leaf with an
external force) is never held: how it answers a push, however small, is the network's to say, as
is how far a slow push moves it. Both steps count, so an object that the network
brakes hard (a fast step, then a short one) is not caught mid-way, and an object in the air is
never held (at the top of a throw it is slow but touches nothing). A hold only takes motion away:
it gives no energy and moves nothing into another object.

Each batch copy is judged on its own (objects are per copy, :func:`~hrn_pyg.sim.step.object_of`).
No host read: every row is computed and the held ones selected.

**Shapes.** positions ``(N, 3)``, ``objects`` ``((N,) long, R)``; the masks are ``(R,)`` bool.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.data.graph import COLLISION, NODE, node_pitch
from hrn_pyg.sim.step import Prediction, held_at_current


def supported_objects(graph: HeteroData, objects: tuple[Tensor, int]) -> Tensor:
    """``(R,)`` bool: objects with a collision edge to another object at :math:`x_t`, or whose
    lowest leaf is less than one pitch above the ground."""
    group, count = objects
    store = graph[NODE]
    leaves = store.is_leaf
    height = (store.pos[:, 2] - node_pitch(graph).to(store.pos.dtype))[leaves]
    lowest = torch.full((count,), float("inf"), dtype=store.pos.dtype, device=group.device)
    lowest = lowest.scatter_reduce(0, group[leaves], height, "amin")
    supported = lowest < 0
    edges = graph[COLLISION].edge_index if COLLISION in graph.edge_types else None
    if edges is not None and edges.numel():
        sender, receiver = group[edges[0]], group[edges[1]]
        between = sender != receiver
        supported = supported.index_fill(0, sender[between], True).index_fill(0, receiver[between], True)
    return supported


def resting_objects(graph: HeteroData, pos: Tensor, objects: tuple[Tensor, int], limit: float,
                    force: Tensor | None = None) -> Tensor:
    """``(R,)`` bool: movable, supported objects whose every leaf moved less than ``limit``
    pitches in the last step and moves less in the predicted one (``pos``, :math:`x_{t+1}`), and
    on none of whose nodes ``force`` ``(N, 3)`` (the step's external force; None: none) acts."""
    group, count = objects
    store = graph[NODE]
    leaves = store.is_leaf
    step = torch.maximum((pos - store.pos).norm(dim=-1), (store.pos - store.prev_pos).norm(dim=-1))
    relative = (step / node_pitch(graph).to(step.dtype))[leaves]
    longest = torch.zeros(count, dtype=step.dtype, device=group.device)
    longest = longest.scatter_reduce(0, group[leaves], relative, "amax")
    moving = torch.zeros(count, dtype=torch.bool, device=group.device).index_fill_(0, group[~store.is_static], True)
    resting = moving & (longest < limit) & supported_objects(graph, objects)
    if force is not None:
        pushed = (force != 0).any(-1)
        resting = resting & ~torch.zeros_like(resting).index_fill_(0, group[pushed], True)
    return resting


def hold_resting(graph: HeteroData, prediction: Prediction, objects: tuple[Tensor, int], limit: float,
                 force: Tensor | None = None) -> Prediction:
    """``prediction`` with every object of :func:`resting_objects` held at :math:`x_t` (zero
    velocity; its ``prev_pos`` too, where the prediction carries one)."""
    return held_at_current(graph, prediction, resting_objects(graph, prediction.pos, objects, limit, force)[objects[0]])
