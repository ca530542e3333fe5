"""Training losses of the HRN: local and global velocity errors, two shape terms and a scoring rule.

The group shape loss is the baseline HRN's (distances between siblings of one parent only); the
fully-connected shape loss is the seed paper's (distances between all leaf pairs of an object),
computed object by object in row chunks, each chunk's gradient formed with its value, so its memory
stays bounded by ``chunk_size`` times the size of the largest object (and a few numbers per pair of
each object under 64 leaves), in the forward and the backward pass.
:func:`fair_energy_score` scores K sampled futures against the one observed future (the
stochastic training mode of :mod:`hrn_pyg.train`, ``sample_copies``).
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.data.graph import NODE, copy_object_ids, object_span
from hrn_pyg.nn.collision import safe_norm
from hrn_pyg.nn.normalizer import Normalizer

#: rows of the pairwise-distance matrix handled at once by :func:`full_shape_loss`
DEFAULT_CHUNK_SIZE = 512
#: objects of fewer leaves are padded and taken together by :func:`full_shape_loss`
SMALL_GROUP = 64
#: smoothing length of the norm in :func:`fair_energy_score` (in the units of its inputs)
ENERGY_EPSILON = 1e-6


def _zero(like: Tensor) -> Tensor:
    """A zero loss that still carries the graph of ``like`` (so ``backward`` works)."""
    return like.sum() * 0.0


def local_velocity_loss(
    pred_local: Tensor,
    true_local: Tensor,
    is_root: Tensor,
    is_static: Tensor,
    normalizer: Normalizer,
) -> Tensor:
    r"""Mean squared error of local velocities, in target units.

    .. math::
        \mathcal{L}_{loc} = \frac{1}{3|\mathcal{M}|} \sum_{i \in \mathcal{M}}
            \Bigl\lVert \frac{\hat v^{loc}_i - v^{loc}_i}{\sigma_{r(i)}} \Bigr\rVert^2

    over the non-static nodes :math:`\mathcal{M}`; :math:`\sigma_{r(i)}` is the normaliser's root
    scale for roots (global frame) and its local scale otherwise (parent frame). Equal to the MSE
    of the normalised network output against :func:`hrn_pyg.sim.step.target_output`.

    **Shapes:** pred_local, true_local :math:`(N, 3)`; is_root, is_static :math:`(N,)`; returns a scalar.
    """
    _, std = normalizer.target_stats(is_root)
    err = ((pred_local - true_local) / std)[~is_static]
    return err.pow(2).mean() if err.numel() else _zero(pred_local)


def global_velocity_loss(
    pred_velocity: Tensor,
    true_velocity: Tensor,
    is_root: Tensor,
    is_leaf: Tensor,
    is_static: Tensor,
    scale: Tensor | float = 1.0,
) -> Tensor:
    r"""Mean squared error of global velocities of the roots and the leaves.

    .. math::
        \mathcal{L}_{glob} = \frac{1}{3|\mathcal{G}|} \sum_{i \in \mathcal{G}}
            \Bigl\lVert \frac{\hat v_i - v_i}{\sigma} \Bigr\rVert^2, \qquad
        \mathcal{G} = \{i : (\mathrm{root}_i \lor \mathrm{leaf}_i) \land \lnot \mathrm{static}_i\}

    ``scale`` :math:`\sigma` is a number or a ``(3,)`` tensor (e.g. the normaliser's
    ``velocity_std``).

    **Shapes:** pred_velocity, true_velocity :math:`(N, 3)`; masks :math:`(N,)`; returns a scalar.
    """
    keep = (is_root | is_leaf) & ~is_static
    err = ((pred_velocity - true_velocity) / scale)[keep]
    return err.pow(2).mean() if err.numel() else _zero(pred_velocity)


def rest_velocity_loss(
    pred_velocity: Tensor,
    true_velocity: Tensor,
    scored: Tensor,
    is_static: Tensor,
    threshold: float,
    scale: Tensor | float = 1.0,
) -> Tensor:
    r"""Mean absolute velocity error of the objects (or nodes) that are at rest in the ground truth.

    .. math::
        \mathcal{L}_{rest} = \frac{1}{3|\mathcal{R}|} \sum_{i \in \mathcal{R}}
            \Bigl\lVert \frac{\hat v_i - v_i}{\sigma} \Bigr\rVert_1, \qquad
        \mathcal{R} = \{i : \mathrm{scored}_i \land \lnot \mathrm{static}_i \land \lVert v_i \rVert < \tau\}

    The squared errors of :func:`global_velocity_loss` hardly see a resting object's creep of
    a tenth of a millimetre per step (about 1 % of a typical velocity scale, so 1e-4 of the loss),
    yet over a thousand steps it slides it by decimetres. An absolute error keeps a constant pull
    towards zero error however small the creep is, and only for objects that should be still.
    ``scored`` picks the nodes the term looks at: the roots (``is_root``, one per object), or
    roots and leaves, which also holds still the resting leaves of a soft body (whose shape
    creeps although its centre stays). Zero when nothing rests.

    **Shapes:** pred_velocity, true_velocity :math:`(N, 3)`; masks :math:`(N,)`; returns a scalar.
    """
    resting = scored & ~is_static & (true_velocity.norm(dim=-1) < threshold)
    err = ((pred_velocity - true_velocity) / scale)[resting]
    return err.abs().mean() if err.numel() else _zero(pred_velocity)


def contact_loss(pred_pos: Tensor, true_pos: Tensor, collision_edges: Tensor,
                 scale: Tensor | float = 1.0, floor: Tensor | float | None = None) -> Tensor:
    r"""Mean shortfall of the predicted distance of touching leaf pairs under the true distance.

    .. math::
        \mathcal{L}_{contact} = \frac{1}{|\mathcal{C}|} \sum_{(i, j) \in \mathcal{C}}
            \frac{\max\bigl(0,\ \min(\lVert x_i - x_j \rVert, f_{ij}) - \lVert \hat x_i - \hat x_j \rVert\bigr)}{\sigma}

    over :math:`\mathcal{C}`, the collision pairs (leaves of different objects within the
    collision radius) of the predicted state. A pair the model brings closer than the truth has it
    is one leaf on its way into the other's object, which is how a cloth ends up inside what it
    falls on; the squared position errors see a shortfall of a fraction of a pitch hardly at all,
    and see it no differently from the same error sideways. The term is zero for pairs the model
    keeps at least as far apart as the truth, and zero when nothing touches. Without a floor
    (:math:`f = \infty`) every touching pair is held to its true distance, which pushes pairs
    apart on average (the term is one-sided); a ``floor`` :math:`f_{ij}` (metres, per pair or one
    number) asks only that a pair be no closer than its true distance or :math:`f_{ij}`,
    whichever is smaller, so pairs the model keeps farther than the floor cost nothing.

    **Shapes:** pred_pos, true_pos :math:`(N, 3)`; collision_edges :math:`(2, E)`; floor a
    number or :math:`(E,)`; returns a scalar.
    """
    if collision_edges.numel() == 0:
        return _zero(pred_pos)
    i, j = collision_edges
    pred_distance = safe_norm(pred_pos[i] - pred_pos[j], keepdim=False)
    target = (true_pos[i] - true_pos[j]).norm(dim=-1)
    if floor is not None:
        target = torch.minimum(target, torch.as_tensor(floor, dtype=target.dtype, device=target.device))
    return (torch.relu(target - pred_distance) / scale).mean()


def ground_loss(pred_pos: Tensor, true_pos: Tensor, moving_leaf: Tensor, floor: Tensor | float,
                scale: Tensor | float = 1.0) -> Tensor:
    r"""Mean depth by which the predicted leaves sink under a floor near the ground plane.

    .. math::
        \mathcal{L}_{ground} = \frac{1}{|\mathcal{M}|} \sum_{i \in \mathcal{M}}
            \frac{\max\bigl(0,\ \min(z_i, f_i) - \hat z_i\bigr)}{\sigma}

    over :math:`\mathcal{M}`, the moving leaves, with :math:`z` the true and :math:`\hat z` the
    predicted height above the ground plane :math:`z = 0` and :math:`f_i` the floor (metres, per
    leaf or one number; 0 is the plane itself, a negative floor lies under it). A leaf is held from
    below to its true height or the floor, whichever is lower, so the term is zero for every leaf
    the model keeps at least that high, and a leaf well above the floor is free to move down to
    it. It is one-sided and absolute: a soft body at rest whose leaves creep into the ground by a
    tenth of a millimetre a step (a squared error hardly sees it) feels a constant pull up. A
    floor above the resting leaves' true heights holds every one of them from below and lifts
    resting objects on average (their small errors count on one side only); a floor at or under
    the plane asks only that no leaf end in the ground. Zero when no leaf sinks.

    **Shapes:** pred_pos, true_pos :math:`(N, 3)`; moving_leaf :math:`(N,)` bool; floor a number
    or :math:`(N,)`; returns a scalar.
    """
    floor = torch.as_tensor(floor, dtype=true_pos.dtype, device=true_pos.device).expand(true_pos.size(0))
    true_z, pred_z, floor = true_pos[moving_leaf, 2], pred_pos[moving_leaf, 2], floor[moving_leaf]
    if true_z.numel() == 0:
        return _zero(pred_pos)
    return (torch.relu(torch.minimum(true_z, floor) - pred_z) / scale).mean()


def group_shape_loss(
    pred_pos: Tensor,
    true_pos: Tensor,
    within_siblings: Tensor,
    scale: Tensor | float = 1.0,
) -> Tensor:
    r"""Baseline HRN shape loss: pairwise-distance error between siblings of one parent.

    .. math::
        \mathcal{L}_{group} = \frac{1}{|\mathcal{E}_{WS}|} \sum_{(j, i) \in \mathcal{E}_{WS}}
            \Bigl(\frac{\lVert \hat x_i - \hat x_j \rVert - \lVert x_i - x_j \rVert}{\sigma}\Bigr)^2

    over the ``within_siblings`` edges (every level of the tree).

    **Shapes:** pred_pos, true_pos :math:`(N, 3)`; within_siblings :math:`(2, E)`; returns a scalar.
    """
    if within_siblings.size(1) == 0:
        return _zero(pred_pos)
    src, dst = within_siblings
    d_pred = safe_norm(pred_pos[dst] - pred_pos[src], keepdim=False)
    d_true = safe_norm(true_pos[dst] - true_pos[src], keepdim=False)
    return ((d_pred - d_true) / scale).pow(2).mean()


class _PairDistanceError(torch.autograd.Function):
    r"""Weighted sum of squared distance errors over a block of leaf pairs, with its gradient
    formed in the forward pass.

    .. math::
        E = \sum_{i \in R} \sum_{j \in C} w_{ij} (d_{ij} - \bar d_{ij})^2, \qquad
        \frac{\partial E}{\partial \hat x_i} = \sum_j g_{ij} (\hat x_i - \hat x_j), \qquad
        g_{ij} = \frac{2 w_{ij} (d_{ij} - \bar d_{ij})}{d_{ij}}

    with :math:`d_{ij} = \sqrt{\lVert \hat x_i - \hat x_j \rVert^2 + \epsilon}` predicted and
    :math:`\bar d_{ij}` true (the norm of :func:`~hrn_pyg.nn.collision.safe_norm`). The columns
    start at the rows' first leaf: :math:`w_{ij} = 1` for the first ``diagonal`` columns (the
    square block of the rows with themselves, every pair in both orders) and 2 beyond (pairs whose
    reverse order no later block visits). Only the two gradients, ``[R, 3]`` and ``[C, 3]``, are
    kept for the backward pass, so a block's ``R x C`` distances are freed as soon as it is summed,
    and the gradient's sums over ``j`` are matrix products.

    **Shapes:** pred rows :math:`(R, 3)`, pred columns :math:`(C, 3)`, true rows and columns the
    same; returns a scalar. The true positions are constants (no gradient).
    """

    @staticmethod
    def forward(ctx, p_rows: Tensor, p_cols: Tensor, t_rows: Tensor, t_cols: Tensor, diagonal: int) -> Tensor:
        d_pred = safe_norm(p_rows[:, None, :] - p_cols[None, :, :], keepdim=False)
        d_true = safe_norm(t_rows[:, None, :] - t_cols[None, :, :], keepdim=False)
        error = d_pred - d_true
        weight = torch.full((1, p_cols.size(0)), 2.0, dtype=error.dtype, device=error.device)
        weight[:, :diagonal] = 1.0
        weighted = error * weight
        if ctx.needs_input_grad[0] or ctx.needs_input_grad[1]:
            g = 2.0 * weighted / d_pred
            grad_rows = g.sum(1, keepdim=True) * p_rows - g @ p_cols
            grad_cols = g.sum(0).unsqueeze(1) * p_cols - g.T @ p_rows
            ctx.save_for_backward(grad_rows, grad_cols)
        return (weighted * error).sum()

    @staticmethod
    def backward(ctx, grad_output: Tensor) -> tuple[Tensor | None, ...]:
        grad_rows, grad_cols = ctx.saved_tensors
        return grad_rows * grad_output, grad_cols * grad_output, None, None, None


def _small_groups_error(p: Tensor, t: Tensor, counts: Tensor, starts: Tensor, chunk_size: int) -> Tensor:
    """Sum of squared distance errors over every ordered pair of the groups of fewer than
    :data:`SMALL_GROUP` rows (``p``, ``t`` sorted by group; ``counts`` and ``starts`` the groups'
    sizes and first rows): the groups padded to one size ``m`` and taken together, about ``chunk_size * SMALL_GROUP`` pairs
    at a time, so that many small objects cost a few tensor operations, not a loop over them."""
    small = (counts >= 2) & (counts < SMALL_GROUP)
    if not bool(small.any()):
        return p.new_zeros(())
    sizes, starts = counts[small], starts[small]
    m = int(sizes.max())
    slot = torch.arange(m, device=p.device)
    valid = slot[None, :] < sizes[:, None]  # [G, m]
    index = torch.where(valid, starts[:, None] + slot[None, :], 0)
    per_slice = max(1, (chunk_size * SMALL_GROUP) // (m * m))
    total = p.new_zeros(())
    for g0 in range(0, index.size(0), per_slice):
        rows, ok = index[g0:g0 + per_slice], valid[g0:g0 + per_slice]
        p_s, t_s = p[rows], t[rows]  # [G', m, 3]
        d_pred = safe_norm(p_s[:, :, None, :] - p_s[:, None, :, :], keepdim=False)
        d_true = safe_norm(t_s[:, :, None, :] - t_s[:, None, :, :], keepdim=False)
        pair = ok[:, :, None] & ok[:, None, :]
        total = total + ((d_pred - d_true).pow(2) * pair).sum()
    return total


def full_shape_loss(
    pred_pos: Tensor,
    true_pos: Tensor,
    group: Tensor,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    scale: Tensor | float = 1.0,
    fixed: Tensor | None = None,
) -> Tensor:
    r"""Fully-connected shape loss (seed paper, Fig. 3 right): all leaf pairs of each object.

    .. math::
        \mathcal{L}_{full} = \frac{1}{P} \sum_{g} \sum_{i \ne j \in g}
            \Bigl(\frac{\lVert \hat x_i - \hat x_j \rVert - \lVert x_i - x_j \rVert}{\sigma}\Bigr)^2,
        \qquad P = \sum_g |g| (|g| - 1)

    :math:`g` runs over the groups (one object of one batch copy, see :func:`shape_groups`).
    A group of :data:`SMALL_GROUP` leaves or more is taken on its own, its rows at most
    ``chunk_size`` (and half the group) at a time against its own later rows only: a pair in two
    chunks is visited once and counted twice, so about half of the :math:`|g|^2` distances are
    formed and no pair of two groups is. Such a block's gradient is formed with its value
    (:class:`_PairDistanceError`), so at most one ``chunk_size x (largest group)`` block of
    distances is alive at any time, in the forward and the backward pass. Smaller groups are
    padded to one size and taken together under autograd, which keeps their distances for the
    backward pass (fewer than :data:`SMALL_GROUP` squared pairs each). Exact: every pair is
    counted once per order, as in the formula.

    ``fixed`` marks the rows of groups whose predicted distances the network cannot change: the
    leaves of a rigid object under the model's rigid fit move by one rigid motion of their
    current positions, so their distances are those of the step's input. Such a group's pairs
    still count in :math:`P` but their (constant) errors are not computed: the gradient is the
    same and the value lower by their constant part.

    **Shapes:** pred_pos, true_pos :math:`(L, 3)` (typically leaves); group :math:`(L,)` long;
    fixed :math:`(L,)` bool, the same for every row of a group; returns a scalar.
    """
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
    if pred_pos.shape != true_pos.shape or pred_pos.dim() != 2 or group.shape != pred_pos.shape[:1]:
        raise ValueError(
            f"full_shape_loss: pred_pos, true_pos [L, 3] and group [L] expected, got "
            f"{tuple(pred_pos.shape)}, {tuple(true_pos.shape)}, {tuple(group.shape)}"
        )
    if fixed is not None and fixed.shape != group.shape:
        raise ValueError(f"full_shape_loss: fixed must be [L] like group, got {tuple(fixed.shape)}")
    _, all_counts = torch.unique(group, return_counts=True)
    n_pairs = int((all_counts * (all_counts - 1)).sum())
    if fixed is not None:
        pred_pos, true_pos, group = pred_pos[~fixed], true_pos[~fixed], group[~fixed]
    order = torch.argsort(group, stable=True)
    g, p, t = group[order], pred_pos[order] / scale, true_pos[order] / scale
    t = t.detach()
    _, counts = torch.unique_consecutive(g, return_counts=True)
    if n_pairs == 0 or int((counts * (counts - 1)).sum()) == 0:
        return _zero(pred_pos)
    starts = torch.cumsum(counts, 0) - counts
    total = _small_groups_error(p, t, counts, starts, chunk_size)
    for start, count in zip(starts.tolist(), counts.tolist()):  # a loop over objects and row chunks, not particles
        if count >= SMALL_GROUP:
            # centred on the object (the loss does not see a translation): smaller numbers in the
            # gradient's matrix products; the centre is a constant, so the gradient is unchanged
            centre = p[start:start + count].detach().mean(0)
            p_g, t_g = p[start:start + count] - centre, t[start:start + count]
            rows = min(chunk_size, (count + 1) // 2)
            for r0 in range(0, count, rows):
                r1 = min(r0 + rows, count)
                total = total + _PairDistanceError.apply(p_g[r0:r1], p_g[r0:], t_g[r0:r1], t_g[r0:], r1 - r0)
    return total / n_pairs


def shape_groups(graph: HeteroData) -> tuple[Tensor, Tensor]:
    """Leaves that enter the shape loss and their group: one group per object per batch copy.

    Static leaves are left out (they never move). Returns ``(leaf_index [L'], group [L'])``.
    """
    store = graph[NODE]
    leaf = torch.nonzero(store.is_leaf & ~store.is_static).flatten()
    obj = store.object[leaf]
    if "batch" in store:
        obj = copy_object_ids(store.batch[leaf], obj, object_span(store.object))
    return leaf, obj


def _smooth_distance(diff: Tensor, eps: float) -> Tensor:
    """:math:`\\sqrt{\\lVert d \\rVert^2 + \\epsilon^2} - \\epsilon` over the last dimension: 0 at
    ``d = 0`` with gradient 0 there (finite), within ``eps`` of the Euclidean norm everywhere."""
    return torch.sqrt(diff.pow(2).sum(dim=-1) + eps * eps) - eps


def fair_energy_score(
    samples: Tensor,
    truth: Tensor,
    scale: Tensor | float = 1.0,
    eps: float = ENERGY_EPSILON,
) -> Tensor:
    r"""Fair (unbiased) energy score of ``K >= 2`` samples against one observation (lower is better).

    With :math:`X_k` the samples and :math:`y` the observation, both divided by ``scale``
    :math:`\sigma` (a number or a per-axis ``(D,)`` tensor, e.g. the velocity scale):

    .. math::
        \mathrm{ES} = \frac{1}{K} \sum_{k=1}^{K} \lVert X_k - y \rVert
            \; - \; \frac{1}{2K(K-1)} \sum_{k \ne l} \lVert X_k - X_l \rVert

    This is the unbiased estimate of :math:`E\lVert X - y\rVert - \tfrac12 E\lVert X - X'\rVert` for
    :math:`X, X' \sim F` independent: its expectation over the samples is the energy score of
    their distribution :math:`F` itself, which is proper: in expectation over :math:`y \sim G`
    it is smallest for :math:`F = G`, so a model trained on it is pulled towards the spread of the
    data. (The plug-in form with :math:`1/(2K^2)`, :func:`hrn_pyg.sampling.metrics.energy_score`,
    under-weights the spread by :math:`(K-1)/K` and so rewards too-narrow samples at small K.)
    The norms are smoothed, :math:`\sqrt{\lVert d\rVert^2 + \epsilon^2} - \epsilon`, so the gradient is
    finite (zero) where two samples or a sample and the observation coincide; the value moves by
    less than ``eps`` per norm. Vectorised: every index of the middle dimensions is scored on
    its own (e.g. one 3-D score per particle).

    **Shapes:** samples ``(K, *, D)``, truth ``(*, D)``, scale a number or ``(D,)``; returns ``(*)``.
    """
    if samples.dim() < 2 or samples.shape[0] < 2:
        raise ValueError(f"fair_energy_score: samples must be [K>=2, ..., D], got {tuple(samples.shape)}")
    if truth.shape != samples.shape[1:]:
        raise ValueError(
            f"fair_energy_score: truth must be {tuple(samples.shape[1:])} (one observation), got {tuple(truth.shape)}"
        )
    k = samples.shape[0]
    x, y = samples / scale, truth / scale
    to_truth = _smooth_distance(x - y.unsqueeze(0), eps).mean(dim=0)
    # the diagonal k = l is 0 and drops out of the sum; each unordered pair counted twice
    pairs = _smooth_distance(x.unsqueeze(0) - x.unsqueeze(1), eps).sum(dim=(0, 1))
    return to_truth - pairs / (2 * k * (k - 1))
