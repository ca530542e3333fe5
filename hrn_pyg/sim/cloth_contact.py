r"""Cloth and soft bodies kept out of the objects they fall on: a projection of each step's
deformable leaves.

The network predicts how a cloth drapes over an object, or a soft body lands on one, from the
collision edges between them, and nothing stops a leaf from ending a step inside the object. This
rule, applied after the network like the ground projection
(:attr:`~hrn_pyg.nn.hrn.HRNConfig.cloth_clearance` for cloth leaves,
:attr:`~hrn_pyg.nn.hrn.HRNConfig.solid_clearance` for the leaves of soft bodies and rigid
objects), moves such a leaf back out. Below, "cloth leaf" reads "projected leaf": a moving leaf of
a cloth, or of a soft body or a rigid object when ``solid_clearance`` is on; the object it is kept
out of is any other object but a cloth. A rigid object is not bent: it moves as a whole, by the
longest push any of its leaves needs.

**Surface and normals.** Every object that is not cloth is a set of leaves on a lattice of pitch
:math:`p`. At rest, a leaf :math:`j` whose neighbours within :math:`\sqrt{3}\,p` (its lattice
neighbourhood) do not surround it is a *surface leaf*, with the outward normal

.. math::
    \bar n_j = -\bar m_j / \lVert \bar m_j \rVert, \qquad
    \bar m_j = \frac{1}{|\mathcal N_j|} \sum_{k \in \mathcal N_j} (\bar x_k - \bar x_j)
    \quad\text{when } \lVert \bar m_j \rVert > \mu\, p

(on a flat face :math:`\lVert \bar m_j \rVert = 9p/17`; an interior leaf's neighbours balance and
give 0). The object's normals turn with it: :math:`n_j = R_o \bar n_j`, :math:`R_o` the
mass-weighted best rotation from the rest leaves onto the current ones
(:func:`~hrn_pyg.nn.rigid.rigid_motion`: exact for a rigid body, the co-rotated frame of a soft
body; a static object keeps :math:`R_o = I`).

**The rule.** After a step, a moving cloth leaf :math:`c` lies *inside* object :math:`o` when at
least one surface leaf of :math:`o` is within :math:`\rho = p` of it and it lies behind the plane
of every such leaf,

.. math::
    s_{cj} = (x_c - x_j) \cdot n_j < \delta \quad \forall j \in o,\ \lVert x_c - x_j \rVert < \rho,

and is then moved along the normal of the nearest of them to :math:`\delta` in front of its plane
(:math:`\rho` grows by the length of the leaf's step, so a leaf that crossed the surface fast is
still seen):
:math:`x_c \leftarrow x_c + (\delta - s_{cj^*})\, n_{j^*}` (:math:`\delta` =
``cloth_clearance`` pitches). The plane of the outermost leaf centres is the surface of the solid
that :mod:`hrn_pyg.sim.penetration` counts cloth leaves inside, so a leaf that the rule leaves
alone on a flat face is not counted there. Asking every nearby plane, not only the nearest,
keeps a leaf beside a convex edge or corner (behind the corner's diagonal plane, in front of the
face's) where it is; a leaf inside a concave notch may be missed, never pushed wrongly. Pairs
come from the step's collision edges at :math:`x_t` (radius above :math:`\rho` plus a step's
move). Only cloth leaves move; the object is not pushed back (the network already decided its
motion), and a cloth leaf held still by sleeping stays where it is.

**Shapes.** :func:`cloth_contact` gives a :class:`ClothContact` of a graph with ``N`` nodes once
per rollout; :meth:`ClothContact.project` maps ``pos`` ``[N, 3]`` to ``[N, 3]``, and calling
the contact maps a step's prediction (positions and velocities) to the projected one, which is
how a rollout applies it (``StepOptions.position_projection``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.data.graph import CHILD_TO_PARENT, COLLISION, NODE, leaf_to_ancestor_mean, node_pitch
from hrn_pyg.data.kinds import CLOTH, RIGID, SOFT, STATIC
from hrn_pyg.nn.rigid import rigid_motion
from hrn_pyg.nn.state import to_local_velocity
from hrn_pyg.sim.step import Prediction, object_of

#: a leaf is on the surface when its neighbours' mean offset is longer than this many pitches
SURFACE_OFFSET = 0.1
#: the neighbourhood of a leaf at rest, in pitches (the 26 lattice neighbours, with slack)
NEIGHBOURHOOD = 1.8


def surface_normals(rest: np.ndarray, pitch: float) -> np.ndarray:
    """``[P, 3]`` -> ``[P, 3]``: the outward unit normal of every surface leaf of one object at rest
    (module docstring), zero for an interior leaf (and for every leaf of a part one leaf thick,
    whose neighbours balance too)."""
    rest = np.asarray(rest, dtype=np.float64)
    normals = np.zeros_like(rest)
    if len(rest) < 2:
        return normals
    pairs = cKDTree(rest).query_pairs(NEIGHBOURHOOD * pitch, output_type="ndarray")
    if len(pairs) == 0:
        return normals
    offset = rest[pairs[:, 1]] - rest[pairs[:, 0]]
    total = np.zeros_like(rest)
    np.add.at(total, pairs[:, 0], offset)
    np.add.at(total, pairs[:, 1], -offset)
    count = np.bincount(pairs.ravel(), minlength=len(rest))[:, None]
    mean = total / np.maximum(count, 1)
    length = np.linalg.norm(mean, axis=1, keepdims=True)
    surface = length[:, 0] > SURFACE_OFFSET * pitch
    normals[surface] = -mean[surface] / length[surface]
    return normals


@dataclass(frozen=True)
class ClothContact:
    """The constants of :func:`cloth_contact` for one graph of ``N`` nodes (module docstring).

    ``rest`` ``[N, 3]`` the rest positions the normals belong to; ``normal`` ``[N, 3]`` the rest
    normal of every surface leaf (zero elsewhere); ``surface``, ``cloth``, ``static``, ``leaf``
    ``[N]`` bool: the surface leaves of objects that are not cloth, the leaves projected (moving
    leaves of cloth, and of soft bodies and rigid objects under a solid clearance), the rows of
    static objects, the leaves; ``rigid`` ``[N]`` bool: the projected leaves of rigid objects,
    which move with their object, and ``rigid_rows`` ``[N]`` bool every moving leaf of a rigid
    object; ``kind`` ``[N]`` long each node's material code and ``size`` ``[R]`` each object's leaf
    count (of two bodies of one material only the smaller gives way); ``group`` ``[N]`` long and
    ``count``: every node's object;
    ``reach``, ``clearance`` ``[N]``: :math:`\\rho` and :math:`\\delta` in metres at each node's
    pitch.
    """

    rest: Tensor
    normal: Tensor
    surface: Tensor
    cloth: Tensor
    static: Tensor
    leaf: Tensor
    rigid: Tensor
    rigid_rows: Tensor
    kind: Tensor
    size: Tensor
    group: Tensor
    count: int
    reach: Tensor
    clearance: Tensor

    def current_normals(self, pos: Tensor, rows: Tensor | None = None) -> Tensor:
        """The rest normals of ``rows`` (default: all ``N``) turned with their objects onto
        ``pos`` ``[N, 3]`` (static objects: as at rest), ``[len(rows), 3]``."""
        rows = torch.arange(pos.size(0), device=pos.device) if rows is None else rows
        _, _, rotation = rigid_motion(self.rest, pos, self.leaf.to(pos.dtype), self.group, self.count)
        eye = torch.eye(3, dtype=pos.dtype, device=pos.device).expand_as(rotation)
        rotation = torch.where(torch.isfinite(rotation).all(dim=(1, 2), keepdim=True), rotation, eye)
        normal = self.normal[rows]
        turned = torch.einsum("nij,nj->ni", rotation[self.group[rows]], normal)
        return torch.where(self.static[rows].unsqueeze(-1), normal, turned)

    def project(self, graph: HeteroData, pos: Tensor, movable: Tensor | None = None) -> Tensor:
        """``pos`` ``[N, 3]`` (:math:`x_{t+1}`, a step of ``graph`` at :math:`x_t`) with every
        cloth leaf that is inside another object moved out (module docstring) and the ancestors
        re-derived; returned as it is, the same tensor, when no leaf moves. ``movable`` ``[N]``
        bool (optional): only these rows may move (a step with sleeping objects: the awake ones).
        """
        src, dst = graph[COLLISION].edge_index
        cloth_end = torch.cat([dst, src])
        solid_end = torch.cat([src, dst])
        cloth = self.cloth if movable is None else self.cloth & movable
        keep = cloth[cloth_end] & self.surface[solid_end] & (self.group[cloth_end] != self.group[solid_end])
        # two bodies of one material give way one way only: the smaller is kept out of the larger
        same = self.kind[cloth_end] == self.kind[solid_end]
        size_c, size_j = self.size[self.group[cloth_end]], self.size[self.group[solid_end]]
        yields = (size_c < size_j) | ((size_c == size_j) & (self.group[cloth_end] < self.group[solid_end]))
        keep = keep & (~same | yields)
        if not bool(keep.any()):
            return pos
        c, j = cloth_end[keep], solid_end[keep]
        arm = pos[c] - pos[j]
        distance = arm.norm(dim=-1)
        # a leaf that moved far in the step may be that far in: the reach grows by its step
        reach = self.reach[c] + (pos[c] - graph[NODE].pos[c]).norm(dim=-1)
        near = distance < reach
        c, j, arm, distance = c[near], j[near], arm[near], distance[near]
        if c.numel() == 0:
            return pos
        normal = self.current_normals(pos, j)
        height = (arm * normal).sum(-1)  # s_cj
        # one row per (cloth leaf, object) pair: inside when behind every near plane of that object
        pair, slot = torch.unique(c * self.count + self.group[j], return_inverse=True)
        highest = height.new_full((pair.numel(),), -torch.inf).scatter_reduce(0, slot, height, "amax")
        inside = highest[slot] < self.clearance[c]
        nearest = distance.new_full((pair.numel(),), torch.inf).scatter_reduce(0, slot, distance, "amin")
        chosen = torch.nonzero(inside & (distance == nearest[slot])).flatten()
        if chosen.numel() == 0:
            return pos
        # one push per cloth leaf: its first chosen pair (a tie in distance, or a leaf inside two objects)
        first = c.new_full((pos.size(0),), c.numel()).scatter_reduce(0, c[chosen], chosen, "amin")
        picked = first[first < c.numel()]
        push = (self.clearance[c[picked]] - height[picked]).unsqueeze(-1) * normal[picked]
        leaf_rows = c[picked]
        whole = self.rigid[leaf_rows]
        if bool(whole.any()):  # a rigid object moves as a whole, by its leaves' longest push
            owner, length = self.group[leaf_rows[whole]], push[whole].norm(dim=-1)
            longest = length.new_zeros(self.count).scatter_reduce(0, owner, length, "amax")
            chosen = torch.nonzero(length == longest[owner]).flatten()
            shift = push.new_zeros(self.count, 3).index_copy(0, owner[chosen], push[whole][chosen])
            moved = self.rigid_rows & (longest > 0)[self.group]
            pos = torch.where(moved.unsqueeze(-1), pos + shift[self.group], pos)
            leaf_rows, push = leaf_rows[~whole], push[~whole]
        return leaf_to_ancestor_mean(pos.index_add(0, leaf_rows, push), graph)

    def __call__(self, graph: HeteroData, prediction: Prediction, movable: Tensor | None = None) -> Prediction:
        """A step's :class:`~hrn_pyg.sim.step.Prediction` after :meth:`project`: a moved node's
        velocity is its whole move from :math:`x_t` (the prediction's ``prev_pos`` when the ground
        lift moved it), and the local velocities of a cloth that moved are derived anew. The
        same prediction when nothing moves."""
        pos, local, velocity, prev_pos = prediction
        projected = self.project(graph, pos, movable)
        if projected is pos:
            return prediction
        since = graph[NODE].pos if prev_pos is None else prev_pos
        moved = (projected != pos).any(-1)
        touched = torch.zeros(self.count, dtype=torch.bool, device=pos.device).index_fill_(
            0, self.group[moved], True)[self.group]
        velocity = torch.where(moved.unsqueeze(-1), projected - since, velocity)
        fresh = to_local_velocity(velocity, graph[CHILD_TO_PARENT].edge_index)
        return Prediction(projected, torch.where(touched.unsqueeze(-1), fresh, local), velocity, prev_pos)


def cloth_contact(graph: HeteroData, clearance: float, reach: float = 1.0,
                  objects: tuple[Tensor, int] | None = None, solid_clearance: float = 0.0,
                  project_cloth: bool = True) -> ClothContact | None:
    """The :class:`ClothContact` of ``graph`` (rest shape: its ``rest_pos``, else its ``pos``),
    with ``clearance`` :math:`\\delta` for cloth leaves, ``solid_clearance`` for the leaves of soft
    bodies and rigid objects (0: they are not projected) and ``reach`` :math:`\\rho`, in pitches
    of each node's graph (one host pass over the objects); None when the scene has no leaf to
    project or no other object with a surface, so the rule has nothing to do. Needs the graph's
    pitch. ``objects``: :func:`~hrn_pyg.sim.step.object_of` of ``graph``, if the caller has it;
    ``project_cloth=False``: cloth leaves are left alone (only the solid clearance applies)."""
    if not clearance >= 0 or not solid_clearance >= 0 or not reach > 0:
        raise ValueError(f"cloth_contact: clearances must be >= 0 and reach > 0, got {clearance}, "
                         f"{solid_clearance}, {reach}")
    store = graph[NODE]
    material = store.material.argmax(dim=1)
    leaf = store.is_leaf
    moving = leaf & ~store.is_static
    cloth = moving & (material == CLOTH) if project_cloth else torch.zeros_like(leaf)
    rigid_rows = moving & (material == RIGID)
    solid = moving & ((material == SOFT) | (material == RIGID)) if solid_clearance > 0 else torch.zeros_like(leaf)
    projected = cloth | solid
    if not bool(projected.any()):
        return None
    pitch = node_pitch(graph).to(store.pos.dtype)
    rest = store.rest_pos if "rest_pos" in store else store.pos
    group, count = object_of(graph) if objects is None else objects
    normal = torch.zeros_like(rest)
    solid_leaf = leaf & (material != CLOTH)
    points = rest.detach().double().cpu().numpy()
    groups = group.cpu().numpy()
    has_solid = solid_leaf.cpu().numpy()
    pitches = pitch.double().cpu().numpy()
    for obj in np.unique(groups[has_solid]):
        rows = np.flatnonzero((groups == obj) & has_solid)
        found = surface_normals(points[rows], float(pitches[rows[0]]))
        normal[torch.from_numpy(rows).to(rest.device)] = torch.from_numpy(found).to(rest)
    surface = solid_leaf & (normal.norm(dim=-1) > 0)
    if not bool(surface.any()):
        return None
    static = store.is_static | (material == STATIC)
    gap = torch.where(material == CLOTH, torch.full_like(pitch, clearance), torch.full_like(pitch, solid_clearance))
    return ClothContact(rest=rest, normal=normal, surface=surface, cloth=projected, static=static, leaf=leaf,
                        rigid=projected & rigid_rows, rigid_rows=rigid_rows, kind=material,
                        size=torch.zeros(count, dtype=torch.long, device=group.device).index_add(
                            0, group, leaf.long()), group=group, count=count,
                        reach=reach * pitch, clearance=gap * pitch)
