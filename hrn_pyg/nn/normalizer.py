"""Normalisation statistics of the HRN's inputs and targets, fitted once on training data.

The statistics are buffers of :class:`Normalizer` (saved with every checkpoint), computed by
:func:`fit_normalizer`; nothing is estimated at inference. Unfitted, it is the identity.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch
from torch import Tensor, nn
from torch_geometric.data import HeteroData

from hrn_pyg.data.graph import CHILD_TO_PARENT, NODE, node_pitch
from hrn_pyg.nn.state import to_local_velocity

#: a column whose training values span at most this fraction of their largest magnitude "never
#: varies" (e.g. one mass for every particle; a few float32 rounding steps) and gets the scale of
#: its quantity's other columns (1 if it has none), so an unseen value is not blown up by 1/0. Relative, not absolute: a scene in micrometres has real
#: velocity spreads far below any fixed epsilon, and forcing them to 1 m/step made a fitted model
#: fly apart (tests/stability, small scales)
STD_EPSILON = 5e-7

#: floor under masses before the logarithm (static bodies may carry zero mass)
MASS_FLOOR = 1e-8


class Normalizer(nn.Module):
    r"""Explicit input and target statistics of the model.

    Inputs: velocity :math:`(v - \mu_v) / \sigma_v`, force :math:`f / \sigma_f` (zero stays zero),
    height :math:`(z - \mu_z) / \sigma_z`, log mass :math:`(\log m - \mu_m) / \sigma_m`, edge
    offsets :math:`\Delta x / \ell`. Targets: :math:`\delta_i = v^{loc}_i(t+1) - v^{loc}_i(t)`,
    standardised with :math:`(\mu_{loc}, \sigma_{loc})` (parent frame) or
    :math:`(\mu_{root}, \sigma_{root})` for roots (global frame).

    **Shapes:** every buffer is :math:`(3,)` (per axis) or :math:`(1,)`; ``fitted`` is a bool scalar.
    """

    def __init__(self) -> None:
        super().__init__()
        for name, dim in (
            ("velocity_mean", 3), ("local_mean", 3), ("root_mean", 3),
            ("height_mean", 1), ("log_mass_mean", 1),
        ):
            self.register_buffer(name, torch.zeros(dim))
        for name, dim in (
            ("velocity_std", 3), ("force_std", 3), ("local_std", 3), ("root_std", 3),
            ("height_std", 1), ("log_mass_std", 1), ("length_scale", 1),
        ):
            self.register_buffer(name, torch.ones(dim))
        self.register_buffer("fitted", torch.tensor(False))

    def velocity(self, v: Tensor) -> Tensor:
        return (v - self.velocity_mean) / self.velocity_std

    def force(self, f: Tensor) -> Tensor:
        return f / self.force_std

    def height(self, z: Tensor) -> Tensor:
        return (z - self.height_mean) / self.height_std

    def log_mass(self, mass: Tensor) -> Tensor:
        return (torch.log(mass.clamp_min(MASS_FLOOR)) - self.log_mass_mean) / self.log_mass_std

    def length(self, x: Tensor) -> Tensor:
        return x / self.length_scale

    def target_stats(self, is_root: Tensor) -> tuple[Tensor, Tensor]:
        """Per-node ``(mean, std)`` of the local-velocity change, ``[N, 3]`` each."""
        r = is_root.unsqueeze(-1)
        return torch.where(r, self.root_mean, self.local_mean), torch.where(r, self.root_std, self.local_std)

    def normalize_target(self, delta: Tensor, is_root: Tensor) -> Tensor:
        mean, std = self.target_stats(is_root)
        return (delta - mean) / std

    def denormalize_target(self, out: Tensor, is_root: Tensor) -> Tensor:
        """Inverse of :meth:`normalize_target`."""
        mean, std = self.target_stats(is_root)
        return out * std + mean

    def extra_repr(self) -> str:
        return f"fitted={bool(self.fitted)}"


class _Moments:
    """Running count, sum and sum of squares per column, in float64."""

    def __init__(self, dim: int) -> None:
        self.n = 0
        self.s = torch.zeros(dim, dtype=torch.float64)
        self.ss = torch.zeros(dim, dtype=torch.float64)
        self.lo = torch.full((dim,), float("inf"), dtype=torch.float64)
        self.hi = torch.full((dim,), float("-inf"), dtype=torch.float64)

    def add(self, x: Tensor) -> None:
        x = x.detach().reshape(-1, self.s.numel()).to(torch.float64).cpu()
        if x.size(0) == 0:
            return
        self.n += x.size(0)
        self.s += x.sum(0)
        self.ss += (x * x).sum(0)
        self.lo = torch.minimum(self.lo, x.amin(0))
        self.hi = torch.maximum(self.hi, x.amax(0))

    def mean(self) -> Tensor:
        return (self.s / self.n).float() if self.n else torch.zeros_like(self.s, dtype=torch.float32)

    def std(self, centred: bool = True, fallback: Tensor | None = None) -> Tensor:
        """Standard deviation per column (RMS if not ``centred``); a constant column takes the mean scale
        of the others (an unused axis is not decoded at 1 m/step), or ``fallback`` when none varies."""
        fallback = torch.ones_like(self.s, dtype=torch.float32) if fallback is None else fallback.float()
        if self.n == 0:
            return fallback
        m2 = self.ss / self.n
        var = m2 - (self.s / self.n) ** 2 if centred else m2
        std = var.clamp_min(0.0).sqrt()
        if not centred:  # a scale of the raw values: only all-zero columns are degenerate
            constant = std == 0
        else:
            constant = (self.hi - self.lo) <= STD_EPSILON * torch.maximum(self.hi.abs(), self.lo.abs())
        degenerate = constant | (std == 0)
        if bool(degenerate.all()):
            return fallback.clone()
        return torch.where(degenerate, std[~degenerate].mean(), std).float()


def _positions(store) -> Tensor:
    """``[N, K, 3]`` positions over time: ``pos_seq`` if the window has one, else ``x_{t-2..t}``."""
    if "pos_seq" in store:
        return store.pos_seq
    return torch.stack([store.prev_prev_pos, store.prev_pos, store.pos], dim=1)


def fit_normalizer(graphs: Iterable[HeteroData], normalizer: Normalizer | None = None,
                   reference_pitch: float | None = None) -> Normalizer:
    """Fit a :class:`Normalizer` on training graphs or dataset windows: velocities, their local
    changes and heights from ``pos_seq`` (or the three positions), the force scale (RMS over nonzero
    rows), log-mass statistics, and the length scale from the ``child_to_parent`` offsets, static
    nodes left out. ``reference_pitch``: offsets divided by each graph's :math:`s = p / p_{ref}`.
    Returns ``normalizer`` (a new one if None), fitted."""
    vel, loc, root, height, log_mass, force, length = (
        _Moments(3), _Moments(3), _Moments(3), _Moments(1), _Moments(1), _Moments(3), _Moments(1)
    )
    seen = 0
    for graph in graphs:
        seen += 1
        store = graph[NODE]
        moving = ~store.is_static
        pos = _positions(store)  # [N, K, 3]
        if pos.dim() != 3 or pos.size(-1) != 3 or pos.size(1) < 2:
            raise ValueError(f"fit_normalizer: positions must be [N, K>=2, 3], got {tuple(pos.shape)}")
        c2p = graph[CHILD_TO_PARENT].edge_index
        v = pos[:, 1:] - pos[:, :-1]  # [N, K-1, 3]
        vel.add(v[moving])
        height.add(pos[moving][..., 2:])
        log_mass.add(torch.log(store.mass[moving].clamp_min(MASS_FLOOR)))
        if v.size(1) >= 2:
            local = to_local_velocity(v, c2p)
            delta = local[:, 1:] - local[:, :-1]
            loc.add(delta[moving & ~store.is_root])
            root.add(delta[moving & store.is_root])
        f = store.force_seq if "force_seq" in store else store.force.unsqueeze(1)
        f = f.reshape(-1, 3)
        force.add(f[(f != 0).any(-1)])
        if c2p.numel():
            offset = pos[c2p[0], 0] - pos[c2p[1], 0]
            size = offset.norm(dim=-1)
            if reference_pitch is not None:
                size = size / (node_pitch(graph).to(size.dtype) / reference_pitch)[c2p[0]]
            length.add(size)
    if seen == 0:
        raise ValueError("fit_normalizer: no training graphs given")
    norm = normalizer if normalizer is not None else Normalizer()
    with torch.no_grad():
        norm.velocity_mean.copy_(vel.mean())
        norm.velocity_std.copy_(vel.std())
        # a target that never varies (e.g. the local velocity of a one-leaf object, always 0)
        # takes the scale of the other target, then of the velocity: a per-step velocity change,
        # not 1 m/step, which made a barely trained one-voxel model fly off (tests/stability)
        root_std = root.std(fallback=vel.std())
        norm.local_mean.copy_(loc.mean())
        norm.local_std.copy_(loc.std(fallback=root_std))
        norm.root_mean.copy_(root.mean())
        norm.root_std.copy_(root_std)
        norm.height_mean.copy_(height.mean())
        norm.height_std.copy_(height.std())
        norm.log_mass_mean.copy_(log_mass.mean())
        norm.log_mass_std.copy_(log_mass.std())
        norm.force_std.copy_(force.std(centred=False))
        norm.length_scale.copy_(length.std(centred=False))
        norm.fitted.fill_(True)
    return norm


def isotropic_horizontal(normalizer: Normalizer) -> Normalizer:
    r"""Make the statistics those of the data averaged over all turns about z, in place: horizontal
    mean 0, each horizontal second moment :math:`\tfrac12(\mu_x^2 + \sigma_x^2 + \mu_y^2 +
    \sigma_y^2)`, for velocity, targets and force; returns ``normalizer``."""
    pairs = (("velocity_mean", "velocity_std"), ("local_mean", "local_std"), ("root_mean", "root_std"))
    with torch.no_grad():
        for mean_name, std_name in pairs:
            mean, std = getattr(normalizer, mean_name), getattr(normalizer, std_name)
            second = (mean[:2].square() + std[:2].square()).mean()
            mean[:2] = 0.0
            std[:2] = second.sqrt()
        force = normalizer.force_std  # an uncentred root mean square already
        force[:2] = force[:2].square().mean().sqrt()
    return normalizer
