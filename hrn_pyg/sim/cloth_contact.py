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
come from the step's collision edges at :math:`x_t` and from the leaves within :math:`\rho` of
each other at :math:`x_{t+1}` (a fast body crosses several pitches in one step). Only the
projected leaves move; a leaf held still by sleeping stays where it is.

**Stopped where it enters.** A leaf whose step from :math:`x_t` takes it into another object's
solid (the tetrahedra of :mod:`hrn_pyg.sim.penetration`, the solid the plausibility report
measures depth in, moving from :math:`x_t` to :math:`x_{t+1}`) is stopped just before the
fraction of its step at which it enters; a rigid object takes the smallest fraction of its
leaves (fitted rigid again, since a turning body's leaves cut short by one fraction are not quite
rigid), and of two rigid bodies both are stopped where they enter each other. This only
shortens steps, so it adds no energy; the planes above then push out what is left.

**Two rigid bodies** may overlap by :data:`RIGID_DEPTH` pitches beyond the clearance, as
pybullet's own do in this solid (its rigid piles of the validation set reach 0.4-1.2 pitch): a
leaf that ends its step no deeper than that in another rigid body is neither stopped nor pushed,
so a collision the network resolves by itself is left to it (stopping every touch of two cubes
took their bounce and raised their position error at 50 steps by 45 %). The depth was chosen on
the validation sets: at 0.5 pitch two thrown meshes were still stopped where the network had
them part, at 0.9 and 1.0 a pile at pitch 0.025 settled more than a pitch deeper than
pybullet's. A leaf whose step ends outside the other rigid body is stopped where it enters only
if the step ran more than :data:`RIGID_RUN` pitches inside it (through a part of it); a shorter
run is a fast body's straight step cutting across the other's corner, which pybullet's own steps
do at an impact (applied to pybullet's steps of the third validation set's rigid episodes as if
they were predictions, stopping every such step moved 30 of 5880 steps, by up to 10 cm, and cost
the model 5-10 % of its position error on unseen rigid meshes; stopping only the runs, 18; a run
of half a pitch let a pile at 0.035 m sink 7.3 cm into itself, over its bar). A
leaf already inside at :math:`x_t` is not seen by the entry stop, so a rigid body that sinks
deeper than that into another (its leaf's step, less the other body's mean step, points inwards)
loses the part of its step along its pushes out and keeps the rest, so a body sliding off another
goes on sliding (holding it at :math:`x_t` instead stopped such slides for good: 1.23 against 1.17
times the eight-pass model's position error on unseen rigid meshes); if that would still leave it
deeper in the others than at :math:`x_t` and than that depth, it is held there. A stopped or held
body may leave another inside it, so the stops run again on the pairs of the new positions, up to
:data:`STOP_PASSES` times. A leaf inside one object at :math:`x_t` is still stopped where it
enters another.

**Out of the solid.** The planes see a leaf only within :math:`\rho` of the surface, and a
deformed soft body's turned normals may not match its surface. So a second pass asks the solid
itself: a projected leaf in a tetrahedron of another object moves to :math:`\delta` beyond the
nearest *anchor* of the tetrahedron's corners (each leaf's nearest surface leaf at rest), along
the anchor's turned normal. A rigid object moves whole by its leaves' longest push; of two
bodies of one material the smaller moves whole, out of the larger, and of two rigid bodies also
back off the larger's leaves inside it. Each such whole move is at most :data:`SHIFT_LIMIT`
pitches long, so a body deep in another climbs out over a few steps instead of jumping. A rigid
object is never pushed by a soft body, by its planes or its solid: the soft body gives way to it
instead (below), since pushing a box out of a soft body draped over it lifts the box onto it.

**A soft body gives way.** A leaf :math:`q` of another object that is not cloth inside a
tetrahedron of a soft body moves that tetrahedron's corners :math:`v` along a direction
:math:`n` until :math:`(x_v - x_q) \cdot n \ge \delta`: the tetrahedron then lies beyond a
plane through :math:`q`, so :math:`q` is out of it. :math:`n` is whichever of :math:`q`'s
outward normal (at its anchor) and the soft body's inward normals at its corners' anchors needs
the shortest longest push; each corner moves by its longest push, in :data:`GIVE_WAY_PASSES`
passes. This keeps a box's corner out of a soft body draped over it, and the larger of two soft
bodies out of the smaller.

**Stretch limit.** Before and after the passes above, no lattice edge of a soft body (two leaves
one pitch apart at rest) is longer than :data:`STRETCH_LIMIT` times its rest length: an edge
over it has both ends moved towards each other by the excess, equal and opposite, so the body's
centre of mass stays. A future stretched further has tetrahedra so long that another body's
leaves fall inside them far from any surface. The limit was chosen on the validation set of
:mod:`hrn_pyg.sim.plausibility`: at 2.5 a small soft body still sank 5.6 cm into a larger one's
stretched top. 1.5 leaves pybullet's large soft bodies room (in its validation episodes 99 of
100 of their edges never pass 1.1-1.4 times their length) but is stiffer than some of its small
ones (up to 2-3 times): a stiffer body, but a possible one.

**Motion and correction.** A step shortened by the first stretch limit or stopped where it
enters is a motion: the node's velocity becomes its shorter move. The pushes out, the giving way
and the last stretch limit are corrections of place, as in position-based dynamics'
pre-stabilisation: the node keeps its predicted velocity and its :math:`x_t` moves with it, so a
body moved out of another gains height but no speed, and the next step's network and energy
limit do not read the push as a motion.

**Shapes.** :func:`cloth_contact` gives a :class:`ClothContact` of a graph with ``N`` nodes once
per rollout; :meth:`ClothContact.project` maps ``pos`` ``[N, 3]`` to ``[N, 3]``, and calling
the contact maps a step's prediction (positions and velocities) to the projected one, which is
how :class:`~hrn_pyg.sim.rules.StepRules` applies it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.data.graph import CHILD_TO_PARENT, COLLISION, NODE, leaf_to_ancestor_mean, node_pitch
from hrn_pyg.data.kinds import CLOTH, RIGID, SOFT, STATIC
from hrn_pyg.data.radius import collision_edges
from hrn_pyg.nn.rigid import rigid_motion
from hrn_pyg.nn.state import to_local_velocity
from hrn_pyg.sim.penetration import CELL_TETS, INSIDE_TOLERANCE, lattice_cells, tet_coordinates
from hrn_pyg.sim.step import Prediction, object_of, rigid_leaf_positions

#: a leaf is on the surface when its neighbours' mean offset is longer than this many pitches
SURFACE_OFFSET = 0.1
#: the neighbourhood of a leaf at rest, in pitches (the 26 lattice neighbours, with slack)
NEIGHBOURHOOD = 1.8
#: passes of the soft bodies' giving way in one step
GIVE_WAY_PASSES = 4
#: a soft body's lattice edges stretch at most this many times their rest length
STRETCH_LIMIT = 1.5
#: passes of the stretch limit in one step
STRETCH_PASSES = 4
#: the share of its step a leaf stopped where it enters a solid ends before it
ENTRY_MARGIN = 1.0 / 64
#: a whole body (a rigid object, or the smaller of two of one material) moves out of another by at
#: most this many pitches a push
SHIFT_LIMIT = 0.5
#: two rigid bodies may overlap by this many pitches (a leaf this far inside the other's solid,
#: beyond the clearance) before a stop or a push acts between them
RIGID_DEPTH = 0.75
#: a rigid leaf whose step ends outside another rigid body is stopped where it entered it only if
#: the step ran more than this many pitches inside it (through a part of it, not across a corner)
RIGID_RUN = 0.25
#: passes of the stops in one step (a body stopped can leave another inside it)
STOP_PASSES = 4


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


def padded_rows(owner: np.ndarray, item: np.ndarray, rows: int) -> np.ndarray:
    """``[rows, M]``: the ``item`` of each row, from pairs ``(owner[i], item[i])``, padded with
    -1 (``M`` the most items of one row, at least 1)."""
    order = np.argsort(owner, kind="stable")
    owner, item = owner[order], item[order]
    count = np.bincount(owner, minlength=rows)
    table = np.full((rows, max(int(count.max(initial=0)), 1)), -1, dtype=np.int64)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    table[owner, np.arange(len(owner)) - start[owner]] = item
    return table


@dataclass(frozen=True)
class SolidMesh:
    """One object's solid (:mod:`hrn_pyg.sim.penetration`) at rest, in its leaves' indices:
    ``tets [K, 4]``, ``leaf_tets [P, M]`` the tetrahedra of the cells each leaf is a corner of
    (padded with -1), ``anchor [P]`` each leaf's nearest surface leaf (-1: none) and ``edges
    [E, 2]`` the lattice edges (leaves one pitch apart at rest)."""

    tets: np.ndarray
    leaf_tets: np.ndarray
    anchor: np.ndarray
    edges: np.ndarray


def solid_mesh(rest: np.ndarray, normal: np.ndarray, pitch: float) -> SolidMesh:
    """The :class:`SolidMesh` of one object that is not cloth from its leaves at rest ``[P, 3]``
    and their :func:`surface_normals`; no tetrahedra when the leaves are not on a lattice (as a
    rest shape taken from a deformed frame may not be) or form no full cell."""
    try:
        cells = lattice_cells(rest, pitch)
    except ValueError:
        cells = np.zeros((0, 8), dtype=np.int64)
    tets = cells[:, CELL_TETS].reshape(-1, 4)
    tet_of_cell = np.arange(len(tets)).reshape(-1, len(CELL_TETS))  # [C, 6]
    leaf_tets = padded_rows(np.repeat(cells.reshape(-1), len(CELL_TETS)),
                            np.repeat(tet_of_cell, 8, axis=0).reshape(-1), len(rest))
    anchor = np.full(len(rest), -1, dtype=np.int64)
    surface = np.flatnonzero(np.linalg.norm(normal, axis=1) > 0)
    if len(surface):
        anchor = surface[cKDTree(rest[surface]).query(rest)[1]]
    edges = cKDTree(rest).query_pairs((1.0 + 1e-2) * pitch, output_type="ndarray").reshape(-1, 2)
    return SolidMesh(tets, leaf_tets, anchor, edges.astype(np.int64))


def unique_pairs(first: Tensor, second: Tensor, span: int) -> tuple[Tensor, Tensor]:
    """The distinct pairs ``(first[i], second[i])`` (``[P]`` long each, ``0 <= second < span``),
    sorted (no host read)."""
    if first.numel() == 0:
        return first, second
    key = torch.unique(first * span + second)
    return key // span, key % span


def longest_per(index: Tensor, push: Tensor, size: int) -> tuple[Tensor, Tensor]:
    """Of pushes ``[M, 3]`` in ``size`` groups (``index [M]``): each group's longest push
    ``[size, 3]`` (the first of a tie; zero for a group with none) and its length ``[size]``."""
    length = push.norm(dim=-1)
    longest = length.new_zeros(size).scatter_reduce(0, index, length, "amax")
    pick = torch.where(length == longest[index], torch.arange(index.numel(), device=index.device), index.numel())
    first = index.new_full((size,), index.numel()).scatter_reduce(0, index, pick, "amin")
    has = first < index.numel()
    chosen = push.new_zeros(size, 3)
    chosen[has] = push[first[has]]
    return chosen, longest


def shortened(shift: Tensor, longest: Tensor) -> Tensor:
    """Each row of ``shift`` ``[M, 3]`` with its length cut to at most ``longest`` ``[M]``."""
    length = shift.norm(dim=-1, keepdim=True)
    return shift * (longest.unsqueeze(-1) / length.clamp(min=1e-12)).clamp(max=1.0)


def scene_solid_mesh(meshes: list[tuple[np.ndarray, SolidMesh]], rows: int) -> SolidMesh:
    """One :class:`SolidMesh` over a scene's ``rows`` nodes from each object's rows and mesh
    (local indices): indices made global, the tables padded alike."""
    width = max([mesh.leaf_tets.shape[1] for _, mesh in meshes], default=1)
    leaf_tets = np.full((rows, width), -1, dtype=np.int64)
    anchor = np.full(rows, -1, dtype=np.int64)
    tets, edges, count = [], [], 0
    for at, mesh in meshes:
        tets.append(at[mesh.tets])
        edges.append(at[mesh.edges])
        leaf_tets[at, : mesh.leaf_tets.shape[1]] = np.where(mesh.leaf_tets >= 0, mesh.leaf_tets + count, -1)
        anchor[at] = np.where(mesh.anchor >= 0, at[mesh.anchor.clip(min=0)], -1)
        count += len(mesh.tets)

    def joined(parts: list[np.ndarray], width: int) -> np.ndarray:
        return np.concatenate(parts, dtype=np.int64) if parts else np.zeros((0, width), dtype=np.int64)

    return SolidMesh(joined(tets, 4), leaf_tets, anchor, joined(edges, 2))


class StepPairs(NamedTuple):
    """The pairs one step of :class:`ClothContact` works on, each ``[P]`` long (its own ``P``):
    ``(a, b)`` the contact pairs of leaves of different objects, both ways; ``(c, j)`` those of a
    projected leaf ``c`` that may be pushed out of ``j``'s object; ``(leaf, tet)`` each such leaf
    and the tetrahedra near it; ``(back, back_tet)`` of two rigid bodies, the other's leaves and
    the tetrahedra near them."""

    a: Tensor
    b: Tensor
    c: Tensor
    j: Tensor
    leaf: Tensor
    tet: Tensor
    back: Tensor
    back_tet: Tensor


@dataclass(frozen=True)
class ClothContact:
    """The constants of :func:`cloth_contact` for one graph of ``N`` nodes (module docstring).

    ``rest`` ``[N, 3]`` the rest positions the normals belong to; ``normal`` ``[N, 3]`` the rest
    normal of every surface leaf (zero elsewhere); ``surface``, ``cloth``, ``static``, ``leaf``
    ``[N]`` bool: the surface leaves of objects that are not cloth, the leaves projected (moving
    leaves of cloth, and of soft bodies and rigid objects under a solid clearance), the rows of
    static objects, the leaves; ``rigid`` ``[N]`` bool: the projected leaves of rigid objects,
    which move with their object, and ``rigid_rows`` ``[N]`` bool every moving leaf of a rigid
    object (``rigid_object`` ``[R]`` bool: the objects that have one; ``has_rigid``: whether any
    does); ``kind`` ``[N]`` long each node's material code
    and ``size`` ``[R]`` each object's leaf count (of two bodies of one material only the smaller
    gives way); ``group`` ``[N]`` long and
    ``count``: every node's object; ``reach``, ``clearance`` ``[N]``: :math:`\\rho` and
    :math:`\\delta` in metres at each node's pitch, ``pitch`` ``[N]`` that pitch; ``tets``,
    ``leaf_tets``, ``anchor``, ``edges``: the scene's :class:`SolidMesh` in node indices.
    """

    rest: Tensor
    normal: Tensor
    surface: Tensor
    cloth: Tensor
    static: Tensor
    leaf: Tensor
    rigid: Tensor
    rigid_rows: Tensor
    rigid_object: Tensor
    has_rigid: bool
    kind: Tensor
    size: Tensor
    group: Tensor
    count: int
    reach: Tensor
    clearance: Tensor
    pitch: Tensor
    tets: Tensor
    leaf_tets: Tensor
    anchor: Tensor
    edges: Tensor

    def rotations(self, pos: Tensor) -> Tensor:
        """``[R, 3, 3]``: each object's best rotation from the rest leaves onto ``pos`` ``[N, 3]``
        (the identity where it is not finite)."""
        _, _, rotation = rigid_motion(self.rest, pos, self.leaf.to(pos.dtype), self.group, self.count)
        eye = torch.eye(3, dtype=pos.dtype, device=pos.device).expand_as(rotation)
        return torch.where(torch.isfinite(rotation).all(dim=(1, 2), keepdim=True), rotation, eye)

    def current_normals(self, pos: Tensor, rows: Tensor | None = None, rotation: Tensor | None = None) -> Tensor:
        """The rest normals of ``rows`` (default: all ``N``) turned with their objects onto
        ``pos`` ``[N, 3]`` (static objects: as at rest), ``[len(rows), 3]``; ``rotation``: the
        :meth:`rotations` of ``pos`` if the caller has them."""
        rows = torch.arange(pos.size(0), device=pos.device) if rows is None else rows
        rotation = self.rotations(pos) if rotation is None else rotation
        normal = self.normal[rows]
        turned = torch.einsum("nij,nj->ni", rotation[self.group[rows]], normal)
        return torch.where(self.static[rows].unsqueeze(-1), normal, turned)

    def contact_pairs(self, graph: HeteroData, pos: Tensor) -> tuple[Tensor, Tensor]:
        """The step's ordered leaf pairs ``(a, b)`` (``[P]`` each) of different objects: the
        collision edges at :math:`x_t` and the leaves within reach at ``pos`` (:math:`x_{t+1}`:
        a fast body may cross several pitches in a step), both ways."""
        store = graph[NODE]
        leaves = torch.nonzero(self.leaf).flatten()
        batch = store.batch[leaves] if "batch" in store else None
        near = leaves[collision_edges(pos[leaves].detach(), store.object[leaves], self.reach[leaves], batch)]
        src, dst = torch.cat([graph[COLLISION].edge_index, near], dim=1)
        return torch.cat([dst, src]), torch.cat([src, dst])

    def movers(self, c: Tensor, j: Tensor, movable: Tensor | None) -> tuple[Tensor, Tensor]:
        """Of the :meth:`contact_pairs` ``(c, j)``, those of a movable projected leaf ``c`` and a
        leaf ``j`` of an object that is not cloth, of two bodies of one material only the smaller
        giving way."""
        cloth = self.cloth if movable is None else self.cloth & movable
        solid = self.leaf & (self.kind != CLOTH)
        keep = cloth[c] & solid[j] & (self.group[c] != self.group[j])
        same = self.kind[c] == self.kind[j]
        size_c, size_j = self.size[self.group[c]], self.size[self.group[j]]
        yields = (size_c < size_j) | ((size_c == size_j) & (self.group[c] < self.group[j]))
        keep = keep & (~same | yields)
        return c[keep], j[keep]

    def project(self, graph: HeteroData, pos: Tensor, movable: Tensor | None = None) -> Tensor:
        """``pos`` ``[N, 3]`` (:math:`x_{t+1}`, a step of ``graph`` at :math:`x_t`) with every
        projected leaf that is inside another object stopped where it entered or moved out, and
        soft bodies giving way (module docstring, in that order), the ancestors re-derived;
        returned as it is, the same tensor, when no leaf moves. ``movable`` ``[N]`` bool
        (optional): only these rows may move (a step with sleeping objects: the awake ones)."""
        return self.stop_and_push(graph, pos, movable)[1]

    def stop_and_push(self, graph: HeteroData, pos: Tensor,
                      movable: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """:meth:`project` in its two parts, ``([N, 3], [N, 3])``: ``pos`` stretched no further
        than the limit and stopped where it enters (a shorter step), and that with the pushes out,
        the giving way and the last stretch limit (corrections of place); each the same tensor as
        the one before it when it moves nothing."""
        pos = self.limit_stretch(graph, pos, movable)
        pairs = self.step_pairs(graph, pos, movable)
        stopped = pos
        for _ in range(STOP_PASSES):
            moved = self.stop(graph, stopped, pairs)
            if moved is stopped:
                break
            stopped, pairs = moved, self.step_pairs(graph, moved, movable)
        if pairs.c.numel() == 0:
            return stopped, stopped
        pos = stopped
        a, b, c, j, leaf, tet, back, back_tet = pairs
        rotation = self.rotations(pos)
        # a rigid object is not pushed out of a soft body: the soft body gives way to it below
        pushed = ~(self.rigid_rows[c] & (self.kind[j] == SOFT))
        rows, push, host = self.plane_pushes(graph, pos, c[pushed], j[pushed], rotation)
        rows, push, _ = self.beyond_rigid_depth(rows, push, host)
        pos = self.apply(graph, pos, rows, push)
        host = self.kind[self.tets[tet, 0]]
        same = self.kind[leaf] == host
        other = ~same & ~(self.rigid_rows[leaf] & (host == SOFT))
        rows, push, _ = self.solid_pushes(pos, leaf[other], tet[other], rotation)
        pos = self.apply(graph, pos, rows, push)
        rows, push, owner = self.solid_pushes(pos, leaf[same], tet[same], rotation)
        rows, push, _ = self.beyond_rigid_depth(rows, push, owner)
        pos = self.shift_whole(graph, pos, self.group[rows], push, movable)
        # of two rigid bodies the smaller also moves back off the larger's leaves inside it
        rows, push, owner = self.beyond_rigid_depth(*self.solid_pushes(pos, back, back_tet, rotation))
        pos = self.shift_whole(graph, pos, owner, -push, movable)
        give = self.cloth & (self.kind == SOFT)  # the projected leaves of soft bodies
        give = give if movable is None else give & movable
        keep = give[b] & (self.kind[a] != CLOTH) & (self.group[a] != self.group[b]) & (self.anchor[a] >= 0)
        leaf, tet = self.tets_near(a[keep], b[keep])  # leaves of other objects near a soft body's
        for _ in range(GIVE_WAY_PASSES):
            moved = self.give_way(graph, pos, leaf, tet, give)
            if moved is pos:
                break
            pos = moved
        return stopped, self.limit_stretch(graph, pos, movable)

    def step_pairs(self, graph: HeteroData, pos: Tensor, movable: Tensor | None) -> StepPairs:
        """The :class:`StepPairs` of a step that ends at ``pos`` ``[N, 3]``."""
        a, b = self.contact_pairs(graph, pos)
        c, j = self.movers(a, b, movable)
        leaf, tet = self.tets_near(c, j)  # the tetrahedra each projected leaf may be in
        # of two rigid bodies the larger is stopped where it enters the smaller too
        rigid = self.rigid_rows[c] & self.rigid_rows[j]
        back, back_tet = self.tets_near(j[rigid], c[rigid])
        return StepPairs(a, b, c, j, leaf, tet, back, back_tet)

    def stop(self, graph: HeteroData, pos: Tensor, pairs: StepPairs) -> Tensor:
        """One pass of the stops: ``pos`` ``[N, 3]`` with the leaves of ``pairs`` that enter another
        object's solid in the step stopped where they enter (:meth:`entry_clamp`; between two rigid
        bodies only where the leaf ends more than :data:`RIGID_DEPTH` pitches in, or
        :meth:`runs_through` a part of the other)
        and a rigid body sinking deeper than that into another stopped (:meth:`stop_sinking`);
        ``pos`` itself when no leaf moves."""
        leaf, tet = torch.cat([pairs.leaf, pairs.back]), torch.cat([pairs.tet, pairs.back_tet])
        if leaf.numel() == 0:
            return pos
        between = self.rigid_rows[leaf] & self.rigid_rows[self.tets[tet, 0]]
        if not (self.has_rigid and bool(between.any())):
            return self.entry_clamp(graph, pos, leaf, tet)
        rows, push, host = self.solid_pushes(pos, leaf[between], tet[between], self.rotations(pos))
        within = self.within_rigid_depth(rows, push, host)
        ends_in = torch.zeros(pos.size(0), dtype=torch.bool, device=pos.device)
        ends_in[rows] = True
        deep_end = torch.zeros_like(ends_in)
        deep_end[rows[~within]] = True
        # between rigid bodies: a leaf that ends too deep, or outside after a run through a part
        outside = between & ~ends_in[leaf]
        through = torch.zeros_like(outside)
        through[outside] = self.runs_through(graph, pos, leaf[outside], tet[outside])
        keep = ~between | deep_end[leaf] | through
        stopped = self.entry_clamp(graph, pos, leaf[keep], tet[keep])
        if stopped is pos:  # the depths found above still hold
            deep = (rows[~within], push[~within], host[~within])
        else:
            deep = self.beyond_rigid_depth(*self.solid_pushes(stopped, leaf[between], tet[between],
                                                              self.rotations(stopped)))
        return self.stop_sinking(graph, stopped, *deep, leaf[between], tet[between])

    def within_rigid_depth(self, rows: Tensor, push: Tensor, host: Tensor) -> Tensor:
        """``[M]`` bool: which pushes ``push [M, 3]`` of leaves ``rows [M]`` out of objects
        ``host [M]`` are between two rigid bodies and no longer than the clearance plus
        :data:`RIGID_DEPTH` pitches (an overlap left alone)."""
        between = self.rigid_rows[rows] & self.rigid_object[host]
        return between & (push.norm(dim=-1) <= self.clearance[rows] + RIGID_DEPTH * self.pitch[rows])

    def beyond_rigid_depth(self, rows: Tensor, push: Tensor, host: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Of pushes ``(rows, push, host)`` those not :meth:`within_rigid_depth`."""
        keep = ~self.within_rigid_depth(rows, push, host)
        return rows[keep], push[keep], host[keep]

    def stop_sinking(self, graph: HeteroData, pos: Tensor, rows: Tensor, push: Tensor, host: Tensor,
                     leaf: Tensor, tet: Tensor) -> Tensor:
        r"""``pos`` with every rigid body that sinks further into another stopped: its leaf ``rows [M]``
        must be pushed ``push [M, 3]`` out of rigid body ``host [M]`` beyond :data:`RIGID_DEPTH`
        and moves further in (its step less the other body's mean leaf step, along the push). A
        leaf inside another body at :math:`x_t` is left alone by :meth:`entry_clamp`, so a body
        resting on another could otherwise sink into it step by step.

        Such a body keeps the part of its step across the pushes: with :math:`\hat p_i` a sinking
        leaf's push direction, :math:`u_i` its step and :math:`\bar u_h` the other body's mean
        leaf step, the body moves back by the longest of

        .. math::
            \min\bigl(\max(0, -(u_i - \bar u_h) \cdot \hat p_i),\ \max(0, -u_i \cdot \hat p_i)\bigr)\, \hat p_i

        (no further back than :math:`x_t` along it; a body sliding off another goes on sliding),
        if it then lies no deeper in the others (the deepest overlap among the rigid pairs
        ``(leaf, tet)``, ``[P]`` each, along the anchors' normals, :meth:`deepest_rigid`) than
        held at :math:`x_t` or than the clearance plus :data:`RIGID_DEPTH` pitches; else it is
        held at :math:`x_t`. ``pos`` itself when no body sinks."""
        if rows.numel() == 0:
            return pos
        start = graph[NODE].pos
        step = pos - start
        weight = self.rigid_rows.to(pos.dtype)
        total = pos.new_zeros(self.count, 3).index_add(0, self.group, step * weight.unsqueeze(-1))
        mean = total / pos.new_zeros(self.count).index_add(0, self.group, weight).clamp(min=1.0).unsqueeze(-1)
        sinking = ((step[rows] - mean[host]) * push).sum(-1) < 0
        rows, host, out = rows[sinking], host[sinking], torch.nn.functional.normalize(push[sinking], dim=-1)
        body = self.group[rows]
        stopped = torch.zeros(self.count, dtype=torch.bool, device=pos.device).index_fill_(0, body, True)
        moving = stopped[self.group] & self.rigid_rows & (step != 0).any(-1)
        if not bool(moving.any()):
            return pos
        held = leaf_to_ancestor_mean(torch.where(moving.unsqueeze(-1), start, pos), graph)
        inward = -((step[rows] - mean[host]) * out).sum(-1)
        own = -(step[rows] * out).sum(-1)
        back, _ = longest_per(body, torch.minimum(inward, own).clamp(min=0.0).unsqueeze(-1) * out, self.count)
        slid = leaf_to_ancestor_mean(torch.where(moving.unsqueeze(-1), pos + back[self.group], pos), graph)
        involved = stopped[self.group[leaf]] | stopped[self.group[self.tets[tet, 0]]]
        leaf, tet = leaf[involved], tet[involved]  # the pairs that may hold a stopped body's depth
        allowed = pos.new_zeros(self.count).scatter_reduce(
            0, self.group, self.clearance + RIGID_DEPTH * self.pitch, "amax")
        deepest = torch.maximum(self.deepest_rigid(held, leaf, tet), allowed)
        kept = self.deepest_rigid(slid, leaf, tet) <= deepest + 1e-7
        return torch.where((moving & kept[self.group]).unsqueeze(-1), slid, held)

    def deepest_rigid(self, pos: Tensor, leaf: Tensor, tet: Tensor) -> Tensor:
        """``[R]``: per object, the deepest overlap among the pairs ``(leaf, tet)`` (``[P]`` each) at
        ``pos`` ``[N, 3]`` of its leaves in another object or of another's leaves in it, measured
        along the push's normal (0: none)."""
        rows, push, host, normal = self.solid_contacts(pos, leaf, tet, self.rotations(pos))
        depth = (push * normal).sum(-1).clamp(min=0.0)
        return pos.new_zeros(self.count).scatter_reduce(0, torch.cat([self.group[rows], host]),
                                                        torch.cat([depth, depth]), "amax")

    def limit_stretch(self, graph: HeteroData, pos: Tensor, movable: Tensor | None) -> Tensor:
        """``pos`` with no lattice edge of a soft body longer than :data:`STRETCH_LIMIT` times its
        rest length: each such edge's ends move towards each other by the excess (the movable
        end alone if the other is held), shared out over the edges of its busier end, for
        :data:`STRETCH_PASSES` passes. ``pos`` itself when no edge is too long."""
        free = self.cloth & (self.kind == SOFT)
        free = free if movable is None else free & movable
        i, j = self.edges[:, 0], self.edges[:, 1]
        keep = free[i] | free[j]
        i, j = i[keep], j[keep]
        if i.numel() == 0:
            return pos
        longest = STRETCH_LIMIT * (self.rest[j] - self.rest[i]).norm(dim=-1)
        moved = pos
        for _ in range(STRETCH_PASSES):
            arm = moved[j] - moved[i]
            length = arm.norm(dim=-1)
            over = length > longest
            if not bool(over.any()):
                break
            share_i, share_j = free[i].to(pos.dtype), free[j].to(pos.dtype)
            edges_of = torch.zeros(pos.size(0), dtype=pos.dtype, device=pos.device)
            edges_of.index_add_(0, i, over.to(pos.dtype)).index_add_(0, j, over.to(pos.dtype))
            # equal and opposite moves (the centre of mass stays), shared out over a leaf's edges
            relax = torch.maximum(edges_of[i], edges_of[j]).clamp(min=1.0) * (share_i + share_j)
            excess = torch.where(over, (length - longest) / length.clamp(min=1e-12), 0.0)  # a share of the edge
            pull = arm * (excess / relax).unsqueeze(-1)
            moved = moved.index_add(0, i, pull * share_i.unsqueeze(-1)).index_add(0, j, -pull * share_j.unsqueeze(-1))
        return pos if moved is pos else leaf_to_ancestor_mean(moved, graph)

    def give_way(self, graph: HeteroData, pos: Tensor, q: Tensor, tet: Tensor, give: Tensor) -> Tensor:
        """``pos`` with the soft bodies' tetrahedra moved off the leaves of other objects inside
        them (module docstring), for the pairs ``(q, tet)`` (``[P]`` each) of a leaf and a soft
        body's tetrahedron; only the ``give`` ``[N]`` rows move. ``pos`` itself when none is
        inside."""
        if q.numel() == 0:
            return pos
        x = pos.double()
        hit = self.inside_tets(x, x[q], tet)
        q, tet = q[hit], tet[hit]
        if q.numel() == 0:
            return pos
        corners = self.tets[tet]  # [H, 4]
        rotation = self.rotations(pos)
        anchors = self.anchor[corners]  # [H, 4]
        own = self.current_normals(pos, self.anchor[q], rotation).unsqueeze(1)  # [H, 1, 3]
        theirs = -self.current_normals(pos, anchors.clamp(min=0).flatten(), rotation).view(-1, 4, 3)
        direction = torch.cat([own, theirs], dim=1).double()  # [H, 5, 3]: the candidates
        height = torch.einsum("hkc,hdc->hdk", x[corners] - x[q].unsqueeze(1), direction)  # [H, 5, 4]
        amount = (self.clearance[corners].double().unsqueeze(1) - height).clamp(min=0.0)
        usable = torch.cat([torch.ones_like(anchors[:, :1], dtype=torch.bool), anchors >= 0], dim=1)
        cost = torch.where(usable, amount.amax(dim=2), torch.inf)
        best = cost.argmin(dim=1)
        pick = torch.arange(best.numel(), device=best.device)
        normal, amount = direction[pick, best].unsqueeze(1), amount[pick, best]  # [H, 1, 3], [H, 4]
        rows, amount = corners.reshape(-1), amount.reshape(-1)
        push = (amount.view(-1, 4, 1) * normal).reshape(-1, 3)
        ok = give[rows] & (amount > 0)
        rows, push = rows[ok], push[ok]
        if rows.numel() == 0:
            return pos
        shift, longest = longest_per(rows, push, pos.size(0))
        moved = torch.where((longest > 0).unsqueeze(-1), (x + shift).to(pos.dtype), pos)
        return leaf_to_ancestor_mean(moved, graph)

    def tets_near(self, c: Tensor, j: Tensor) -> tuple[Tensor, Tensor]:
        """The distinct pairs ``(leaf, tet)`` of each leaf ``c`` and the tetrahedra of the cells
        its pair ``j`` is a corner of."""
        keep = self.leaf_tets[j, 0] >= 0
        candidates = self.leaf_tets[j[keep]]  # [P, M]
        which, column = torch.nonzero(candidates >= 0, as_tuple=True)
        return unique_pairs(c[keep][which], candidates[which, column], self.tets.size(0))

    def barycentric(self, x: Tensor, point: Tensor, tet: Tensor) -> tuple[Tensor, Tensor]:
        """The barycentric coordinates ``[P, 4]`` of each ``point`` ``[P, 3]`` in its ``tet`` at
        ``x`` ``[N, 3]``, and ``[P]`` bool whether the tetrahedron is not flattened (a flattened one
        holds nothing; its coordinates are not meaningful)."""
        return tet_coordinates(x[self.tets[tet]], point)

    def inside_tets(self, x: Tensor, point: Tensor, tet: Tensor) -> Tensor:
        """``[P]`` bool: whether each ``point`` ``[P, 3]`` lies in its ``tet`` at ``x`` ``[N, 3]``
        (closed). Only the points within a tetrahedron's bounding box (with the slack its
        tolerance allows) are solved for."""
        corners = x[self.tets[tet]]  # [P, 4, 3]
        low, high = corners.amin(dim=1), corners.amax(dim=1)
        slack = 4 * INSIDE_TOLERANCE * (high - low).amax(dim=1, keepdim=True)
        near = ((point >= low - slack) & (point <= high + slack)).all(dim=1)
        inside = torch.zeros_like(near)
        if bool(near.any()):
            bary, usable = tet_coordinates(corners[near], point[near])
            inside[near] = usable & (bary >= -INSIDE_TOLERANCE).all(dim=1)
        return inside

    def crossings(self, graph: HeteroData, pos: Tensor, leaf: Tensor, tet: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        r"""Where each ``leaf``'s step from :math:`x_t` to ``pos`` ``[N, 3]`` is inside its ``tet``
        (pairs ``[P]``): ``(enters, leaves, crossing)``, the fractions :math:`\alpha` of the step
        between which it is inside (``[P]`` each) and ``[P]`` bool whether it is at all. A leaf's
        barycentric coordinates in a tetrahedron are taken from both at :math:`x_t` and both at
        :math:`x_{t+1}` and interpolated linearly in :math:`\alpha` between them (exact when the
        tetrahedron does not move)."""
        x, start = pos.double(), graph[NODE].pos.double()
        before, usable = self.barycentric(start, start[leaf], tet)
        after, usable_after = self.barycentric(x, x[leaf], tet)
        slope = after - before
        bound = (-INSIDE_TOLERANCE - before) / torch.where(slope == 0, torch.ones_like(slope), slope)
        infinity = torch.full_like(bound, torch.inf)
        enters = torch.where(slope > 0, bound, -infinity).amax(dim=1).clamp(min=0.0)
        leaves = torch.where(slope < 0, bound, infinity).amin(dim=1).clamp(max=1.0)
        never = ((slope == 0) & (before < -INSIDE_TOLERANCE)).any(dim=1)
        return enters, leaves, usable & usable_after & ~never & (enters <= leaves)

    def runs_through(self, graph: HeteroData, pos: Tensor, leaf: Tensor, tet: Tensor) -> Tensor:
        r"""``[P]`` bool: whether ``leaf``'s step runs more than :data:`RIGID_RUN` pitches inside
        the object of its ``tet`` (pairs ``[P]``): from the first fraction of the step at which it
        is in one of that object's tetrahedra to the last (:meth:`crossings`), times its step
        relative to theirs: a step through a part of the other, not a cut across its corner.

        .. math:: \ell = \bigl(\max_\tau \beta_\tau - \min_\tau \alpha_\tau\bigr)\,
            \max_\tau \bigl\lVert \Delta x_{\mathrm{leaf}} - \overline{\Delta x}_\tau \bigr\rVert

        over the tetrahedra :math:`\tau` of the object it crosses (a leaf on a face or edge is in
        several at once, so their lengths are not summed)."""
        enters, leaves, crossing = self.crossings(graph, pos, leaf, tet)
        x, start = pos.double(), graph[NODE].pos.double()
        corners = self.tets[tet]
        relative = ((x[leaf] - start[leaf]) - (x[corners] - start[corners]).mean(dim=1)).norm(dim=-1)
        key = leaf * self.count + self.group[corners[:, 0]]
        keys, which = torch.unique(key, return_inverse=True)
        count = keys.numel()
        first = enters.new_full((count,), torch.inf).scatter_reduce(0, which[crossing], enters[crossing], "amin")
        last = enters.new_full((count,), -torch.inf).scatter_reduce(0, which[crossing], leaves[crossing], "amax")
        longest = enters.new_zeros(count).scatter_reduce(0, which[crossing], relative[crossing], "amax")
        run = torch.where(last >= first, (last - first) * longest, torch.zeros_like(longest))
        return run[which] > RIGID_RUN * self.pitch[leaf].double()

    def entry_clamp(self, graph: HeteroData, pos: Tensor, leaf: Tensor, tet: Tensor) -> Tensor:
        r"""``pos`` with each ``leaf`` whose step from :math:`x_t` passes into its ``tet`` (pairs
        ``[P]`` each, :meth:`tets_near`) stopped where it enters (module docstring); leaves already inside at
        :math:`x_t` are left to the pushes. Where it enters is the least :math:`\alpha` of its
        :meth:`crossings`; the leaf moves by that fraction of its step less :data:`ENTRY_MARGIN`."""
        if leaf.numel() == 0:
            return pos
        x, start = pos.double(), graph[NODE].pos.double()
        enters, _, crossing = self.crossings(graph, pos, leaf, tet)
        # a leaf inside an object at x_t is left to the pushes there, and still stopped entering another
        key = leaf * self.count + self.group[self.tets[tet, 0]]
        crossing = crossing & ~torch.isin(key, key[crossing & (enters <= 0)])
        first = x.new_full((pos.size(0),), torch.inf).scatter_reduce(0, leaf[crossing], enters[crossing], "amin")
        ends_in = torch.isfinite(first) & (first > 0)
        if not bool(ends_in.any()):
            return pos
        alpha = torch.where(ends_in, (first - ENTRY_MARGIN).clamp(min=0.0), torch.ones_like(first))
        if self.has_rigid:
            smallest = alpha.new_ones(self.count).scatter_reduce(0, self.group[ends_in & self.rigid_rows],
                                                                 alpha[ends_in & self.rigid_rows], "amin")
            alpha = torch.where(self.rigid_rows, smallest[self.group], alpha)
        clamped = start + alpha.unsqueeze(-1) * (x - start)
        moved = self.leaf & (alpha < 1)
        stopped = torch.where(moved.unsqueeze(-1), clamped.to(pos.dtype), pos)
        if bool((moved & self.rigid_rows).any()):  # a turning body's leaves cut short are fitted rigid again
            stopped = rigid_leaf_positions(graph, stopped, (self.group, self.count))
        return leaf_to_ancestor_mean(stopped, graph)

    def plane_pushes(self, graph: HeteroData, pos: Tensor, c: Tensor, j: Tensor,
                     rotation: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The pushes of the near planes: ``rows [M]`` leaves and ``push [M, 3]`` (m), one per
        leaf behind every plane of an object's surface leaves within reach, and the object ``[M]``
        each is pushed out of."""
        keep = self.surface[j]
        c, j = c[keep], j[keep]
        arm = pos[c] - pos[j]
        distance = arm.norm(dim=-1)
        # a leaf that moved far in the step may be that far in: the reach grows by its step
        reach = self.reach[c] + (pos[c] - graph[NODE].pos[c]).norm(dim=-1)
        near = distance < reach
        c, j, arm, distance = c[near], j[near], arm[near], distance[near]
        empty = (c[:0], pos[:0], c[:0])
        if c.numel() == 0:
            return empty
        normal = self.current_normals(pos, j, rotation)
        height = (arm * normal).sum(-1)  # s_cj
        # one row per (cloth leaf, object) pair: inside when behind every near plane of that object
        pair, slot = torch.unique(c * self.count + self.group[j], return_inverse=True)
        highest = height.new_full((pair.numel(),), -torch.inf).scatter_reduce(0, slot, height, "amax")
        inside = highest[slot] < self.clearance[c]
        nearest = distance.new_full((pair.numel(),), torch.inf).scatter_reduce(0, slot, distance, "amin")
        chosen = torch.nonzero(inside & (distance == nearest[slot])).flatten()
        if chosen.numel() == 0:
            return empty
        # one push per cloth leaf: its first chosen pair (a tie in distance, or a leaf inside two objects)
        first = c.new_full((pos.size(0),), c.numel()).scatter_reduce(0, c[chosen], chosen, "amin")
        picked = first[first < c.numel()]
        push = (self.clearance[c[picked]] - height[picked]).unsqueeze(-1) * normal[picked]
        return c[picked], push, self.group[j[picked]]

    def solid_pushes(self, pos: Tensor, leaf: Tensor, tet: Tensor, rotation: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The pushes out of the solids, for the pairs ``(leaf, tet)`` (``[P]`` each,
        :meth:`tets_near`): ``rows [M]`` and ``push [M, 3]`` (m), one per leaf that lies in its
        tetrahedron, to the clearance beyond the nearest anchor of that tetrahedron's corners, and
        the object ``[M]`` each is pushed out of."""
        rows, push, host, _ = self.solid_contacts(pos, leaf, tet, rotation)
        return rows, push, host

    def solid_contacts(self, pos: Tensor, leaf: Tensor, tet: Tensor,
                       rotation: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """:meth:`solid_pushes` with the normal ``[M, 3]`` each push leaves along (its anchor's)."""
        x = pos.double()
        inside = self.inside_tets(x, x[leaf], tet)
        anchor = self.anchor[self.tets[tet[inside]]]  # [H, 4]
        leaf = leaf[inside].unsqueeze(1).expand_as(anchor)[anchor >= 0]
        anchor = anchor[anchor >= 0]
        if leaf.numel() == 0:
            return leaf, pos[:0], leaf, pos[:0]
        leaf, anchor = unique_pairs(leaf, anchor, pos.size(0))
        gap = (x[anchor] - x[leaf]).norm(dim=-1)
        nearest = gap.new_full((pos.size(0),), torch.inf).scatter_reduce(0, leaf, gap, "amin")
        index = torch.where(gap == nearest[leaf], torch.arange(leaf.numel(), device=leaf.device), leaf.numel())
        first = leaf.new_full((pos.size(0),), leaf.numel()).scatter_reduce(0, leaf, index, "amin")
        picked = first[first < leaf.numel()]
        leaf, anchor = leaf[picked], anchor[picked]
        normal = self.current_normals(pos, anchor, rotation)
        return leaf, pos[anchor] + self.clearance[leaf].unsqueeze(-1) * normal - pos[leaf], self.group[anchor], normal

    def shift_whole(self, graph: HeteroData, pos: Tensor, owner: Tensor, push: Tensor,
                    movable: Tensor | None) -> Tensor:
        """``pos`` with each object of ``owner [M]`` moved whole (its projected, movable leaves)
        by the longest of its ``push [M, 3]``; ``pos`` itself when there is none."""
        if owner.numel() == 0:
            return pos
        rows = self.cloth if movable is None else self.cloth & movable
        moved, shifted = self.moved_whole(pos, owner, push, rows)
        return leaf_to_ancestor_mean(shifted, graph) if bool(moved.any()) else pos

    def moved_whole(self, pos: Tensor, owner: Tensor, push: Tensor, rows: Tensor) -> tuple[Tensor, Tensor]:
        """``([N] bool, [N, 3])``: the ``rows`` of the objects of ``owner [M]`` with a push, and
        ``pos`` with them moved by their object's longest ``push [M, 3]``, at most
        :data:`SHIFT_LIMIT` pitches (ancestors not re-derived)."""
        shift, longest = longest_per(owner, push, self.count)
        moved = rows & (longest > 0)[self.group]
        shift = shortened(shift[self.group], SHIFT_LIMIT * self.pitch)
        return moved, torch.where(moved.unsqueeze(-1), pos + shift, pos)

    def apply(self, graph: HeteroData, pos: Tensor, leaf_rows: Tensor, push: Tensor) -> Tensor:
        """``pos`` with each of ``leaf_rows`` moved by its ``push`` (a rigid object's leaves: the
        whole object by their longest push) and the ancestors re-derived; ``pos`` itself when
        there is no push."""
        if leaf_rows.numel() == 0:
            return pos
        whole = self.rigid[leaf_rows]
        if bool(whole.any()):  # a rigid object moves as a whole, by its leaves' longest push
            _, pos = self.moved_whole(pos, self.group[leaf_rows[whole]], push[whole], self.rigid_rows)
            leaf_rows, push = leaf_rows[~whole], push[~whole]
        return leaf_to_ancestor_mean(pos.index_add(0, leaf_rows, push), graph)

    def __call__(self, graph: HeteroData, prediction: Prediction, movable: Tensor | None = None) -> Prediction:
        """A step's :class:`~hrn_pyg.sim.step.Prediction` after :meth:`project`. A step shortened
        by the stretch limit or stopped where it enters is a motion: the node's velocity is its
        shorter move from :math:`x_t` (the prediction's ``prev_pos`` when the ground lift moved
        it). A push out, the giving way and the last stretch limit are corrections of place: the
        node keeps its velocity and its :math:`x_t` moves with it (the returned ``prev_pos``), so
        moving a body out of another gives it no speed. The local velocities of an object that
        moved are derived anew. The same prediction when nothing moves."""
        pos, local, velocity, prev_pos = prediction
        stopped, projected = self.stop_and_push(graph, pos, movable)
        if projected is pos:
            return prediction
        since = graph[NODE].pos if prev_pos is None else prev_pos
        moved = (projected != pos).any(-1)
        touched = torch.zeros(self.count, dtype=torch.bool, device=pos.device).index_fill_(
            0, self.group[moved], True)[self.group]
        if stopped is not pos:
            velocity = torch.where((stopped != pos).any(-1, keepdim=True), stopped - since, velocity)
        if projected is not stopped:
            pushed = (projected != stopped).any(-1, keepdim=True)
            # the leaves' x_t moved by their push, the ancestors' derived from them
            moved_since = leaf_to_ancestor_mean(torch.where(pushed, projected - velocity, since), graph)
            prev_pos = torch.where(touched.unsqueeze(-1), moved_since, since)
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
    meshes = []
    for obj in np.unique(groups[has_solid]):
        rows = np.flatnonzero((groups == obj) & has_solid)
        found = surface_normals(points[rows], float(pitches[rows[0]]))
        normal[torch.from_numpy(rows).to(rest.device)] = torch.from_numpy(found).to(rest)
        meshes.append((rows, solid_mesh(points[rows], found, float(pitches[rows[0]]))))
    solids = scene_solid_mesh(meshes, len(points))
    surface = solid_leaf & (normal.norm(dim=-1) > 0)
    if not bool(surface.any()):
        return None
    static = store.is_static | (material == STATIC)
    gap = torch.where(material == CLOTH, torch.full_like(pitch, clearance), torch.full_like(pitch, solid_clearance))
    return ClothContact(rest=rest, normal=normal, surface=surface, cloth=projected, static=static, leaf=leaf,
                        rigid=projected & rigid_rows, rigid_rows=rigid_rows,
                        rigid_object=torch.zeros(count, dtype=torch.bool, device=group.device).index_fill_(
                            0, group[rigid_rows], True),
                        has_rigid=bool(rigid_rows.any()), kind=material,
                        size=torch.zeros(count, dtype=torch.long, device=group.device).index_add(
                            0, group, leaf.long()), group=group, count=count,
                        reach=reach * pitch, clearance=gap * pitch, pitch=pitch,
                        **{name: torch.from_numpy(value).to(group.device)
                           for name, value in dataclasses.asdict(solids).items()})
