"""The Hierarchical Relation Network (Fig. 2): force, collision and history effects, propagated
through each object hierarchy, decoded into next velocities in the parent's frame."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, NamedTuple

import torch
from torch import Tensor, nn
from torch_geometric.data import HeteroData

from hrn_pyg.nn import equivariant
from hrn_pyg.nn.collision import CollisionModule
from hrn_pyg.nn.equivariant.features import invariant_state, squash
from hrn_pyg.nn.force import ForceModule
from hrn_pyg.nn.history import HistoryModule
from hrn_pyg.nn.mlp import NetworkConfig, dropout_mask, in_degree
from hrn_pyg.nn.normalizer import Normalizer
from hrn_pyg.nn.pitch import PITCH_DIM
from hrn_pyg.nn.propagation import PropagationModule, edge_offsets
from hrn_pyg.nn.state import NextStateModule

#: the learned sub-modules, by the name a dropout mask or ``HRNConfig.dropout_modules`` uses
MODULE_NAMES = ("force", "collision", "history", "l2a", "ws", "a2d", "state")

#: layout of a particle's state vector s_i (see :func:`state_features`)
STATE_LAYOUT = (
    ("velocity", 3),   # normalised per-step displacement
    ("height", 1),     # normalised z above the ground plane
    ("log_mass", 1),   # normalised log mass
    ("material", 4),   # one-hot rigid, soft, cloth, static
    ("stiffness", 1),
    ("depth", 1),      # level in the tree, root 0
    ("is_leaf", 1),
    ("is_root", 1),
    ("gravity", 3),    # unit gravity direction on roots, zero elsewhere (HRN: gravity enters the root)
)
STATE_DIM = sum(d for _, d in STATE_LAYOUT)
#: the extra state column of ``HRNConfig.ground_contact``: height clipped at the collision radius
GROUND_CONTACT_DIM = 1

#: marks a group element that exchanges x and y before it negates its axes
SWAP_XY = "swap_xy"
#: the groups of ``HRNConfig.mirror_planes``: each element as the axes it negates, after
#: exchanging x and y where it holds :data:`SWAP_XY` (``d4``: the eight signed permutations of x
#: and y, the symmetries of the square voxel lattice in the ground plane)
MIRROR_GROUPS: dict[str, tuple[tuple[int | str, ...], ...]] = {
    "x": ((), (0,)),
    "xy": ((), (0,), (1,), (0, 1)),
    "d4": ((), (0,), (1,), (0, 1), (SWAP_XY,), (SWAP_XY, 0), (SWAP_XY, 1), (SWAP_XY, 0, 1)),
}
#: the axis order of an element with :data:`SWAP_XY` (a swap is its own inverse)
SWAPPED_AXES = (1, 0, 2)

#: direction of gravity, z up
GRAVITY_DIRECTION = (0.0, 0.0, -1.0)


@dataclass(frozen=True)
class HRNConfig(NetworkConfig):
    r"""Everything that fixes the shape and behaviour of an :class:`HRN`; saved with checkpoints.

    Attributes:
        hidden: hidden width of every MLP.
        depth: hidden layers of every MLP.
        activation: MLP activation (see :data:`hrn_pyg.nn.mlp.ACTIVATIONS`).
        effect_dim: size of an effect vector.
        collision_radius: metres; leaves of different objects closer than this interact.
        dropout_rate: default rate of :meth:`HRN.sample_masks` (0: deterministic).
        dropout_modules: which sub-modules accept a dropout mask (names from :data:`MODULE_NAMES`).
        skip_idle_modules: skip the force / collision module without force / collision edges.
        rigid_fit: replace the predicted leaf motion of every rigid object by its best rigid
            transform (:func:`hrn_pyg.nn.rigid.fit_rigid_motion`), in training and at inference.
        rigid_fit_rest: fit that transform from the object's rest shape (``rest_pos``) rather than
            its current leaves, so rounding does not add up over steps (needs ``rigid_fit``).
        rest_offsets: the propagation modules also see each edge's rest-shape offset
            (``graph['particle'].rest_pos``), so an elastic restoring effect is learnable.
        ground_contact: a state column :math:`\mathrm{clip}(z / r_c, -1, 1)`, the distance to the
            ground saturated beyond the collision radius.
        mirror_average: frame averaging over the group of ``mirror_planes``,
            :math:`u = \frac{1}{|G|} \sum_{M \in G} M^{-1} f(M s)`, one pass (and mask) per element.
        mirror_planes: ``"x"`` (x = 0; two passes), ``"xy"`` (x = 0, y = 0, the half-turn about z;
            four) or ``"d4"`` (also x and y exchanged: the square lattice's eight symmetries).
        pitch_aware: read each scene relative to its voxel pitch :math:`p` (:mod:`hrn_pyg.nn.pitch`)
            with :math:`s = p / p_{ref}`: collision radius :math:`r_c s`, positions divided by
            :math:`s`, and a last state column :math:`\log_2 s`.
        reference_pitch: :math:`p_{ref}` (m), where a pitch-aware model reads a scene as a plain one.
        ground_projection: after the rigid fit, keep every moving leaf on or above :math:`z = 0`
            (:func:`hrn_pyg.sim.step.ground_projected_positions`; a rigid object lifted whole).
        ground_projection_rigid: the ground projection also lifts rigid objects (False: only soft
            and cloth leaves).
        rigid_ground_depth: pitches under the plane a rigid object's lowest leaf may lie before it
            is lifted (back to that depth); 0 lifts every rigid leaf onto the plane.
        rigid_ground_speed: the furthest (pitches) a rigid object's leaves may move in the step for
            it to be lifted; a faster one is left where the network put it (0: any speed).
        rigid_ground_lift: the furthest (pitches) a rigid object is lifted in one step; one sunk
            deeper climbs out over several steps (0: all the way at once).
        ground_lift_velocity: a lift counts as motion, so the next step's velocity
            :math:`x_{t+1} - x_t` includes it; False moves ``prev_pos`` with the node too.
        rigid_leaf_siblings: the within-siblings phase also runs on the edges into rigid objects'
            leaves (False drops them, :func:`within_siblings_of`; a setting to train with).
        corotated_rest: with ``rest_offsets``, each soft body's and cloth's rest shape is turned
            every step onto its current leaves (:func:`hrn_pyg.sim.step.corotated_rest_positions`).
        cloth_clearance: pitches in front of another object's surface to which a cloth leaf that a
            step leaves inside it is moved back (:mod:`hrn_pyg.sim.cloth_contact`; 0: off).
        solid_clearance: the same rule for soft and rigid leaves (a rigid object moved whole; 0: off).
        energy_limit: no step's prediction ends with more energy per scene copy than it started
            with plus the pushes' work (:mod:`hrn_pyg.sim.energy`); the clearance after it may add
            the height of an overlap it removes, never speed (:mod:`hrn_pyg.sim.rules`).
        rest_friction: pitches: a supported object whose last and predicted steps are both
            shorter than this is held still, as static friction holds it
            (:mod:`hrn_pyg.sim.rest_friction`; 0: off).
        equivariant: the network of :mod:`hrn_pyg.nn.equivariant`, exactly equivariant in one pass
            under turns about z and vertical mirrors; needs a horizontally isotropic normaliser,
            not with ``mirror_average``.
        vector_channels: :math:`C`, the horizontal vectors each effect carries (``equivariant``).
        collision_force: the collision module also reads the external force on both ends of an
            edge, so pushed bodies resist in the step of the push.
    """

    hidden: int = 64
    depth: int = 2
    activation: str = "relu"
    effect_dim: int = 64
    collision_radius: float = 0.08
    dropout_rate: float = 0.0
    dropout_modules: tuple[str, ...] = field(default=("force", "collision"))
    skip_idle_modules: bool = True
    rigid_fit: bool = False
    rigid_fit_rest: bool = False
    rest_offsets: bool = False
    ground_contact: bool = False
    mirror_average: bool = False
    mirror_planes: str = "x"
    pitch_aware: bool = False
    reference_pitch: float = 0.05
    ground_projection: bool = False
    ground_projection_rigid: bool = True
    rigid_ground_depth: float = 0.0
    rigid_ground_speed: float = 0.0
    rigid_ground_lift: float = 0.0
    ground_lift_velocity: bool = True
    rigid_leaf_siblings: bool = True
    corotated_rest: bool = False
    cloth_clearance: float = 0.0
    solid_clearance: float = 0.0
    energy_limit: bool = False
    rest_friction: float = 0.0
    equivariant: bool = False
    #: fields of earlier releases a saved config may hold, at the value that builds this network
    #: (:meth:`~hrn_pyg.nn.mlp.NetworkConfig.from_dict` drops them)
    REMOVED_FIELDS: ClassVar[dict[str, Any]] = {"material_heads": False}
    vector_channels: int = 8
    collision_force: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "dropout_modules", tuple(self.dropout_modules))
        _ = self.mlp  # builds an MLPConfig, which validates hidden / depth / activation
        if self.effect_dim < 1:
            raise ValueError(f"HRNConfig.effect_dim must be >= 1, got {self.effect_dim}")
        if not self.collision_radius >= 0:
            raise ValueError(f"HRNConfig.collision_radius must be >= 0, got {self.collision_radius}")
        if self.ground_contact and not self.collision_radius > 0:
            raise ValueError("HRNConfig.ground_contact needs collision_radius > 0")
        if not 0.0 <= self.dropout_rate < 1.0:
            raise ValueError(f"HRNConfig.dropout_rate must be in [0, 1), got {self.dropout_rate}")
        unknown = set(self.dropout_modules) - set(MODULE_NAMES)
        if unknown:
            raise ValueError(f"HRNConfig.dropout_modules: unknown {sorted(unknown)}; choose from {MODULE_NAMES}")
        if self.mirror_planes not in MIRROR_GROUPS:
            raise ValueError(f"HRNConfig.mirror_planes must be one of {sorted(MIRROR_GROUPS)}, "
                             f"got {self.mirror_planes!r}")
        if self.corotated_rest and not self.rest_offsets:
            raise ValueError("HRNConfig.corotated_rest turns the rest shape: it needs rest_offsets=True")
        if not 0.0 <= self.rigid_ground_depth <= 1.0:
            raise ValueError(f"HRNConfig.rigid_ground_depth must be in [0, 1] pitches, got {self.rigid_ground_depth}")
        if not 0.0 <= self.rigid_ground_speed < float("inf"):
            raise ValueError(f"HRNConfig.rigid_ground_speed must be a finite number of pitches >= 0, "
                             f"got {self.rigid_ground_speed}")
        if not 0.0 <= self.rigid_ground_lift < float("inf"):
            raise ValueError(f"HRNConfig.rigid_ground_lift must be a finite number of pitches >= 0, "
                             f"got {self.rigid_ground_lift}")
        for name in ("cloth_clearance", "solid_clearance", "rest_friction"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ValueError(f"HRNConfig.{name} must be in [0, 1) pitches, got {getattr(self, name)}")
        if self.vector_channels < 1:
            raise ValueError(f"HRNConfig.vector_channels must be >= 1, got {self.vector_channels}")
        if self.equivariant and self.mirror_average:
            raise ValueError("HRNConfig.equivariant is exact in one pass and has one output network: "
                             "not with mirror_average")
        if not 0.0 < self.reference_pitch < float("inf"):
            raise ValueError(f"HRNConfig.reference_pitch must be a finite number > 0, got {self.reference_pitch}")

    @property
    def mirror_group(self) -> tuple[tuple[int | str, ...], ...]:
        """The transforms the network is averaged over, each as the axes it negates (``()`` is
        the identity; :data:`SWAP_XY` in it: x and y exchanged first); just the identity without
        ``mirror_average``."""
        return MIRROR_GROUPS[self.mirror_planes] if self.mirror_average else ((),)

    @property
    def state_dim(self) -> int:
        """Size of a particle's state vector under this config: :data:`STATE_LAYOUT`, then the
        ground-contact column (``ground_contact``), then the pitch column (``pitch_aware``)."""
        return STATE_DIM + (GROUND_CONTACT_DIM if self.ground_contact else 0) + (PITCH_DIM if self.pitch_aware else 0)



class HierarchyConstants(NamedTuple):
    r"""What the propagation phases (L2A, WS, A2D) read of the hierarchy that no step changes, computed
    once per rollout (:func:`hierarchy_constants`) with the same numbers bit for bit: each phase's
    in-degree and, with ``HRNConfig.rest_offsets``, its edges' normalised rest offsets
    :math:`\bar x_j - \bar x_i`; ``within_siblings``, the WS edges when they are not the graph's
    (:func:`within_siblings_of`).

    **Shapes:** ``degree``: three ``[N]`` float; ``rest_offset``: three ``[E_k, 3]`` or None;
    ``within_siblings`` ``[2, E_WS]`` or None (the graph's own).
    """

    degree: tuple[Tensor, Tensor, Tensor]
    rest_offset: tuple[Tensor, Tensor, Tensor] | None = None
    within_siblings: Tensor | None = None


@dataclass(frozen=True)
class StepOptions:
    r"""How one model step is run: what its caller knows ahead, so that the step need not find out.

    Each option saves work (a host read, a collision search, a data-dependent size) and leaves the
    prediction as it is. The object travels from :func:`hrn_pyg.sim.step.step` through
    :func:`~hrn_pyg.sim.step.predict` and :func:`~hrn_pyg.sim.step.build_inputs` into
    :class:`HRNInputs`. The defaults check everything; a new option of the step is a field here.

    Attributes:
        force_active: whether :math:`f_i(t)` is nonzero somewhere, so the force module
            :math:`e_F = \phi_F(s_i, f_i)` runs (False is the caller's promise); None: asked of the
            force tensor (a host read).
        check: check positions and force for NaN / inf before the step; False: the caller did.
        objects: ``([N] long, R)``, every node's object and the object count
            (:func:`hrn_pyg.sim.step.object_of`) for the rigid fit; None: found in the step.
        collision_weight: ``[E_C]``, 1 for collision edges that act and 0 for padded candidates
            (:mod:`hrn_pyg.sim.fixed_shape`); None: every edge acts.
        fixed_shape: no tensor's size depends on the data (the force module runs on every row and
            zeroes those without force).
        collisions: whether the next graph gets a collision search at :math:`x_{t+1}`; False: nothing
            can touch, so no search is made.
        rules: ``(graph, prediction, force, movable) -> prediction``, the scene's rules after the
            network (:class:`~hrn_pyg.sim.rules.StepRules`), applied on the whole graph before it
            advances (``movable``: the awake rows, or None). None: made from the model each step.
        hierarchy: the graph's :class:`HierarchyConstants`
            (:func:`hrn_pyg.sim.step.hierarchy_constants`); None: recomputed in the pass.
    """

    force_active: bool | None = None
    check: bool = True
    objects: tuple[Tensor, int] | None = None
    collision_weight: Tensor | None = None
    fixed_shape: bool = False
    collisions: bool = True
    hierarchy: HierarchyConstants | None = None
    # (graph, Prediction, force, movable) -> Prediction; the sim package, above this one, defines both
    rules: Callable[[HeteroData, tuple, Tensor | None, Tensor | None], tuple] | None = None


class HRNInputs(NamedTuple):
    """Everything one network pass reads, already normalised (:func:`hrn_pyg.sim.step.build_inputs`).

    Shapes: ``state``, ``prev_state`` ``[N, STATE_DIM]`` (s(t), s(t-1)); ``pos`` ``[N, 3]``
    positions over the length scale (and a pitch-aware model's pitch scale :math:`s_i`); ``force``
    ``[N, 3]``; ``is_static``, ``is_root`` ``[N]`` bool; ``batch`` ``[N]`` long; the four edge sets
    ``[2, E]``; ``rest_pos`` ``[N, 3]`` scaled as ``pos``, or None. ``options``: the step's
    :class:`StepOptions`; ``hierarchy``: the :class:`HierarchyConstants` of these edges, or None.
    """

    state: Tensor
    prev_state: Tensor
    pos: Tensor
    force: Tensor
    is_static: Tensor
    is_root: Tensor
    batch: Tensor
    collision: Tensor
    leaf_to_ancestor: Tensor
    within_siblings: Tensor
    ancestor_to_descendant: Tensor
    rest_pos: Tensor | None = None
    options: StepOptions = StepOptions()
    hierarchy: HierarchyConstants | None = None


def within_siblings_of(edge_index: Tensor, rigid_leaf: Tensor) -> Tensor:
    r"""The within-siblings edges ``[2, E]`` without those whose destination is a rigid leaf
    (``rigid_leaf`` ``[N]`` bool), in their order (:attr:`HRNConfig.rigid_leaf_siblings`)."""
    return edge_index[:, ~rigid_leaf.index_select(0, edge_index[1])]


def hierarchy_constants(inputs: HRNInputs, rest_offsets: bool) -> HierarchyConstants:
    """The :class:`HierarchyConstants` of ``inputs``' three hierarchy edge sets: in-degrees
    (float, in the positions' dtype) and, with ``rest_offsets`` and a rest shape, the rest
    offsets (:func:`~hrn_pyg.nn.propagation.edge_offsets` of ``inputs.rest_pos``)."""
    n, dtype = inputs.pos.size(0), inputs.pos.dtype
    edges = (inputs.leaf_to_ancestor, inputs.within_siblings, inputs.ancestor_to_descendant)
    degree = tuple(in_degree(e, n).to(dtype) for e in edges)
    rest = None
    if rest_offsets and inputs.rest_pos is not None:
        rest = tuple(edge_offsets(inputs.rest_pos, e) for e in edges)
    return HierarchyConstants(degree, rest, inputs.within_siblings)


def check_hierarchy(hierarchy: HierarchyConstants, inputs: HRNInputs) -> None:
    """Raise ValueError unless ``hierarchy`` has a degree per node and a rest offset per edge of
    ``inputs`` (constants of another graph)."""
    n = inputs.pos.size(0)
    edges = (inputs.leaf_to_ancestor, inputs.within_siblings, inputs.ancestor_to_descendant)
    bad = any(d.shape != (n,) for d in hierarchy.degree)
    if hierarchy.within_siblings is not None:
        bad |= hierarchy.within_siblings.shape != inputs.within_siblings.shape
    if hierarchy.rest_offset is not None:
        bad |= any(r.shape != (e.size(1), 3) for r, e in zip(hierarchy.rest_offset, edges))
    if bad:
        raise ValueError("StepOptions.hierarchy: the constants are of another graph (a degree per node and a "
                         "rest offset per hierarchy edge expected)")


def propagation_phases(inputs: HRNInputs) -> list[tuple[str, Tensor, Tensor | None, Tensor | None]]:
    """The three propagation phases in order, each as ``(module name, edges, in-degree or None,
    rest offsets or None)``: L2A, WS, A2D with the constants of ``inputs.hierarchy`` when it has
    them."""
    hierarchy = inputs.hierarchy
    degree = (None, None, None) if hierarchy is None else hierarchy.degree
    rest = (None, None, None) if hierarchy is None or hierarchy.rest_offset is None else hierarchy.rest_offset
    edges = (inputs.leaf_to_ancestor, inputs.within_siblings, inputs.ancestor_to_descendant)
    return list(zip(("l2a", "ws", "a2d"), edges, degree, rest))


def state_features(
    normalizer: Normalizer,
    velocity: Tensor,
    z: Tensor,
    mass: Tensor,
    material: Tensor,
    stiffness: Tensor,
    depth: Tensor,
    is_leaf: Tensor,
    is_root: Tensor,
    ground_radius: float | Tensor | None = None,
    pitch: Tensor | None = None,
) -> Tensor:
    r"""A particle's state vector in the order of :data:`STATE_LAYOUT`, then (with ``ground_radius``)
    the column :math:`\mathrm{clip}(z / r, -1, 1)`, then (with ``pitch``) the pitch column
    (:func:`hrn_pyg.nn.pitch.pitch_column`). No absolute horizontal position enters.

    **Shapes:** velocity ``[N, 3]``, z / mass / stiffness ``[N, 1]``, material ``[N, 4]``,
    depth / is_leaf / is_root ``[N]``, ``ground_radius`` a number or ``[N, 1]``, ``pitch``
    ``[N, 1]``; returns ``[N, STATE_DIM (+1 per optional column)]``.
    """
    dtype = velocity.dtype
    root = is_root.to(dtype).unsqueeze(-1)
    # one column per axis, scaled by a Python number: no host-to-device copy (a CUDA graph
    # cannot record one from pageable memory)
    gravity = torch.cat([root * g for g in GRAVITY_DIRECTION], dim=-1)
    ground = [] if ground_radius is None else [(z / ground_radius).clamp(-1.0, 1.0)]
    pitch_part = [] if pitch is None else [pitch.to(dtype)]
    return torch.cat(
        [
            normalizer.velocity(velocity),
            normalizer.height(z),
            normalizer.log_mass(mass),
            material.to(dtype),
            stiffness.to(dtype),
            depth.to(dtype).unsqueeze(-1),
            is_leaf.to(dtype).unsqueeze(-1),
            root,
            gravity,
            *ground,
            *pitch_part,
        ],
        dim=-1,
    )


class HRN(nn.Module):
    r"""Hierarchical Relation Network (Mrowca et al. 2018) with optional graph-convolutional dropout.

    .. math::
        e &= e_F + e_C + e_H \\
        e &\leftarrow e + \mathrm{L2A}(s, e, x) \\
        e &\leftarrow e + \mathrm{WS}(s, e, x) \\
        e &\leftarrow e + \mathrm{A2D}(s, e, x) \\
        \hat u_i &= \psi(s_i, e_i)

    :math:`e_F` (:class:`ForceModule`) and :math:`e_C` (:class:`CollisionModule`) are skipped when
    there is no force / collision edge (same result). The output is the normalised change of each
    particle's local velocity (zero on static particles); :func:`hrn_pyg.sim.step.decode` turns it
    into positions. A dropout mask (:meth:`sample_masks`) is a ``[B, hidden]`` table per module, one
    row per trajectory copy; without masks the model is deterministic.

    **Shapes:**
        - **input:** :class:`HRNInputs` over :math:`|\mathcal{V}|` nodes; masks ``{name: (B, H)}``
        - **output:** :math:`(|\mathcal{V}|, 3)`
    """

    def __init__(self, config: HRNConfig = HRNConfig()) -> None:
        super().__init__()
        self.config = config
        if config.equivariant:
            self._build_equivariant(config)
        else:
            self._build_plain(config)
        self.normalizer = Normalizer()
        # [G, 3] signs of the mirror group's reflections: made once, moved with the module, so a
        # step builds no tensor from host data (none to copy, nothing a CUDA graph cannot hold)
        self.register_buffer("mirror_signs", reflection_signs(config.mirror_group), persistent=False)

    def _build_plain(self, config: HRNConfig) -> None:
        s, d, mlp = config.state_dim, config.effect_dim, config.mlp
        self.force = ForceModule(s, d, mlp)
        self.collision = CollisionModule(s, d, mlp, reads_force=config.collision_force)
        self.history = HistoryModule(s, d, mlp)
        rest = config.rest_offsets
        self.l2a = PropagationModule(s, d, mlp, name="l2a", rest_offsets=rest)
        self.ws = PropagationModule(s, d, mlp, name="ws", rest_offsets=rest)
        self.a2d = PropagationModule(s, d, mlp, name="a2d", rest_offsets=rest)
        self.state = NextStateModule(s, d, mlp)

    def _build_equivariant(self, config: HRNConfig) -> None:
        """The modules of :mod:`hrn_pyg.nn.equivariant`, under the same names (one state column
        fewer: the horizontal velocity is read as its length)."""
        s, d, c, mlp = config.state_dim - 1, config.effect_dim, config.vector_channels, config.mlp
        self.force = equivariant.ForceModule(s, d, c, mlp)
        self.collision = equivariant.CollisionModule(s, d, c, mlp, reads_force=config.collision_force)
        self.history = equivariant.HistoryModule(s, d, c, mlp)
        rest = config.rest_offsets
        self.l2a = equivariant.PropagationModule(s, d, c, mlp, name="l2a", rest_offsets=rest)
        self.ws = equivariant.PropagationModule(s, d, c, mlp, name="ws", rest_offsets=rest)
        self.a2d = equivariant.PropagationModule(s, d, c, mlp, name="a2d", rest_offsets=rest)
        self.state = equivariant.NextStateModule(s, d, c, mlp)

    def reset_parameters(self) -> None:
        for name in MODULE_NAMES:
            getattr(self, name).reset_parameters()

    def sample_masks(
        self,
        num_copies: int,
        rate: float | None = None,
        generator: torch.Generator | None = None,
    ) -> dict[str, Tensor]:
        """One fresh mask per module of ``config.dropout_modules``, one row per trajectory copy; call once
        per step. ``rate`` defaults to ``config.dropout_rate``. With ``mirror_average`` each mask has
        ``G * num_copies`` rows, one block per element of ``config.mirror_group``."""
        rate = self.config.dropout_rate if rate is None else rate
        device = self.normalizer.velocity_std.device
        return {
            name: dropout_mask(self.mask_rows(num_copies), self.config.hidden, rate, generator, device)
            for name in self.config.dropout_modules
        }

    def mask_rows(self, num_copies: int) -> int:
        """Rows of a dropout mask for ``num_copies`` trajectory copies: one per copy and pass."""
        return num_copies * len(self.config.mirror_group)

    def forward(self, inputs: HRNInputs, masks: Mapping[str, Tensor] | None = None) -> Tensor:
        masks = dict(masks or {})
        unknown = set(masks) - set(self.config.dropout_modules)
        if unknown:
            raise ValueError(
                f"HRN: masks given for {sorted(unknown)}, not in dropout_modules {self.config.dropout_modules}"
            )
        columns = inputs.state.size(-1)
        if columns != self.config.state_dim:
            raise ValueError(f"HRN: state has {columns} columns, this config needs {self.config.state_dim}")
        if self.config.rest_offsets and inputs.rest_pos is None:
            raise ValueError("HRN: config.rest_offsets needs inputs.rest_pos (the rest shape)")
        group = self.config.mirror_group
        if len(group) == 1:
            return self._pass(inputs, masks)
        norm = self.normalizer
        mean, std = norm.target_stats(inputs.is_root)
        flips = self.mirror_signs.to(inputs.pos.dtype)  # [G, 3]
        total = None
        for axes, flip, pass_masks in zip(group, flips, split_mirror_masks(masks, len(group))):
            if axes:  # the scene mapped, the answer mapped back
                swap = SWAP_XY in axes
                moved = self._pass(transformed_inputs(inputs, norm, flip, swap), pass_masks)
                out = untransform_normalised(moved, mean, std, flip, swap)
            else:
                out = self._pass(inputs, pass_masks)
            total = out if total is None else total + out
        return total / len(group)

    def _pass(self, inputs: HRNInputs, masks: Mapping[str, Tensor]) -> Tensor:
        """One pass of the modules (the whole network without the mirror average)."""
        if self.config.equivariant:
            return self._equivariant_pass(inputs, masks)
        x, s, b, rest, options = inputs.pos, inputs.state, inputs.batch, inputs.rest_pos, inputs.options
        effect = self.history(s, inputs.prev_state, masks.get("history"), b)
        run_force, run_collision = self._busy_modules(inputs)
        if run_force:
            effect = effect + self.force(s, inputs.force, masks.get("force"), b, dense=options.fixed_shape)
        if run_collision:
            effect = effect + self.collision(s, x, inputs.collision, masks.get("collision"), b,
                                             edge_weight=options.collision_weight, force=self._collision_force(inputs))
        for name, edges, d, r in propagation_phases(inputs):
            phase = getattr(self, name)
            effect = effect + phase(s, effect, x, edges, masks.get(name), b, rest, degree=d, rest_offset=r)
        return self.state(s, effect, inputs.is_static, masks.get("state"), b)

    def _equivariant_pass(self, inputs: HRNInputs, masks: Mapping[str, Tensor]) -> Tensor:
        """One pass of the equivariant modules: the phases of :meth:`_pass`, each adding to the scalar
        effect and the vector channels (squashed after each stage, :func:`~hrn_pyg.nn.equivariant.features.squash`)."""
        x, b, rest, options = inputs.pos, inputs.batch, inputs.rest_pos, inputs.options
        s, velocity = invariant_state(inputs.state), inputs.state[:, :2]
        effect, vectors = self.history(s, invariant_state(inputs.prev_state), velocity,
                                       inputs.prev_state[:, :2], masks.get("history"), b)
        run_force, run_collision = self._busy_modules(inputs)
        if run_force:
            e, v = self.force(s, velocity, inputs.force, masks.get("force"), b, dense=options.fixed_shape)
            effect, vectors = effect + e, vectors + v
        if run_collision:
            e, v = self.collision(s, velocity, x, inputs.collision, masks.get("collision"), b,
                                  edge_weight=options.collision_weight, force=self._collision_force(inputs))
            effect, vectors = effect + e, vectors + v
        vectors = squash(vectors)
        for name, edges, d, r in propagation_phases(inputs):
            e, v = getattr(self, name)(s, velocity, effect, vectors, x, edges, masks.get(name), b, rest,
                                       degree=d, rest_offset=r)
            effect, vectors = effect + e, squash(vectors + v)
        return self.state(s, velocity, effect, vectors, inputs.is_static, masks.get("state"), b)

    def _collision_force(self, inputs: HRNInputs) -> Tensor | None:
        """The force the collision module reads (``collision_force``), else None."""
        return inputs.force if self.config.collision_force else None

    def _busy_modules(self, inputs: HRNInputs) -> tuple[bool, bool]:
        """Whether the force and the collision module run this pass: always without
        ``skip_idle_modules``, else only with a nonzero force (``StepOptions.force_active``, or
        one host read of the force) and with a collision edge."""
        if not self.config.skip_idle_modules:
            return True, True
        force_active = inputs.options.force_active
        if force_active is None:
            force_active = bool(inputs.force.ne(0).any())
        return bool(force_active), inputs.collision.size(1) > 0

    def __repr__(self) -> str:
        c = self.config
        return (
            f"{self.__class__.__name__}(hidden={c.hidden}, depth={c.depth}, effect_dim={c.effect_dim}, "
            f"collision_radius={c.collision_radius}, dropout={c.dropout_rate} on {list(c.dropout_modules)}, "
            f"rigid_fit={c.rigid_fit}, rest_offsets={c.rest_offsets}, ground_contact={c.ground_contact}"
            + (", rigid_fit_rest=True" if getattr(c, "rigid_fit_rest", False) else "")
            + (f", pitch_aware=True, reference_pitch={c.reference_pitch}" if c.pitch_aware else "")
            + (", corotated_rest=True" if getattr(c, "corotated_rest", False) else "")
            + (f", cloth_clearance={c.cloth_clearance}" if getattr(c, "cloth_clearance", 0.0) else "")
            + (f", rest_friction={c.rest_friction}" if getattr(c, "rest_friction", 0.0) else "")
            + (f", equivariant=True, vector_channels={c.vector_channels}" if getattr(c, "equivariant", False) else "")
            + (", collision_force=True" if getattr(c, "collision_force", False) else "")
            + (", ground_projection=True" if c.ground_projection else "")
            + (", ground_projection_rigid=False" if c.ground_projection and not c.ground_projection_rigid else "")
            + (f", rigid_ground_depth={c.rigid_ground_depth}" if c.ground_projection and c.ground_projection_rigid
               and c.rigid_ground_depth else "")
            + (f", rigid_ground_speed={c.rigid_ground_speed}" if c.ground_projection and c.ground_projection_rigid
               and c.rigid_ground_speed else "")
            + (f", rigid_ground_lift={c.rigid_ground_lift}" if c.ground_projection and c.ground_projection_rigid
               and getattr(c, "rigid_ground_lift", 0.0) else "")
            + (", ground_lift_velocity=False" if not c.ground_lift_velocity else "")
            + (f", mirror_average=True, mirror_planes={c.mirror_planes!r})" if c.mirror_average else ")")
        )


def reflection_signs(group: tuple[tuple[int | str, ...], ...]) -> Tensor:
    """``[G, 3]`` float: for each element of ``group`` (the axes it negates, after exchanging x
    and y where it holds :data:`SWAP_XY`), -1 on those axes and +1 on the others (the buffer
    ``HRN.mirror_signs``)."""
    return torch.tensor([[-1.0 if a in axes else 1.0 for a in range(3)] for axes in group])


def transform_normalised(x: Tensor, mean: Tensor | float, std: Tensor, flip: Tensor, swap: bool = False) -> Tensor:
    r"""The first three columns of ``x = (v - mean) / std`` under :math:`v \mapsto f \odot P v`
    (``flip`` :math:`f \in \{\pm 1\}^3`, :math:`P` exchanges x and y when ``swap``): denormalised,
    mapped, normalised again; the other columns as they are. ``mean = 0`` maps a force.

    **Shapes:** ``x`` ``[N, C]``; ``mean``, ``std`` ``[3]`` or ``[N, 3]``; ``flip`` ``[3]``.
    """
    v = x[:, :3] * std + mean
    if swap:
        v = v[:, SWAPPED_AXES]
    return torch.cat([(v * flip - mean) / std, x[:, 3:]], dim=-1)


def untransform_normalised(x: Tensor, mean: Tensor | float, std: Tensor, flip: Tensor, swap: bool = False) -> Tensor:
    r"""The inverse of :func:`transform_normalised`: :math:`v' \mapsto P (f \odot v') = (P f)
    \odot P v'`, so the same map with the signs exchanged too when ``swap`` (a pure reflection is
    its own inverse). **Shapes:** as :func:`transform_normalised`."""
    return transform_normalised(x, mean, std, flip[list(SWAPPED_AXES)] if swap else flip, swap)


def transformed_inputs(inputs: HRNInputs, normalizer: Normalizer, flip: Tensor, swap: bool = False) -> HRNInputs:
    r"""The network inputs of the scene under :math:`v \mapsto f \odot P v` (a mirror, a half- or
    quarter-turn about z, or a diagonal mirror): velocities and forces through
    :func:`transform_normalised`, positions through one length scale; edges, masses, materials,
    heights and gravity unchanged."""
    def move(p: Tensor) -> Tensor:
        return (p[:, SWAPPED_AXES] if swap else p) * flip

    v_mean, v_std = normalizer.velocity_mean, normalizer.velocity_std
    return inputs._replace(
        state=transform_normalised(inputs.state, v_mean, v_std, flip, swap),
        prev_state=transform_normalised(inputs.prev_state, v_mean, v_std, flip, swap),
        pos=move(inputs.pos),
        force=transform_normalised(inputs.force, 0.0, normalizer.force_std, flip, swap),
        rest_pos=None if inputs.rest_pos is None else move(inputs.rest_pos),
        hierarchy=None if inputs.hierarchy is None else moved_hierarchy(inputs.hierarchy, move),
    )


def moved_hierarchy(hierarchy: HierarchyConstants, move: Callable[[Tensor], Tensor]) -> HierarchyConstants:
    """``hierarchy`` of a scene mapped by ``move`` (a signed permutation of the axes, exact in
    floats): the degrees as they are, each rest offset moved (the offset of the moved rest
    positions, bit for bit)."""
    if hierarchy.rest_offset is None:
        return hierarchy
    return hierarchy._replace(rest_offset=tuple(move(r) for r in hierarchy.rest_offset))


def split_mirror_masks(masks: Mapping[str, Tensor], passes: int = 2) -> list[dict[str, Tensor]]:
    """Masks of a mirror-averaged step (:meth:`HRN.sample_masks`: ``passes * copies`` rows) ->
    one dict per pass, in the order of ``HRNConfig.mirror_group`` (the direct pass first)."""
    per_pass: list[dict[str, Tensor]] = [{} for _ in range(passes)]
    for name, mask in masks.items():
        if mask.size(0) % passes:
            raise ValueError(f"HRN: a mirror-averaged model takes masks of {passes} x copies rows (one block "
                             f"per pass, HRN.sample_masks); {name!r} has {mask.size(0)}")
        for block, rows in zip(per_pass, mask.chunk(passes, dim=0)):
            block[name] = rows
    return per_pass
