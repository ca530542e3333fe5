r"""Could this future happen? A physics report of a rollout or of K sampled futures.

Mean errors and spreads say how close a future is to pybullet's; this report says whether it is
possible at all. Per future (trajectories of leaf positions from a known start):

* **Energy.** :math:`E_t = \sum_i m_i (g z_i + \tfrac12 \lVert x_i(t) - x_i(t-1) \rVert^2 / \Delta t^2)`
  over the moving leaves; the largest rise over the start beyond the work the scene's pushes did
  up to that step, :math:`\max_t (E_t - E_0 - W_{0..t})`, in joules and as a share of
  :math:`E_0` (the potential energy is counted from the ground plane, so :math:`E_0 > 0` for
  anything above it). A scene of passive bodies has no source of energy: any rise is an error.
* **Interpenetration.** A leaf of one object inside another object's solid (the lattice cells
  whose corners are all that object's leaves, cut into tetrahedra: the solid that
  :mod:`hrn_pyg.sim.penetration` counts cloth leaves in, here for the leaves of every object), and
  how deep: its distance to the nearest surface leaf of the object it is in, the largest over
  leaves and checked frames.
* **Unsupported at rest.** At the last frame, objects that have stopped (every leaf moved less
  than :data:`REST_SPEED` pitches in the last step) with no leaf within
  :data:`SUPPORT_REACH` pitches of the ground or of another object: a body hanging in the air.
* **Non-finite.** The first step whose positions hold NaN or inf (a blow-up), if any.

pybullet's own episode through the same report is the reference row: its interpenetration is
the floor a model is held to (plus a pitch).

**Shapes.** :func:`plausibility` takes futures ``(K, T, L, 3)`` (``x_1 .. x_T``), the start
``(2, L, 3)`` (``x_{-1}, x_0``), and gives K :class:`FutureReport` rows.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.data.graph import HISTORY, NODE, graph_pitch
from hrn_pyg.data.io import episode_pitch
from hrn_pyg.data.kinds import CLOTH, GRAVITY, STATIC
from hrn_pyg.sim.energy import STEP_SECONDS, scene_energy, step_seconds
from hrn_pyg.sim.cloth_contact import NEIGHBOURHOOD
from hrn_pyg.sim.penetration import INSIDE_TOLERANCE, object_solids

#: an object has stopped when no leaf moved more than this many pitches in the last step
REST_SPEED = 0.05
#: an object is supported when a leaf is within this many pitches of the ground or another object
SUPPORT_REACH = 1.5
#: a rise of energy above this share of the start counts as a gain (the issue's bar: 5 %)
ENERGY_TOLERANCE = 0.05
#: interpenetration is checked every this many frames (and at the last one)
DEPTH_STRIDE = 5


@dataclass(frozen=True)
class FutureReport:
    """One future's plausibility (module docstring).

    Attributes:
        energy_rise: largest :math:`E_t - E_0 - W_{0..t}` (J); <= 0 when energy never rose.
        energy_share: ``energy_rise`` over :math:`E_0`.
        depth: deepest interpenetration (m): a leaf's distance into another object's solid.
        leaves_inside: the most leaves inside another object's solid at one checked frame.
        unsupported: objects at rest with nothing under them at the last frame.
        first_non_finite: the first step (1-based) whose positions are not finite; 0: none.
    """

    energy_rise: float
    energy_share: float
    depth: float
    leaves_inside: int
    unsupported: int
    first_non_finite: int

    @property
    def gains_energy(self) -> bool:
        return self.energy_share > ENERGY_TOLERANCE

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Scene:
    """What the report needs of a scene: ``leaf_mass`` ``(L,)`` kg, ``leaf_object`` ``(L,)``,
    ``object_material`` ``(O,)`` (codes of :data:`hrn_pyg.data.kinds.MATERIALS`), ``rest``
    ``(L, 3)`` the rest positions (each object's lattice), ``pitch`` (m), ``dt`` (s)."""

    leaf_mass: Tensor
    leaf_object: Tensor
    object_material: Tensor
    rest: Tensor
    pitch: float
    dt: float = STEP_SECONDS

    def __post_init__(self) -> None:
        leaves = self.rest.shape[0]
        if self.rest.dim() != 2 or self.rest.shape[1] != 3 or leaves == 0:
            raise ValueError(f"rest must be [L, 3] with L >= 1, got {tuple(self.rest.shape)}")
        for name in ("leaf_mass", "leaf_object"):
            if tuple(getattr(self, name).shape) != (leaves,):
                raise ValueError(f"{name} must be [{leaves}], got {tuple(getattr(self, name).shape)}")
        if not (math.isfinite(self.pitch) and self.pitch > 0 and math.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"pitch and dt must be finite and > 0, got {self.pitch}, {self.dt}")

    @classmethod
    def of_episode(cls, episode: dict) -> Scene:
        """The scene of an episode of ``hrn-pyg generate`` (rest: its first frame)."""
        pitch = episode_pitch(episode)
        if pitch is None:
            raise ValueError("the episode records no pitch")
        return cls(torch.as_tensor(np.asarray(episode["leaf_mass"]), dtype=torch.float64),
                   torch.as_tensor(np.asarray(episode["leaf_object"]), dtype=torch.long),
                   torch.as_tensor(np.asarray(episode["object_material"]), dtype=torch.long),
                   torch.as_tensor(np.asarray(episode["positions"][0]), dtype=torch.float64),
                   float(pitch), float(episode["dt"]))

    @classmethod
    def of_graph(cls, graph: HeteroData) -> Scene:
        """The scene of a model's one-scene graph (rest: its ``rest_pos``, else its ``pos``;
        pitch: the graph's, which it must record; dt: the graph's ``dt``, else the default)."""
        store = graph[NODE]
        pitch = graph_pitch(graph)
        if pitch is None:
            raise ValueError("the graph records no pitch (hrn_pyg.data.graph.set_pitch)")
        leaf = store.is_leaf
        leaf_object = store.object[leaf].long()
        count = int(leaf_object.max()) + 1
        material = store.material[leaf].argmax(dim=1)
        object_material = torch.zeros(count, dtype=torch.long).scatter_(0, leaf_object.cpu(), material.cpu())
        rest = (store.rest_pos if "rest_pos" in store else store.pos)[leaf]
        dt = float(step_seconds(graph)[0])
        return cls(store.mass[leaf, 0].double().cpu(), leaf_object.cpu(), object_material,
                   rest.detach().double().cpu(), float(pitch.reshape(-1)[0]), dt)

    @property
    def moving_mass(self) -> Tensor:
        """``(L,)`` the leaf masses, 0 on static objects."""
        return torch.where(self.object_material[self.leaf_object] == STATIC, 0.0, self.leaf_mass.double())


class Solids:
    """Every solid object's tetrahedra (:func:`~hrn_pyg.sim.penetration.object_solids`: its
    lattice cells cut six ways) and its surface leaves, found once from the rest positions:
    ``tets`` ``(K, 4)`` leaf indices, ``owner`` ``(K,)`` the object of each, ``surface`` ``(L,)``
    bool, the leaves with fewer than 26 lattice neighbours (every leaf of a part one leaf thick,
    which the surface normals of :mod:`hrn_pyg.sim.cloth_contact` leave out)."""

    def __init__(self, scene: Scene) -> None:
        solids = object_solids(scene.rest, scene.leaf_object, scene.object_material, scene.pitch)
        points = scene.rest.detach().double().cpu().numpy()
        objects = scene.leaf_object.cpu().numpy()
        surface = np.ones(len(points), dtype=bool)  # cloth leaves: all surface
        for obj, kind in enumerate(scene.object_material.cpu().numpy()):
            members = np.flatnonzero(objects == obj)
            if kind == CLOTH or len(members) == 0:
                continue
            near = cKDTree(points[members]).query_ball_point(points[members], NEIGHBOURHOOD * scene.pitch)
            surface[members] = np.array([len(n) - 1 for n in near]) < 26
        self.tets, self.owner = solids.tets.numpy(), solids.tet_object.numpy()
        self.surface = surface
        self.leaf_object = objects

    def depth(self, x: np.ndarray, pitch: float) -> tuple[float, int]:
        """Of one frame ``x`` ``(L, 3)``: the deepest leaf inside another object's solid (m) and
        how many leaves are inside one."""
        if len(self.tets) == 0:
            return 0.0, 0
        corners = x[self.tets]  # [K, 4, 3]
        centre = corners.mean(axis=1)
        reach = np.linalg.norm(corners - centre[:, None], axis=2).max(axis=1)  # [K]
        tree = cKDTree(centre)
        candidates = tree.query_ball_point(x, float(reach.max()) * (1 + 1e-9))
        leaf = np.repeat(np.arange(len(x)), [len(c) for c in candidates])
        tet = np.fromiter((t for c in candidates for t in c), dtype=np.int64, count=len(leaf))
        other = self.owner[tet] != self.leaf_object[leaf]
        leaf, tet = leaf[other], tet[other]
        if len(leaf) == 0:
            return 0.0, 0
        edges = corners[tet, 1:] - corners[tet, :1]  # [P, 3, 3]
        det = np.linalg.det(edges)
        usable = np.abs(det) > 1e-12 * np.prod(np.linalg.norm(edges, axis=2), axis=1)
        leaf, tet, edges = leaf[usable], tet[usable], edges[usable]
        if len(leaf) == 0:
            return 0.0, 0
        b = np.linalg.solve(np.transpose(edges, (0, 2, 1)), (x[leaf] - corners[tet, 0])[..., None])[..., 0]
        bary = np.concatenate([1.0 - b.sum(axis=1, keepdims=True), b], axis=1)
        hit = (bary >= -INSIDE_TOLERANCE).all(axis=1)
        leaf, owner = leaf[hit], self.owner[tet[hit]]
        if len(leaf) == 0:
            return 0.0, 0
        deepest = 0.0
        for obj in np.unique(owner):
            inside = np.unique(leaf[owner == obj])
            skin = np.flatnonzero((self.leaf_object == obj) & self.surface)
            distance, _ = cKDTree(x[skin]).query(x[inside])
            deepest = max(deepest, float(distance.max()))
        return deepest, int(len(np.unique(leaf)))


def energy_rise(futures: Tensor, start: Tensor, scene: Scene, forces: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """``(K,)`` the largest :math:`E_t - E_0 - W_{0..t}` (J) of each future and ``(K,)`` :math:`E_0`.

    ``futures`` ``(K, T, L, 3)``, ``start`` ``(2, L, 3)``; ``forces`` ``(T, L, 3)`` N (the
    external force of each step on each leaf; None: no pushes). Non-finite steps are skipped."""
    k, steps = futures.shape[:2]
    x = torch.cat([start.double().expand(k, 2, *start.shape[1:]), futures.double()], dim=1)  # [K, T+2, L, 3]
    energy = scene_energy(x, scene.moving_mass, scene.dt, GRAVITY)  # [K, T+1]: E_0 .. E_T
    if forces is None:
        work = torch.zeros(k, steps, dtype=torch.float64)
    else:
        moves = x[:, 2:] - x[:, 1:-1]  # [K, T, L, 3]
        per_step = (forces[:steps].double() * moves * (scene.moving_mass > 0)[:, None]).sum(dim=(-1, -2))
        work = per_step.cumsum(dim=1)  # [K, T]: work up to each step
    rise = energy[:, 1:] - energy[:, :1] - work
    rise = torch.where(torch.isfinite(rise), rise, torch.full_like(rise, -math.inf))
    return rise.amax(dim=1).clamp_min(0.0), energy[:, 0]


def unsupported_at_rest(last: np.ndarray, before: np.ndarray, scene: Scene) -> int:
    """Objects (not static) that stopped between ``before`` and ``last`` ``(L, 3)`` with no leaf
    within :data:`SUPPORT_REACH` pitches of the ground or of another object."""
    objects = scene.leaf_object.cpu().numpy()
    material = scene.object_material.cpu().numpy()
    reach = SUPPORT_REACH * scene.pitch
    tree = cKDTree(last)
    count = 0
    for obj, kind in enumerate(material):
        members = np.flatnonzero(objects == obj)
        if kind == STATIC or len(members) == 0:
            continue
        if np.linalg.norm(last[members] - before[members], axis=1).max() > REST_SPEED * scene.pitch:
            continue  # still moving
        if last[members, 2].min() <= reach:
            continue  # on the ground
        near = tree.query_ball_point(last[members], reach)
        if any(objects[j] != obj for n in near for j in n):
            continue  # on another object
        count += 1
    return count


def plausibility(futures: Tensor, start: Tensor, scene: Scene, forces: Tensor | None = None,
                 stride: int = DEPTH_STRIDE) -> list[FutureReport]:
    """A :class:`FutureReport` for each of the futures ``(K, T, L, 3)`` (or one rollout
    ``(T, L, 3)``) from ``start`` ``(2, L, 3)`` (:math:`x_{-1}, x_0`); ``forces`` ``(T, L, 3)`` N
    or None. Interpenetration is checked every ``stride`` frames and at the last."""
    if futures.dim() == 3:
        futures = futures.unsqueeze(0)
    leaves = scene.rest.shape[0]
    if futures.dim() != 4 or futures.shape[-2:] != (leaves, 3) or futures.shape[1] < 1:
        raise ValueError(f"futures must be [K, T>=1, {leaves}, 3], got {tuple(futures.shape)}")
    if tuple(start.shape) != (2, leaves, 3):
        raise ValueError(f"start must be [2, {leaves}, 3] (x_(-1), x_0), got {tuple(start.shape)}")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    futures = futures.detach().cpu()
    rise, e0 = energy_rise(futures, start.detach().cpu(), scene, None if forces is None else forces.detach().cpu())
    solids = Solids(scene)
    steps = futures.shape[1]
    frames = sorted(set(range(stride - 1, steps, stride)) | {steps - 1})
    reports = []
    for b, future in enumerate(futures.double().numpy()):
        finite = np.isfinite(future).all(axis=(1, 2))
        first_bad = int(np.argmin(finite)) + 1 if not finite.all() else 0
        usable = [t for t in frames if finite[t]]
        depth, inside = 0.0, 0
        for t in usable:
            d, n = solids.depth(future[t], scene.pitch)
            depth, inside = max(depth, d), max(inside, n)
        last_good = (first_bad - 2) if first_bad else steps - 1
        unsupported = 0
        if last_good >= 1:
            unsupported = unsupported_at_rest(future[last_good], future[last_good - 1], scene)
        share = float(rise[b] / e0[b]) if float(e0[b]) > 0 else (math.inf if float(rise[b]) > 0 else 0.0)
        reports.append(FutureReport(float(rise[b]), share, depth, inside, unsupported, first_bad))
    return reports


def state_plausibility(state: HeteroData, futures: Tensor,
                       forces: Tensor | None = None) -> tuple[list[FutureReport], FutureReport, Scene]:
    """The reports of ``futures`` ``(K, T, L, 3)`` from a start state that carries its ground truth
    (``pos_seq``, as :func:`~hrn_pyg.sampling.ensemble.episode_state` makes it), that truth's own
    report over the same ``T`` steps (pybullet's row) and the scene; ``forces`` ``(T', N, 3)``
    (N, on every node; ``T' >= T``) or None."""
    store = state[NODE]
    leaf = store.is_leaf
    scene = Scene.of_graph(state)
    steps = futures.shape[1]
    seq = store.pos_seq[leaf].transpose(0, 1).detach().double().cpu()  # x_{-2} .. x_end
    history = seq[HISTORY - 1:HISTORY + 1]
    leaf_forces = None if forces is None else forces[:steps][:, leaf].detach().double().cpu()
    reference = plausibility(seq[HISTORY + 1:HISTORY + 1 + steps], history, scene, leaf_forces)[0]
    return plausibility(futures.double(), history, scene, leaf_forces), reference, scene


def is_implausible(report: FutureReport, reference: FutureReport, pitch: float) -> bool:
    """A blow-up, more than :data:`ENERGY_TOLERANCE` of the energy gained, or deeper into another
    body than ``reference`` (pybullet's row) plus one ``pitch``."""
    return report.first_non_finite > 0 or report.gains_energy or report.depth > reference.depth + pitch


def summary_line(reports: Sequence[FutureReport], pitch: float, reference: FutureReport | None = None) -> str:
    """One line of a set of reports: how many futures blew up, gained more than
    :data:`ENERGY_TOLERANCE` of their energy, the largest gain, the deepest interpenetration
    (beside pybullet's, ``reference``) and the objects left unsupported at rest."""
    k = len(reports)
    blown = sum(r.first_non_finite > 0 for r in reports)
    gaining = sum(r.gains_energy for r in reports)
    largest = max((r.energy_share for r in reports), default=0.0)
    depth = max((r.depth for r in reports), default=0.0)
    floating = sum(r.unsupported for r in reports)
    line = (f"plausibility of {k} future{'s' if k != 1 else ''}: {blown} blew up, {gaining} gained more than "
            f"{ENERGY_TOLERANCE:.0%} energy (largest {largest:+.1%}), deepest interpenetration "
            f"{depth * 100:.1f} cm = {depth / pitch:.2f} pitch")
    if reference is not None:
        line += f" (pybullet {reference.depth * 100:.1f} cm)"
    return line + f", {floating} object{'s' if floating != 1 else ''} unsupported at rest"
