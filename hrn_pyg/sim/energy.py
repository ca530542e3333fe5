r"""No step creates energy: the energy limit applied to a step's prediction.

A scene of rigid bodies, soft bodies and cloth under gravity loses energy to friction, damping
and collisions; only the scene's pushes put energy in. The network does not know this, and a
sampled future (or the network alone, at a pitch it reads badly) can gain energy step after
step until a body climbs onto another or flies off. This rule holds every step to the balance

.. math::
    E_{t+1} \le E_t + \max(0, W_t), \qquad
    E_t = \sum_{i} m_i \Bigl(g\, z_i(t) + \tfrac{1}{2} \lVert x_i(t) - x_i(t-1) \rVert^2 / \Delta t^2\Bigr),
    \qquad W_t = \sum_i f_i \cdot \bigl(x_i(t+1) - x_i(t)\bigr)

per scene copy of a batch (the sums run over its moving leaves: velocities by differences of
positions, :math:`f_i` the step's external force in newtons, :math:`\Delta t` the model step).

**How.** Objects whose own energy falls in the step keep their prediction: what they give up
may pass to the others (a falling body pushes a box). When the copy's total still rises by a
surplus :math:`S > 0`, the objects that gained energy (set :math:`G`) move by a fraction
:math:`\alpha \in [0, 1)` of their predicted step :math:`d_i = x_i(t+1) - x_i(t)`:

.. math::
    x_i(t+1) \leftarrow x_i(t) + \alpha\, d_i, \qquad
    E_G(\alpha) = P + \alpha A + \alpha^2 B, \quad
    A = \sum_{i \in G} m_i g\, d_{i,z}, \quad B = \sum_{i \in G} \tfrac{m_i}{2} \lVert d_i \rVert^2 / \Delta t^2,

the largest :math:`\alpha` with :math:`E_G(\alpha) - \alpha W_G \le E_G(1) - W_G - S`
(:math:`W_G` the work of the pushes on :math:`G`, which shrinks with their step; 0 when the
copy's pushes do no work), the root :math:`\alpha = 2C / (A' + \sqrt{A'^2 + 4BC})` with
:math:`A' = A - W_G` and :math:`C = A' + B - S` (0 when :math:`C \le 0`).
Every point of the segment from :math:`x(t)` to the prediction is as far from the ground as its
ends, so the rule keeps what the ground projection made; a rigid object that moved by a fraction
of a turn is fitted rigid again (:func:`~hrn_pyg.sim.step.rigid_leaf_positions`). The rule is a
dissipation: it takes energy from the bodies that made it and gives none.

Where the ground projection moved :math:`x_t` rather than the prediction (``prev_pos`` of a
:class:`~hrn_pyg.sim.step.Prediction`), the balance starts from the lifted place: a correction of
place is not a motion.

**Shapes.** :func:`limit_energy` maps a step's prediction over ``N`` nodes to one over ``N``
nodes; :func:`scene_energy` gives ``(B,)`` energies of ``B`` copies.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.data.graph import CHILD_TO_PARENT, NODE, RIGID, leaf_to_ancestor_mean
from hrn_pyg.data.kinds import GRAVITY, PHYSICS_HZ, SUBSTEPS
from hrn_pyg.nn.state import to_local_velocity
from hrn_pyg.sim.step import Prediction, rigid_leaf_positions

#: the model step (s) of every scene whose graph records none (``graph.dt``): the scenes' default
STEP_SECONDS = SUBSTEPS / PHYSICS_HZ
#: the graph-level attribute that records a scene's model step (s), one per copy of a batch
DT = "dt"


class EnergyBalance(NamedTuple):
    """A step's balance per node and per copy (:func:`energy_balance`).

    Attributes:
        now: ``[N]`` float64, each moving leaf's energy at :math:`t` (zero elsewhere).
        next: ``[N]`` float64, its energy at :math:`t+1` under the prediction.
        work: ``[N]`` float64, the work of its external force in the step.
        step: ``[N, 3]``, the prediction's step :math:`d_i` from :math:`x_t`.
        weight: ``[N]`` float64, :math:`m_i` on moving leaves, 0 elsewhere.
        g: ``[N]`` float64, gravity (m/s^2) at each node.
        inv_dt2: ``[N]`` float64, :math:`1 / \\Delta t^2` at each node.
    """

    now: Tensor
    next: Tensor
    work: Tensor
    step: Tensor
    weight: Tensor
    g: Tensor
    inv_dt2: Tensor


def step_seconds(graph: HeteroData) -> Tensor:
    """``[N]`` float64: the model step (s) of every node's copy (``graph.dt``, else
    :data:`STEP_SECONDS`)."""
    store = graph[NODE]
    n = store.num_nodes
    device = store.pos.device
    if DT not in graph:
        return torch.full((n,), STEP_SECONDS, dtype=torch.float64, device=device)
    dt = getattr(graph, DT).to(device=device, dtype=torch.float64).reshape(-1)
    batch = store.batch if "batch" in store else torch.zeros(n, dtype=torch.long, device=device)
    return dt[batch] if dt.numel() > 1 else dt.expand(n)


def moving_leaves(graph: HeteroData, movable: Tensor | None = None) -> Tensor:
    """``[N]`` bool: the leaves that may move in the step (not static; of ``movable`` if given)."""
    store = graph[NODE]
    moving = store.is_leaf & ~store.is_static
    return moving if movable is None else moving & movable


def energy_balance(graph: HeteroData, prediction: Prediction, force: Tensor | None = None,
                   movable: Tensor | None = None) -> EnergyBalance:
    """The per-node terms of the module's balance for ``prediction`` of a step of ``graph``
    (``force`` ``[N, 3]`` newtons, None: no force; ``movable`` ``[N]`` bool, None: every node)."""
    store = graph[NODE]
    weight = torch.where(moving_leaves(graph, movable), store.mass[:, 0].double(), store.mass.new_zeros(()).double())
    g = torch.full_like(weight, GRAVITY)
    inv_dt2 = step_seconds(graph).reciprocal().square()
    start = (store.pos if prediction.prev_pos is None else prediction.prev_pos).double()
    now_velocity = (store.pos - store.prev_pos).double()
    # the balance starts where the ground lift put x_t: its potential energy at the lifted place
    now = weight * (g * start[:, 2] + 0.5 * inv_dt2 * now_velocity.square().sum(-1))
    step = prediction.pos.double() - start
    nxt = weight * (g * prediction.pos[:, 2].double() + 0.5 * inv_dt2 * step.square().sum(-1))
    work = torch.zeros_like(weight) if force is None else (force.double() * step).sum(-1) * (weight > 0)
    return EnergyBalance(now, nxt, work, step, weight, g, inv_dt2)


def copy_of_objects(graph: HeteroData, objects: tuple[Tensor, int]) -> Tensor:
    """``[R]`` long: the batch copy of each of the graph's ``R`` objects."""
    group, count = objects
    store = graph[NODE]
    batch = store.batch if "batch" in store else torch.zeros_like(group)
    return torch.zeros(count, dtype=torch.long, device=group.device).scatter_(0, group, batch)


def limit_energy(graph: HeteroData, prediction: Prediction, objects: tuple[Tensor, int],
                 force: Tensor | None = None, movable: Tensor | None = None,
                 rigid_from_rest: bool = False, host_reads: bool = True) -> Prediction:
    r"""``prediction`` (a step of ``graph``) with no copy's energy above its balance (module
    docstring): the objects that gained energy in a copy whose total rose more than the work of
    its pushes move by the fraction :math:`\alpha` of their step that closes the balance.

    ``objects``: :func:`~hrn_pyg.sim.step.object_of` of ``graph``; ``force`` ``[N, 3]`` the step's
    external force (N); ``movable`` ``[N]`` bool: the rows that may move (a step with sleeping
    objects); ``rigid_from_rest``: the rigid refit reads the rest shape
    (``HRNConfig.rigid_fit_rest``). The same prediction object when no copy gains (a host read
    tells); ``host_reads=False`` never asks (the fixed-shape step: every row is computed and
    the unchanged ones selected). Differentiable in the positions.

    **Shapes:** ``N`` nodes; every tensor of the prediction ``(N, 3)``.
    """
    group, count = objects
    balance = energy_balance(graph, prediction, force, movable)
    node_copy = copy_of_objects(graph, objects)[group]  # [N]

    def per_copy(values: Tensor) -> Tensor:  # [N] -> [R]: sums over each copy (rows past the copies stay 0)
        return torch.zeros(count, dtype=torch.float64, device=group.device).index_add(0, node_copy, values)

    gained = torch.zeros(count, dtype=torch.float64, device=group.device).index_add(
        0, group, balance.next - balance.now)  # [R], per object
    work = per_copy(balance.work)
    surplus = per_copy(balance.next - balance.now) - work.clamp_min(0.0)
    gainer = (gained > 0)[group] & (balance.weight > 0)  # [N]
    w = torch.where(gainer, balance.weight, torch.zeros_like(balance.weight))
    a = per_copy(w * balance.g * balance.step[:, 2])
    b = per_copy(0.5 * w * balance.inv_dt2 * balance.step.square().sum(-1))
    # the pushes' work moves with the gainers' fraction too: W(alpha) = W_others + alpha W_gainers
    a = a - per_copy(torch.where(gainer & (work > 0)[node_copy], balance.work, torch.zeros_like(balance.work)))
    c = a + b - surplus
    root = (a.square() + 4.0 * b * c.clamp_min(0.0)).sqrt()
    fraction = torch.where(c > 0, 2.0 * c.clamp_min(0.0) / (a + root).clamp_min(torch.finfo(torch.float64).tiny),
                           torch.zeros_like(c)).clamp(0.0, 1.0)
    fraction = torch.where(surplus > 0, fraction, torch.ones_like(fraction))  # [copies]
    scale = torch.where(gainer, fraction[node_copy], torch.ones_like(balance.weight))  # [N]
    scaled = scale < 1
    if host_reads and not bool(scaled.any()):  # nothing to change
        return prediction
    store = graph[NODE]
    start = store.pos if prediction.prev_pos is None else prediction.prev_pos
    pos = start + scale.to(start.dtype).unsqueeze(-1) * (prediction.pos - start)
    pos = torch.where(scaled.unsqueeze(-1), pos, prediction.pos)
    touched = torch.zeros(count, dtype=torch.bool, device=group.device).index_fill_(0, group[scaled], True)[group]
    rigid = touched & store.material[:, RIGID].bool()
    if not host_reads or bool(rigid.any()):
        refit = rigid_leaf_positions(graph, pos, objects, rigid_from_rest)
        pos = torch.where(rigid.unsqueeze(-1), refit, pos)
    pos = leaf_to_ancestor_mean(pos, graph)
    pos = torch.where(touched.unsqueeze(-1), pos, prediction.pos)
    velocity = torch.where(touched.unsqueeze(-1), pos - start, prediction.velocity)
    fresh = to_local_velocity(velocity, graph[CHILD_TO_PARENT].edge_index)
    local = torch.where(touched.unsqueeze(-1), fresh, prediction.local_velocity)
    return Prediction(pos, local, velocity, prediction.prev_pos)


def scene_energy(positions: Tensor, mass: Tensor, dt: float = STEP_SECONDS, gravity: float = GRAVITY) -> Tensor:
    r"""Total energy :math:`E_t = \sum_i m_i (g z_i(t) + \tfrac12 \lVert x_i(t) - x_i(t-1) \rVert^2 / \Delta t^2)`
    of leaf trajectories, float64.

    **Shapes:** positions ``(..., T, L, 3)`` (``x_0 .. x_{T-1}``), mass ``(L,)`` (kg; 0 for static
    leaves) -> ``(..., T - 1)``, the energies at ``t = 1 .. T-1``.
    """
    x = positions.double()
    m = mass.double().to(x.device)
    velocity = (x[..., 1:, :, :] - x[..., :-1, :, :]) / dt
    return (m * (gravity * x[..., 1:, :, 2] + 0.5 * velocity.square().sum(-1))).sum(-1)
