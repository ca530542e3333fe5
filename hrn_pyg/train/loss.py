"""The loss of one window: the unrolled HRN terms, the rest terms, the GNS's acceleration loss, input noise."""

from __future__ import annotations

import math
from dataclasses import replace

import torch
from torch import Tensor
from torch_geometric.data import Batch, HeteroData

from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.data.graph import CHILD_TO_PARENT, NODE, RIGID, WITHIN_SIBLINGS, set_state
from hrn_pyg.losses import full_shape_loss, global_velocity_loss, group_shape_loss, local_velocity_loss, rest_velocity_loss, shape_groups
from hrn_pyg.nn.gns import GNS
from hrn_pyg.nn.hrn import HRN
from hrn_pyg.nn.pitch import collision_radius_of
from hrn_pyg.nn.state import to_local_velocity
from hrn_pyg.sim.rollout import iterate
from hrn_pyg.sim.step import root_of
from hrn_pyg.train.config import REST_ROLLOUT_DRAWS, TrainConfig


def batch_size_of(graph: HeteroData) -> int:
    if isinstance(graph, Batch):
        return int(graph.num_graphs)
    store = graph[NODE]
    return int(store.batch.max()) + 1 if "batch" in store and store.batch.numel() else 1


def window_loss(model: HRN, window: HeteroData, seq_len: int, config: TrainConfig,
                generator: torch.Generator | None = None,
                noise_generator: torch.Generator | None = None) -> tuple[Tensor, dict[str, float]]:
    r"""Loss of unrolling the model ``seq_len`` steps from a (batched) window.

    .. math::
        \mathcal{L} = \sum_{k=1}^{T} w_{loc}\mathcal{L}_{loc}^{(k)} + w_{glob}\mathcal{L}_{glob}^{(k)}
            + w_{shape}\mathcal{L}_{shape}^{(k)} \; [+\, w_{rest}\mathcal{L}_{rest}^{(k)}]

    Step ``k`` starts from the model's prediction of step ``k-1`` (the truth for ``k = 1``). Local
    and global terms are velocity errors over the velocity scale, the shape term the group or
    fully-connected pairwise-distance error, the rest term
    (:func:`~hrn_pyg.losses.rest_velocity_loss`) with ``config.w_rest > 0``. A
    :class:`~hrn_pyg.nn.gns.GNS` is scored by :func:`acceleration_loss`.
    """
    if isinstance(model, GNS):
        return acceleration_loss(model, window, config, generator, noise_generator)
    store = window[NODE]
    if "pos_seq" not in store or store.pos_seq.size(1) < seq_len + 3:
        have = store.pos_seq.size(1) - 3 if "pos_seq" in store else 0
        raise ValueError(f"window holds {have} future steps, the unroll needs {seq_len}")
    seq, forces = store.pos_seq, store.force_seq
    if config.rest_rollout > 0:
        seq = held_rest_sequence(model, window, seq_len, config.rest_rollout, config.rest_threshold, noise_generator,
                                 draw=config.rest_rollout_draw)
    inputs = seq[:, :3]
    if config.input_noise > 0:
        inputs = inputs + input_noise(window, config.input_noise, noise_generator)
    radius = collision_radius_of(model.config, window)  # one per window when their pitches differ
    graph = set_state(window, inputs[:, 0], inputs[:, 1], inputs[:, 2], radius=radius)
    norm = model.normalizer
    vel_scale = norm.velocity_std
    shape_scale = vel_scale.mean()
    c2p = window[CHILD_TO_PARENT].edge_index
    leaf_index, groups = shape_groups(window)
    # rigid bodies under the rigid fit keep their input's distances: no gradient to compute
    fixed_shape = store.material[leaf_index, RIGID].bool() if getattr(model.config, "rigid_fit", False) else None
    copies = batch_size_of(window)
    parts = {"local": seq.new_zeros(()), "global": seq.new_zeros(()), "shape": seq.new_zeros(())}
    if config.w_rest > 0:
        parts["rest"] = seq.new_zeros(())
    total = seq.new_zeros(())
    masks_fn = None
    if config.train_dropout > 0:  # one mask per copy per step, drawn as the step starts
        def masks_fn(t: int, g: HeteroData) -> dict[str, Tensor]:
            return model.sample_masks(copies, config.train_dropout, generator)
    unrolled = iterate(model, graph, seq_len, forces.transpose(0, 1), masks_fn, sleep=None)
    for k, result in enumerate(unrolled):  # unrolled time steps, with gradients through all of them
        # the first target is measured from the (possibly noisy) input, later ones from the truth
        true_prev, true_next = (graph[NODE].pos if k == 0 else seq[:, k + 2]), seq[:, k + 3]
        true_local = to_local_velocity(true_next - true_prev, c2p)
        loss_local = local_velocity_loss(result.local_velocity, true_local, store.is_root, store.is_static, norm)
        loss_global = global_velocity_loss(result.pos, true_next, store.is_root, store.is_leaf, store.is_static, vel_scale)
        if config.shape_loss == "full":
            loss_shape = full_shape_loss(result.pos[leaf_index], true_next[leaf_index], groups,
                                         config.shape_chunk, shape_scale, fixed_shape)
        else:
            loss_shape = group_shape_loss(result.pos, true_next, window[WITHIN_SIBLINGS].edge_index, shape_scale)
        total = total + config.w_local * loss_local + config.w_global * loss_global + config.w_shape * loss_shape
        parts["local"] = parts["local"] + loss_local.detach()
        parts["global"] = parts["global"] + loss_global.detach()
        parts["shape"] = parts["shape"] + loss_shape.detach()
        if config.w_rest > 0:  # objects the truth has still: their own velocity error, absolute
            loss_rest = rest_velocity_loss(result.pos - graph[NODE].pos, true_next - seq[:, k + 2], store.is_root,
                                           store.is_static, config.rest_threshold, vel_scale)
            total = total + config.w_rest * loss_rest
            parts["rest"] = parts["rest"] + loss_rest.detach()
        graph = result.graph
    # one host transfer for the logged parts
    values = torch.stack(list(parts.values())).tolist()
    return total, dict(zip(parts, values))


def resting_windows(window: HeteroData, seq_len: int, threshold: float) -> Tensor:
    r"""``[B]`` bool: the windows at rest over the frames an unroll of ``seq_len`` reads:

    .. math::
        \max_{i \text{ moving leaf of } b} \ \max_{0 \le t \le T + 2} \lVert x_i(t) - x_i(0) \rVert < \tau
    """
    store = window[NODE]
    frames = store.pos_seq[:, : seq_len + 3]
    moved = (frames - frames[:, :1]).norm(dim=-1).amax(dim=1)  # [N]
    moved = torch.where(store.is_leaf & ~store.is_static, moved, torch.zeros_like(moved))
    batch = store.batch if "batch" in store else torch.zeros_like(moved, dtype=torch.long)
    count = batch_size_of(window)
    farthest = moved.new_zeros(count).scatter_reduce(0, batch, moved, "amax")
    return farthest < threshold


def rest_rollout_length(max_steps: int, draw: str = "uniform", generator: torch.Generator | None = None) -> int:
    r"""One rollout length :math:`R \in \{1, \dots, R_{max}\}` of :func:`held_rest_sequence`:
    ``uniform``, or ``log``: :math:`R = \lfloor (R_{max} + 1)^u \rfloor`, :math:`u \sim U[0, 1)`, so
    :math:`P(R = k) = \ln\frac{k + 1}{k} / \ln(R_{max} + 1)` and every doubling of R is about as
    likely as the last (mean :math:`\approx R_{max} / \ln R_{max}` rather than :math:`R_{max} / 2`)."""
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    if draw == "uniform":
        return int(torch.randint(1, max_steps + 1, (1,), generator=generator))
    if draw == "log":
        u = float(torch.rand((), generator=generator, dtype=torch.float64))
        return min(max(int(math.floor((max_steps + 1) ** u)), 1), max_steps)
    raise ValueError(f"draw must be one of {REST_ROLLOUT_DRAWS}, got {draw!r}")


def held_rest_sequence(model: HRN, window: HeteroData, seq_len: int, max_steps: int, threshold: float,
                       generator: torch.Generator | None = None, draw: str = "uniform") -> Tensor:
    r"""The window's ``pos_seq`` ``[N, T+3, 3]`` with each scene at rest (:func:`resting_windows`)
    replaced by the model's own rollout from it, then the order to hold still there:

    .. math::
        \bigl(\hat x(R-2),\ \hat x(R-1),\ \hat x(R),\ \hat x(R),\ \dots,\ \hat x(R)\bigr)

    with :math:`R` drawn from ``1..max_steps`` per batch (:func:`rest_rollout_length`; no gradient,
    dropout, sleeping or force). The model so sees the states its own drift leads to.
    """
    store = window[NODE]
    seq = store.pos_seq
    resting = resting_windows(window, seq_len, threshold)
    if not bool(resting.any()):
        return seq
    steps = rest_rollout_length(max_steps, draw, generator)
    batch = store.batch if "batch" in store else torch.zeros(seq.size(0), dtype=torch.long, device=seq.device)
    rows = resting[batch]  # [N]: the nodes of the resting windows
    still = window
    if isinstance(window, Batch) and not bool(resting.all()):  # roll the resting graphs alone
        still = Batch.from_data_list(window.index_select(torch.nonzero(resting).flatten()))
    start = still[NODE].pos_seq
    radius = collision_radius_of(model.config, still)
    with torch.no_grad():
        graph = set_state(still, start[:, 0], start[:, 1], start[:, 2], radius=radius)
        frames = [start[:, 0], start[:, 1], start[:, 2]]
        for result in iterate(model, graph, steps, None, None, sleep=None):
            frames = [frames[1], frames[2], result.pos]
    held = torch.stack(frames + [frames[-1]] * (seq.size(1) - 3), dim=1)  # [N', T+3, 3]
    out = seq.clone()
    out[rows] = held[rows] if still is window else held
    return out


def acceleration_loss(model: GNS, window: HeteroData, config: TrainConfig,
                      generator: torch.Generator | None = None,
                      noise_generator: torch.Generator | None = None) -> tuple[Tensor, dict[str, float]]:
    r"""The GNS's one-step loss: mean squared error of the normalised acceleration over moving leaves.

    .. math::
        \mathcal{L} = \Bigl\langle \bigl((\hat x_{t+1} - \tilde x_t) - (x_{t+1} - x_t)\bigr)^2
            / \sigma_a^2 \Bigr\rangle

    with noisy inputs :math:`\tilde x = x + n` (:func:`input_noise`, none on static leaves): the
    GNS paper's target, so the model learns to undo velocity noise, not position noise.
    """
    store = window[NODE]
    if "pos_seq" not in store or store.pos_seq.size(1) < 4:
        raise ValueError("acceleration_loss: the window holds no future step")
    seq = store.pos_seq
    inputs = seq[:, :3]
    if config.input_noise > 0:
        inputs = inputs + input_noise(window, config.input_noise, noise_generator, rigid_shift=False)
    graph = set_state(window, inputs[:, 0], inputs[:, 1], inputs[:, 2], radius=None)  # iterate searches
    masks_fn = None
    if config.train_dropout > 0:
        copies = batch_size_of(window)

        def masks_fn(t: int, g: HeteroData) -> dict[str, Tensor]:
            return model.sample_masks(copies, config.train_dropout, generator)
    forces = store.force_seq[:, :1].transpose(0, 1)
    result = next(iterate(model, graph, 1, forces, masks_fn, sleep=None))
    moving = store.is_leaf & ~store.is_static
    error = (result.pos - graph[NODE].pos) - (seq[:, 3] - seq[:, 2])
    loss = (error[moving] / model.acceleration_std).square().mean()
    return loss, {"acceleration": float(loss.detach())}


def input_noise(window: HeteroData, std: float, generator: torch.Generator | None = None,
                rigid_shift: bool = True) -> Tensor:
    r"""Random-walk noise for the three input positions of a window, ``[N, 3, 3]``.

    .. math::
        n_{t-2} = \epsilon_0, \quad n_{t-1} = \epsilon_0 + \epsilon_1, \quad
        n_t = \epsilon_0 + \epsilon_1 + \epsilon_2, \qquad \epsilon_k \sim \mathcal{N}(0, \sigma^2 / 3)

    A rigid object's leaves share their root's draw (``rigid_shift=False``: their own), static
    particles get none.
    """
    store = window[NODE]
    n = store.num_nodes
    device = store.pos_seq.device
    steps = torch.randn(n, 3, 3, generator=generator, device="cpu" if generator is not None else device)
    walk = steps.to(device).cumsum(dim=1) * (std / math.sqrt(3.0))
    if rigid_shift:
        rigid = store.material[:, RIGID].bool()
        walk = torch.where(rigid[:, None, None], walk[root_of(window)], walk)
    return torch.where(store.is_static[:, None, None], torch.zeros_like(walk), walk)


@torch.no_grad()
def validation_loss(model: HRN, dataset: EpisodeWindows, ids: list[int], seq_len: int, config: TrainConfig) -> float:
    """Mean unrolled loss on fixed validation windows (no dropout, no input noise, no rest term:
    the deterministic model's loss, comparable between runs of different settings)."""
    was_training = model.training
    model.eval()
    device = next(model.parameters()).device
    batch = Batch.from_data_list([dataset[i] for i in ids]).to(device)
    scored = replace(config, train_dropout=0.0, input_noise=0.0, w_rest=0.0, rest_rollout=0)
    loss, _ = window_loss(model, batch, seq_len, scored)
    model.train(was_training)
    return float(loss) / seq_len
