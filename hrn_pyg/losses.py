"""Training losses of the HRN: local and global velocity errors, two shape terms and the rest term.

The group shape loss is the baseline HRN's (siblings of one parent); the fully-connected one is
the seed paper's (all leaf pairs of an object), computed in row chunks with each chunk's
gradient formed with its value, so memory stays bounded by ``chunk_size`` times the largest
object, forward and backward.
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
    scale for roots and its local scale otherwise (the MSE of the normalised output against
    :func:`hrn_pyg.sim.step.target_output`).

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

    ``scale`` :math:`\sigma`: a number or ``(3,)`` (e.g. the normaliser's ``velocity_std``).

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

    An absolute error keeps pulling a resting object's slow creep to zero, which squared errors
    hardly see. ``scored``: the roots, or roots and leaves (a soft body's shape too). Zero when
    nothing rests.

    **Shapes:** pred_velocity, true_velocity :math:`(N, 3)`; masks :math:`(N,)`; returns a scalar.
    """
    resting = scored & ~is_static & (true_velocity.norm(dim=-1) < threshold)
    err = ((pred_velocity - true_velocity) / scale)[resting]
    return err.abs().mean() if err.numel() else _zero(pred_velocity)


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
    :math:`\bar d_{ij}` true. The columns start at the rows' first leaf: :math:`w_{ij} = 1` for the
    first ``diagonal`` columns (the square block) and 2 beyond. Only the gradients ``[R, 3]`` and
    ``[C, 3]`` are kept for the backward pass, so the ``R x C`` distances are freed at once.

    **Shapes:** pred rows :math:`(R, 3)`, pred columns :math:`(C, 3)`, true rows and columns the
    same (constants); returns a scalar.
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
    """Sum of squared distance errors over every ordered pair of the groups under
    :data:`SMALL_GROUP` rows (sorted by group; ``counts``, ``starts`` their sizes and first rows),
    padded to one size and taken about ``chunk_size * SMALL_GROUP`` pairs at a time."""
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

    :math:`g` runs over the groups (:func:`shape_groups`). A group of :data:`SMALL_GROUP` leaves or
    more is taken ``chunk_size`` rows at a time against its own later rows
    (:class:`_PairDistanceError`), so at most one ``chunk_size x (largest group)`` block is alive;
    smaller groups are padded and taken together (:func:`_small_groups_error`). Exact.

    ``fixed`` marks groups whose distances the network cannot change (rigid objects under the rigid
    fit): their pairs count in :math:`P` but their constant errors are not computed.

    **Shapes:** pred_pos, true_pos :math:`(L, 3)`; group :math:`(L,)` long; fixed :math:`(L,)`
    bool, the same within a group; returns a scalar.
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
    """Leaves that enter the shape loss (non-static) and their group, one per object per batch copy:
    ``(leaf_index [L'], group [L'])``."""
    store = graph[NODE]
    leaf = torch.nonzero(store.is_leaf & ~store.is_static).flatten()
    obj = store.object[leaf]
    if "batch" in store:
        obj = copy_object_ids(store.batch[leaf], obj, object_span(store.object))
    return leaf, obj
