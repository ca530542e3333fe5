"""Graph Network-based Simulator (GNS; Sanchez-Gonzalez et al., ICML 2020): the flat baseline.

A GNS sees the leaves only: one radius graph over every leaf (within and between objects),
encode-process-decode with ``M`` interaction-network steps, decoded to each leaf's acceleration.
It plugs into the package's one step (:mod:`hrn_pyg.sim.step`) as the HRN does: it reads the
leaf rows of the same :class:`~hrn_pyg.nn.hrn.HRNInputs`, and
:func:`~hrn_pyg.sim.step.decode` integrates its output by semi-implicit Euler.

Differences from the paper: two input velocities, not five (the package's state holds
:data:`~hrn_pyg.data.graph.HISTORY` = 2); external force and mass as node inputs (our scenes
push objects and draw masses); the ground plane as the only boundary; a material embedding and
stiffness in place of the particle type; optional MC dropout masks, as the HRN's.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn
from torch_geometric.data import HeteroData
from torch_geometric.nn import MessagePassing

from hrn_pyg.data.graph import MATERIALS, NODE
from hrn_pyg.data.radius import collision_edges
from hrn_pyg.nn.collision import safe_norm
from hrn_pyg.nn.hrn import GROUND_CONTACT_DIM, STATE_DIM, STATE_LAYOUT, HRNInputs
from hrn_pyg.nn.mlp import MLP, NetworkConfig, dropout_mask
from hrn_pyg.nn.normalizer import Normalizer

#: what a checkpoint's model config says in its ``network`` field to be a GNS (no field: HRN)
NETWORK = "gns"
#: the learned parts of the GNS, by the name a dropout mask or ``GNSConfig.dropout_modules`` uses
MODULE_NAMES = ("encoder", "processor", "decoder")
#: options that change how trained weights are applied, not which weights there are
#: (:func:`hrn_pyg.checkpoints.with_applied_options`): the rigid fit is a projection of the
#: decoded positions, so a GNS trained without it can be scored with it
APPLIED_OPTIONS = ("rigid_fit",)
#: the paper's input noise (std 3e-4 of the last input position, unit-box 2D scenes) over their
#: per-step velocity std (2.2e-3 and 2.7e-3 per axis in the published 2D metadata): the
#: ``gns`` training preset draws its noise at this fraction of our fitted velocity std
NOISE_TO_VELOCITY_STD = 0.12


def _columns(name: str) -> slice:
    """The columns of ``name`` in a state vector (:data:`~hrn_pyg.nn.hrn.STATE_LAYOUT`)."""
    start = 0
    for entry, width in STATE_LAYOUT:
        if entry == name:
            return slice(start, start + width)
        start += width
    raise KeyError(name)


VELOCITY = _columns("velocity")
LOG_MASS = _columns("log_mass")
MATERIAL = _columns("material")
STIFFNESS = _columns("stiffness")
IS_LEAF = _columns("is_leaf")
#: the ground-contact column :math:`\mathrm{clip}(z / R, -1, 1)`, the last one of the state
GROUND = slice(STATE_DIM, STATE_DIM + GROUND_CONTACT_DIM)
#: node inputs: v_t, v_{t-1} (3 each), ground distance, stiffness, log mass, force (3)
NODE_NUMBERS = 3 + 3 + GROUND_CONTACT_DIM + 1 + 1 + 3
#: edge inputs: (x_j - x_i) / R and |x_j - x_i| / R
EDGE_INPUTS = 4


@dataclass(frozen=True)
class GNSConfig(NetworkConfig):
    """Everything that fixes the shape and behaviour of a :class:`GNS`; saved with checkpoints.

    Attributes:
        latent: size of the node and edge latents.
        hidden: hidden width of every MLP.
        depth: hidden layers of every MLP.
        activation: MLP activation (see :data:`hrn_pyg.nn.mlp.ACTIVATIONS`).
        message_passing_steps: ``M``, interaction-network steps of the processor.
        collision_radius: the connectivity radius ``R`` (m), also of the collision search and the
            ground column.
        material_embedding: size of the learnt embedding of the material code.
        dropout_rate: default rate of :meth:`GNS.sample_masks` (0: deterministic).
        dropout_modules: which parts take a dropout mask (names from :data:`MODULE_NAMES`).
        rigid_fit: replace each rigid object's leaf motion by its best rigid transform
            (:func:`hrn_pyg.sim.step.rigid_leaf_positions`).
        network: always :data:`NETWORK`; tells a checkpoint's reader which model to build.
    """

    latent: int = 128
    hidden: int = 128
    depth: int = 2
    activation: str = "relu"
    message_passing_steps: int = 10
    collision_radius: float = 0.08
    material_embedding: int = 16
    dropout_rate: float = 0.0
    dropout_modules: tuple[str, ...] = field(default=("processor",))
    rigid_fit: bool = False
    network: str = NETWORK

    def __post_init__(self) -> None:
        object.__setattr__(self, "dropout_modules", tuple(self.dropout_modules))
        _ = self.mlp  # validates hidden / depth / activation
        if self.network != NETWORK:
            raise ValueError(f"GNSConfig.network must be {NETWORK!r}, got {self.network!r}")
        for name in ("latent", "message_passing_steps", "material_embedding"):
            if getattr(self, name) < 1:
                raise ValueError(f"GNSConfig.{name} must be >= 1, got {getattr(self, name)}")
        if not self.collision_radius > 0 or self.collision_radius == float("inf"):
            raise ValueError(f"GNSConfig.collision_radius must be a finite number > 0, got {self.collision_radius}")
        if not 0.0 <= self.dropout_rate < 1.0:
            raise ValueError(f"GNSConfig.dropout_rate must be in [0, 1), got {self.dropout_rate}")
        unknown = set(self.dropout_modules) - set(MODULE_NAMES)
        if unknown:
            raise ValueError(f"GNSConfig.dropout_modules: unknown {sorted(unknown)}; choose from {MODULE_NAMES}")

    # what the package's step reads of a model's config (hrn_pyg.sim.step.build_inputs)
    @property
    def ground_contact(self) -> bool:
        """Always True: the ground column is the GNS's distance to the lower boundary."""
        return True

    @property
    def rest_offsets(self) -> bool:
        return False

    @property
    def mirror_average(self) -> bool:
        return False

    @property
    def mirror_group(self) -> tuple[tuple[int | str, ...], ...]:
        return ((),)

    @property
    def state_dim(self) -> int:
        """Columns of the state vector the step builds for this model (ground column included)."""
        return STATE_DIM + GROUND_CONTACT_DIM



def radius_graph(pos: Tensor, radius: float, batch: Tensor | None = None) -> Tensor:
    r"""Every ordered pair of points of one batch copy closer than ``radius``, no self loops.

    .. math::
        \mathcal{E} = \{(j, i) : j \ne i,\ b_j = b_i,\ \lVert x_i - x_j \rVert < R\}

    (:func:`hrn_pyg.data.radius.collision_edges` with every point its own object), sorted by
    destination, then source.

    **Shapes:** pos ``(L, 3)``, batch ``(L,)``; returns ``(2, |E|)`` (row 0 source ``j``).
    """
    own_object = torch.arange(pos.size(0), device=pos.device)
    return collision_edges(pos, own_object, radius, batch)


class GNS(MessagePassing):
    r"""Encode-process-decode over the radius graph of the leaves (Sanchez-Gonzalez et al. 2020).

    .. math::
        h_i^{0} &= \mathrm{LN}\,\varepsilon^V\bigl(\hat v_i(t), \hat v_i(t-1), g_i, \mathrm{emb}(k_i),
            \kappa_i, \hat m_i, \hat f_i\bigr), \qquad
        e_{ji}^{0} = \mathrm{LN}\,\varepsilon^E\Bigl(\frac{x_j - x_i}{R},
            \frac{\lVert x_j - x_i \rVert}{R}\Bigr) \\
        \tilde e_{ji} &= \mathrm{LN}\,\phi^E_m\bigl(e_{ji}^{m}, h_i^{m}, h_j^{m}\bigr), \qquad
        \tilde h_i = \mathrm{LN}\,\phi^V_m\Bigl(h_i^{m}, \sum_{j \in \mathcal{N}(i)} \tilde e_{ji}\Bigr) \\
        e_{ji}^{m+1} &= e_{ji}^{m} + \tilde e_{ji}, \qquad h_i^{m+1} = h_i^{m} + \tilde h_i
            \qquad (m = 0 .. M-1) \\
        \hat a_i &= \delta^V\bigl(h_i^{M}\bigr)

    over the leaves and the edges of :func:`radius_graph`. :math:`\hat v`: normalised velocities,
    :math:`g_i = \mathrm{clip}(z_i / R, -1, 1)`, :math:`k_i` material code, :math:`\kappa_i`
    stiffness, :math:`\hat m_i` normalised log mass, :math:`\hat f_i` normalised force; every
    :math:`\varepsilon, \phi, \delta` an MLP, LN a LayerNorm. The output is the normalised
    acceleration :math:`\hat a_i = (a_i - \mu_a) / \sigma_a` (buffers of :func:`fit_acceleration`),
    zero on ancestor rows. A dropout mask (:meth:`sample_masks`) is a ``[B, hidden]`` table per part,
    one row per trajectory copy, on every hidden layer of that part's MLPs.

    **Shapes:**
        - **input:** :class:`~hrn_pyg.nn.hrn.HRNInputs` over :math:`|\mathcal{V}|` nodes (state
          :math:`(|\mathcal{V}|, S + 1)`, the last column the ground distance); masks
          ``{name: (B, H)}``
        - **graph:** :math:`L` leaves, edge_index :math:`(2, |\mathcal{E}|)`, latents
          :math:`(L, D)` and :math:`(|\mathcal{E}|, D)`
        - **output:** :math:`(|\mathcal{V}|, 3)`
    """

    def __init__(self, config: GNSConfig = GNSConfig()) -> None:
        super().__init__(aggr="add")
        self.config = config
        d, mlp, m = config.latent, config.mlp, config.message_passing_steps
        self.material = nn.Embedding(len(MATERIALS), config.material_embedding)
        self.node_encoder = MLP(NODE_NUMBERS + config.material_embedding, d, mlp)
        self.node_encoder_norm = nn.LayerNorm(d)
        self.edge_encoder = MLP(EDGE_INPUTS, d, mlp)
        self.edge_encoder_norm = nn.LayerNorm(d)
        self.edge_mlps = nn.ModuleList(MLP(3 * d, d, mlp) for _ in range(m))
        self.edge_norms = nn.ModuleList(nn.LayerNorm(d) for _ in range(m))
        self.node_mlps = nn.ModuleList(MLP(2 * d, d, mlp) for _ in range(m))
        self.node_norms = nn.ModuleList(nn.LayerNorm(d) for _ in range(m))
        self.decoder = MLP(d, 3, mlp)
        self.normalizer = Normalizer()
        self.register_buffer("acceleration_mean", torch.zeros(3))
        self.register_buffer("acceleration_std", torch.ones(3))

    def reset_parameters(self) -> None:
        super().reset_parameters()
        self.material.reset_parameters()
        for module in (self.node_encoder, self.node_encoder_norm, self.edge_encoder, self.edge_encoder_norm,
                       *self.edge_mlps, *self.edge_norms, *self.node_mlps, *self.node_norms, self.decoder):
            module.reset_parameters()

    # --- the dropout API of the HRN (hrn_pyg.sampling, training with --train-dropout)

    def sample_masks(self, num_copies: int, rate: float | None = None,
                     generator: torch.Generator | None = None) -> dict[str, Tensor]:
        """One fresh mask per part of ``config.dropout_modules``, one row per trajectory copy;
        call once per prediction step. ``rate`` defaults to ``config.dropout_rate``."""
        rate = self.config.dropout_rate if rate is None else rate
        device = self.acceleration_std.device
        return {name: dropout_mask(num_copies, self.config.hidden, rate, generator, device)
                for name in self.config.dropout_modules}

    def mask_rows(self, num_copies: int) -> int:
        """Rows of a dropout mask for ``num_copies`` trajectory copies (one pass: one each)."""
        return num_copies

    # --- the acceleration normalisation (the decoder's target)

    def normalize_acceleration(self, acceleration: Tensor) -> Tensor:
        return (acceleration - self.acceleration_mean) / self.acceleration_std

    def denormalize_acceleration(self, out: Tensor) -> Tensor:
        """Inverse of :meth:`normalize_acceleration`."""
        return out * self.acceleration_std + self.acceleration_mean

    # --- the network

    def forward(self, inputs: HRNInputs, masks: Mapping[str, Tensor] | None = None) -> Tensor:
        masks = dict(masks or {})
        unknown = set(masks) - set(self.config.dropout_modules)
        if unknown:
            raise ValueError(f"GNS: masks given for {sorted(unknown)}, not in dropout_modules "
                             f"{self.config.dropout_modules}")
        if inputs.state.size(-1) != self.config.state_dim:
            raise ValueError(f"GNS: state has {inputs.state.size(-1)} columns, this config needs "
                             f"{self.config.state_dim} (the step builds them with the ground column)")
        if inputs.options.fixed_shape or inputs.options.collision_weight is not None:
            raise ValueError("GNS: its radius graph is searched every step, so it has no fixed-shape step")
        leaves = torch.nonzero(inputs.state[:, IS_LEAF].squeeze(-1) > 0.5).flatten()
        batch = inputs.batch.index_select(0, leaves)
        pos = inputs.pos.index_select(0, leaves) * self.normalizer.length_scale  # metres
        edge_index = radius_graph(pos, self.config.collision_radius, batch)
        nodes = self.node_features(inputs, leaves)
        edges = self.edge_features(pos, edge_index)
        acceleration = self.network(nodes, edges, edge_index, batch, masks)
        return acceleration.new_zeros(inputs.state.size(0), 3).index_copy(0, leaves, acceleration)

    def node_features(self, inputs: HRNInputs, leaves: Tensor) -> Tensor:
        r"""``(L, NODE_NUMBERS + emb)``: :math:`[\hat v(t), \hat v(t-1), g, \kappa, \hat m,
        \hat f, \mathrm{emb}(k)]` of the leaves ``leaves`` (rows of the inputs)."""
        state = inputs.state.index_select(0, leaves)
        prev = inputs.prev_state.index_select(0, leaves)
        code = state[:, MATERIAL].argmax(dim=-1)
        return torch.cat([state[:, VELOCITY], prev[:, VELOCITY], state[:, GROUND], state[:, STIFFNESS],
                          state[:, LOG_MASS], inputs.force.index_select(0, leaves), self.material(code)], dim=-1)

    def edge_features(self, pos: Tensor, edge_index: Tensor) -> Tensor:
        r"""``(|E|, 4)``: :math:`[(x_j - x_i) / R, \lVert x_j - x_i \rVert / R]` of each edge
        :math:`j \to i` (``pos`` in metres)."""
        src, dst = edge_index
        offset = (pos.index_select(0, src) - pos.index_select(0, dst)) / self.config.collision_radius
        return torch.cat([offset, safe_norm(offset)], dim=-1)

    def network(self, nodes: Tensor, edges: Tensor, edge_index: Tensor, batch: Tensor,
                masks: Mapping[str, Tensor]) -> Tensor:
        """Encode, ``M`` processor steps, decode: normalised accelerations ``(L, 3)``."""
        edge_batch = batch.index_select(0, edge_index[1])
        encoder, processor = masks.get("encoder"), masks.get("processor")
        h = self.node_encoder_norm(self.node_encoder(nodes, encoder, batch))
        e = self.edge_encoder_norm(self.edge_encoder(edges, encoder, edge_batch))
        n = h.size(0)
        for m in range(self.config.message_passing_steps):
            e_new = self.edge_updater(edge_index, h=h, e=e, m=m, mask=processor, edge_batch=edge_batch)
            received = self.propagate(edge_index, e=e_new, size=(n, n))
            h = h + self.node_norms[m](self.node_mlps[m](torch.cat([h, received], dim=-1), processor, batch))
            e = e + e_new
        return self.decoder(h, masks.get("decoder"), batch)

    def edge_update(self, e: Tensor, h_i: Tensor, h_j: Tensor, m: int, mask: Tensor | None,
                    edge_batch: Tensor) -> Tensor:
        # the edge function of processor step m: LN(phi^E_m(e_ji, h_i, h_j))
        return self.edge_norms[m](self.edge_mlps[m](torch.cat([e, h_i, h_j], dim=-1), mask, edge_batch))

    def message(self, e: Tensor) -> Tensor:
        # what edge j -> i carries to i: its updated latent, summed at i (aggr="add")
        return e

    def __repr__(self) -> str:
        c = self.config
        return (f"{self.__class__.__name__}(latent={c.latent}, hidden={c.hidden}, depth={c.depth}, "
                f"M={c.message_passing_steps}, radius={c.collision_radius}, dropout={c.dropout_rate} on "
                f"{list(c.dropout_modules)}, rigid_fit={c.rigid_fit})")


def leaf_accelerations(pos_seq: Tensor) -> Tensor:
    r"""``(N, K-2, 3)`` accelerations :math:`x_{k+1} - 2 x_k + x_{k-1}` of positions ``(N, K, 3)``."""
    return pos_seq[:, 2:] - 2.0 * pos_seq[:, 1:-1] + pos_seq[:, :-2]


@torch.no_grad()
def fit_acceleration(windows: Iterable[HeteroData], model: GNS) -> GNS:
    """Fit ``model.acceleration_mean`` / ``acceleration_std`` in place: the per-axis mean and std of
    :func:`leaf_accelerations` over the moving leaves of the windows (float64 sums); a constant axis
    takes the others' mean scale, or 1. Returns ``model``."""
    total, squares, count = torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), 0
    for window in windows:
        store = window[NODE]
        acc = leaf_accelerations(store.pos_seq[store.is_leaf & ~store.is_static]).reshape(-1, 3).double()
        total += acc.sum(0)
        squares += (acc * acc).sum(0)
        count += acc.size(0)
    if count == 0:
        raise ValueError("fit_acceleration: no moving leaves with three positions in the windows")
    mean = total / count
    std = (squares / count - mean * mean).clamp_min(0.0).sqrt()
    varies = std > 0
    fallback = std[varies].mean() if bool(varies.any()) else torch.ones((), dtype=std.dtype)
    model.acceleration_mean.copy_(mean.float())
    model.acceleration_std.copy_(torch.where(varies, std, fallback).float())
    return model
