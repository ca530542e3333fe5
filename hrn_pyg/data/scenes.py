r"""Ground-truth physics: a pybullet world stepped one model step at a time.

:class:`Scene` is the mechanics every scene shares: the ground, gravity, rigid, soft and cloth
bodies, pushes, and the leaves read back each step. What a scene holds is data: a scene file
(:mod:`hrn_pyg.data.scene_file`), whose :class:`~hrn_pyg.data.scene_file.FileScene` builds the
bodies. Every scene runs headless in its own client, seeded by one ``numpy.random.Generator``.

Leaves (the particles the model sees), per material:

* **rigid / static**: the filled voxel centres of the body's mesh
  (:func:`hrn_pyg.data.voxelise.voxelise`), carried by its pose :math:`x_i = R(q)\,\ell_i + p`;
* **soft**: the same voxel centres as the nodes of a tetrahedral Neo-Hookean body (``.vtk``,
  node order kept by pybullet);
* **cloth**: a one-layer lattice as a mass-spring soft body; leaves = its nodes.

The ground is a static box with top face ``z = 0`` (``GEOM_PLANE`` does not collide properly
with deformable bodies); it is not an object. A model step is ``substeps`` physics steps of
``1 / physics_hz`` s with constant actions; the episode records each leaf's force: a rigid body's
force over its leaf count, or, for soft bodies and cloth (pushed by a velocity change of all
nodes), :math:`f_i = m_i\,\Delta v_i / \Delta t`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import tempfile
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from hrn_pyg.data.kinds import CLOTH, GRAVITY, PHYSICS_HZ, RIGID, SOFT, STATIC, SUBSTEPS, SceneEffects
from hrn_pyg.data.voxelise import (
    write_obj,
    write_tetrahedral_vtk,
)
from hrn_pyg.utils.files import import_pybullet, quiet_stdout

p = import_pybullet()

#: Nominal density (kg/m^3) giving a static body's leaves a mass: they never move, but the
#: hierarchy and the model's mass feature need a positive value.
STATIC_DENSITY = 1000.0
#: Half thickness of the ground box (m); its top face is z = 0. Thick so nothing tunnels.
GROUND_HALF_THICKNESS = 0.5
#: Half side of the ground box (m): far beyond anything a scene can reach in an episode.
GROUND_HALF_SIDE = 10.0
#: Contact margin of soft bodies (m). Smaller lets nodes sink into the ground, larger leaves a
#: visible gap; 6 mm rests a soft cube ~6 mm above z = 0.
SOFT_COLLISION_MARGIN = 0.006
#: Neo-Hookean lambda / mu ratio (a Poisson ratio of ~0.33, compressible rubber-like).
NEO_HOOKEAN_LAMBDA_OVER_MU = 2.0
#: Soft-body damping; pybullet's examples use 0.01-0.1, lower rings, higher looks like honey.
NEO_HOOKEAN_DAMPING = 0.02
#: Stiffness in [0, 1] of a soft body is log10(mu) mapped linearly from this range (Pa-like
#: pybullet units); fixed, so the feature means the same in every scene and dataset.
SOFT_LOG10_MU_RANGE = (2.0, 4.0)
#: Same for cloth: log10 of the spring elastic stiffness.
CLOTH_LOG10_K_RANGE = (0.0, 3.0)


# ---------------------------------------------------------------------------------------------
# the settings every scene has
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SceneConfig:
    """Settings every scene has (a scene file's top level): ``steps`` per episode, ``substeps`` per
    model step, ``physics_hz``, leaf ``pitch`` (m), ``friction`` of every body and the ground, the
    ground's ``rolling_friction`` (> 0: a rolling ball comes to rest). ``*_range``: ``(low, high)``."""

    steps: int = 150
    substeps: int = SUBSTEPS
    physics_hz: float = PHYSICS_HZ
    pitch: float = 0.05
    friction: float = 0.5
    rolling_friction: float = 0.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name.endswith("_range"):
                lo, hi = value
                if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
                    raise ValueError(f"{f.name}: need finite low <= high, got {value}")
                if f.name in self.nonnegative_ranges and lo < 0:
                    raise ValueError(f"{f.name}: must be >= 0, got {value}")
            elif isinstance(value, (int, float)) and not isinstance(value, bool):
                if not math.isfinite(value):
                    raise ValueError(f"{f.name}: must be finite, got {value}")
        for name in ("steps", "substeps"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name}: must be an integer >= 1, got {value}")
        for name in ("physics_hz", "pitch"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name}: must be > 0, got {getattr(self, name)}")
        for name in ("friction", "rolling_friction"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name}: must be >= 0, got {getattr(self, name)}")

    #: ``*_range`` fields whose values must be >= 0 (masses, sizes, speeds, stiffnesses ...).
    nonnegative_ranges: ClassVar[tuple[str, ...]] = ()

    @property
    def dt(self) -> float:
        """Seconds per model step."""
        return self.substeps / self.physics_hz


# ---------------------------------------------------------------------------------------------
# pybullet helpers
# ---------------------------------------------------------------------------------------------


def _rotation_matrices(quaternions: np.ndarray) -> np.ndarray:
    """Rotation matrices of pybullet quaternions ``(x, y, z, w)``. ``[B, 4] -> [B, 3, 3]``."""
    x, y, z, w = np.moveaxis(np.asarray(quaternions, dtype=np.float64), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def _log_stiffness(log10_value: float, log10_range: tuple[float, float]) -> float:
    lo, hi = log10_range
    return float(np.clip((log10_value - lo) / (hi - lo), 0.0, 1.0))


@dataclass
class SceneObject:
    """One simulated object: its pybullet body and its leaves."""

    material: int
    body: int
    mass: float
    stiffness: float
    local_leaves: np.ndarray  # [n, 3] body-frame leaves (rigid/static) or rest nodes (soft/cloth)
    velocity: np.ndarray | None = None  # [n, 3] node velocities (soft/cloth), m/s


# ---------------------------------------------------------------------------------------------
# scenes
# ---------------------------------------------------------------------------------------------


class Scene:
    r"""A seeded pybullet scene stepped one model step at a time.

    ``scene = make_scene(name_or_spec, seed)`` (:func:`hrn_pyg.data.scene_file.make_scene`);
    ``x0 = scene.reset()`` (the same world each time); ``x = scene.step(action_forces)``;
    ``scene.close()``.

    **Shapes**
    - ``reset()``, ``step()`` return leaf positions ``[L, 3]`` float64.
    - ``action_forces``: ``[O, 3]`` force (N) on each object during the step (rigid: every substep;
      soft / cloth: :math:`\Delta v = F \Delta t / M` of all nodes at the start; static: 0).
    - ``last_forces``: ``[L, 3]`` the per-leaf force of the last step (what the episode records).
    - ``leaf_mass [L]``, ``leaf_object [L]``, ``object_material [O]``, ``object_stiffness [O]``.
    """

    name: ClassVar[str]
    config_cls: ClassVar[type[SceneConfig]]
    #: objects an agent may push (indices); scripted scenes push whatever their script says.
    actuated: ClassVar[tuple[int, ...]] = ()
    #: the effects a model of this scene has to simulate (:mod:`hrn_pyg.data.effects`); None in a
    #: field: the data decide
    effects: ClassVar[SceneEffects] = SceneEffects()

    def __init__(self, seed: int, config: SceneConfig | None = None) -> None:
        config = self.config_cls() if config is None else config
        if type(config) is not self.config_cls:
            raise ValueError(
                f"config: scene {self.name!r} needs {self.config_cls.__name__}, got {type(config).__name__}")
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed: must be an integer >= 0, got {seed}")
        self.seed = int(seed)
        self.config = config
        self.rng = np.random.default_rng(self.seed)
        self.params: dict = self.draw_params(self.rng)
        self._client: int | None = None
        self._objects: list[SceneObject] = []
        self._tmpdir: tempfile.TemporaryDirectory | None = None
        self.last_forces: np.ndarray | None = None
        self.t = 0

    # -- subclass interface -------------------------------------------------------------------
    def draw_params(self, rng: np.random.Generator) -> dict:
        """Draw this episode's parameters (JSON-able dict)."""
        raise NotImplementedError

    def build(self) -> None:
        """Create the bodies (after ground and gravity exist)."""
        raise NotImplementedError

    def scripted_action(self, t: int) -> tuple[np.ndarray, np.ndarray | None]:
        """The episode's own action at step ``t``: forces ``[O, 3]`` and spins ``[O, 3] | None``."""
        return self.zero_action(), None

    uses_deformables: ClassVar[bool] = False

    # -- public API ---------------------------------------------------------------------------
    @property
    def dt(self) -> float:
        return self.config.dt

    @property
    def num_objects(self) -> int:
        return len(self._objects)

    def zero_action(self) -> np.ndarray:
        return np.zeros((self.num_objects, 3))

    def reset(self) -> np.ndarray:
        """(Re)build the world with this episode's parameters; return leaf positions ``[L, 3]``."""
        self.close()
        self._tmpdir = tempfile.TemporaryDirectory(prefix="hrn_pyg_scene_")
        self._client = p.connect(p.DIRECT)
        c = self._client
        if self.uses_deformables:
            p.resetSimulation(p.RESET_USE_DEFORMABLE_WORLD, physicsClientId=c)
        else:
            p.resetSimulation(physicsClientId=c)
        p.setGravity(0, 0, -GRAVITY, physicsClientId=c)
        p.setTimeStep(1.0 / self.config.physics_hz, physicsClientId=c)
        shape = p.createCollisionShape(
            p.GEOM_BOX, halfExtents=[GROUND_HALF_SIDE, GROUND_HALF_SIDE, GROUND_HALF_THICKNESS],
            physicsClientId=c)
        ground = p.createMultiBody(0, shape, basePosition=[0, 0, -GROUND_HALF_THICKNESS],
                                   physicsClientId=c)
        p.changeDynamics(ground, -1, lateralFriction=self.config.friction,
                         rollingFriction=self.config.rolling_friction,
                         spinningFriction=self.config.rolling_friction, physicsClientId=c)
        self._objects = []
        self.build()
        self.t = 0
        self.last_forces = None
        return self.leaf_positions()

    def close(self) -> None:
        """Disconnect the pybullet client and remove temporary mesh files."""
        if self._client is not None:
            with contextlib.suppress(p.error):
                p.disconnect(physicsClientId=self._client)
            self._client = None
        if self._tmpdir is not None:
            self._tmpdir.cleanup()
            self._tmpdir = None

    def __enter__(self) -> Scene:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()

    @property
    def leaf_object(self) -> np.ndarray:
        return np.concatenate([np.full(len(o.local_leaves), i, dtype=np.int64)
                               for i, o in enumerate(self._objects)])

    @property
    def leaf_mass(self) -> np.ndarray:
        """Object mass shared equally by its leaves (pybullet spreads soft mass evenly too)."""
        return np.concatenate([np.full(len(o.local_leaves), o.mass / len(o.local_leaves))
                               for o in self._objects]).astype(np.float32)

    @property
    def object_material(self) -> np.ndarray:
        return np.array([o.material for o in self._objects], dtype=np.int64)

    @property
    def object_stiffness(self) -> np.ndarray:
        return np.array([o.stiffness for o in self._objects], dtype=np.float32)

    def leaf_positions(self) -> np.ndarray:
        """Current leaf positions ``[L, 3]`` (float64)."""
        self._require_started()
        return np.concatenate([self._object_positions(o) for o in self._objects])

    def step(self, action_forces: np.ndarray | None = None,
             action_spins: np.ndarray | None = None) -> np.ndarray:
        """Advance one model step under ``action_forces [O, 3]`` (N) and, for soft / cloth,
        ``action_spins [O, 3]`` (rad/s about the centre of mass); return leaves ``[L, 3]``."""
        self._require_started()
        c, n_obj = self._client, self.num_objects
        forces = self.zero_action() if action_forces is None else np.asarray(action_forces, float)
        if forces.shape != (n_obj, 3) or not np.all(np.isfinite(forces)):
            raise ValueError(f"action_forces: expected finite [{n_obj}, 3], got {forces.shape}")
        spins = np.zeros((n_obj, 3)) if action_spins is None else np.asarray(action_spins, float)
        if spins.shape != (n_obj, 3) or not np.all(np.isfinite(spins)):
            raise ValueError(f"action_spins: expected finite [{n_obj}, 3], got {spins.shape}")
        dt = self.dt
        leaf_forces = []
        for i, obj in enumerate(self._objects):  # loop over a handful of objects, not particles
            n = len(obj.local_leaves)
            if obj.material == STATIC:
                if np.any(forces[i] != 0) or np.any(spins[i] != 0):
                    raise ValueError(f"action_forces: object {i} is static and cannot be pushed")
                leaf_forces.append(np.zeros((n, 3)))
            elif obj.material == RIGID:
                if np.any(spins[i] != 0):
                    raise ValueError(f"action_spins: object {i} is rigid; spins are for soft bodies")
                leaf_forces.append(np.broadcast_to(forces[i] / n, (n, 3)))
            else:
                leaf_forces.append(self._kick_deformable(obj, forces[i] * dt / obj.mass, spins[i]))
        self.last_forces = np.concatenate(leaf_forces)
        soft = [o for o in self._objects if o.material in (SOFT, CLOTH)]
        for k in range(self.config.substeps):
            for i, obj in enumerate(self._objects):
                if obj.material == RIGID and np.any(forces[i] != 0):
                    pos, _ = p.getBasePositionAndOrientation(obj.body, physicsClientId=c)
                    p.applyExternalForce(obj.body, -1, forces[i].tolist(), pos, p.WORLD_FRAME,
                                         physicsClientId=c)
            if k == self.config.substeps - 1:
                before = [self._object_positions(o) for o in soft]
            p.stepSimulation(physicsClientId=c)
        for o, x0 in zip(soft, before if soft else []):
            o.velocity = (self._object_positions(o) - x0) * self.config.physics_hz
        self.t += 1
        return self.leaf_positions()

    def nudge(self, offsets: np.ndarray, velocities: np.ndarray | None = None) -> np.ndarray:
        """Translate each object by ``offsets [O, 3]`` (m) and add ``velocities [O, 3]`` (m/s) at once, to
        perturb a start state; return the leaves ``[L, 3]``. Static objects' rows must be zero."""
        self._require_started()
        c, n_obj = self._client, self.num_objects
        offsets = np.asarray(offsets, float)
        velocities = np.zeros((n_obj, 3)) if velocities is None else np.asarray(velocities, float)
        for name, value in (("offsets", offsets), ("velocities", velocities)):
            if value.shape != (n_obj, 3) or not np.all(np.isfinite(value)):
                raise ValueError(f"{name}: expected finite [{n_obj}, 3], got {value.shape}")
        for i, obj in enumerate(self._objects):  # loop over a handful of objects, not particles
            if obj.material == STATIC:
                if np.any(offsets[i] != 0) or np.any(velocities[i] != 0):
                    raise ValueError(f"offsets/velocities: object {i} is static and cannot be moved")
                continue
            if not np.any(offsets[i]) and not np.any(velocities[i]):
                continue  # a reset of a soft body is not free: it moves pybullet's solver state
            pos, quat = p.getBasePositionAndOrientation(obj.body, physicsClientId=c)
            p.resetBasePositionAndOrientation(obj.body, (np.asarray(pos) + offsets[i]).tolist(), quat,
                                              physicsClientId=c)
            if np.any(velocities[i] != 0):
                if obj.material == RIGID:
                    lin, ang = p.getBaseVelocity(obj.body, physicsClientId=c)
                else:
                    lin = np.zeros(3) if obj.velocity is None else obj.velocity.mean(axis=0)
                    ang = (0.0, 0.0, 0.0)
                p.resetBaseVelocity(obj.body, (np.asarray(lin) + velocities[i]).tolist(), list(ang),
                                    physicsClientId=c)
        return self.leaf_positions()

    # -- internals ----------------------------------------------------------------------------
    def _require_started(self) -> None:
        if self._client is None:
            raise RuntimeError("scene: call reset() first")

    def _object_positions(self, obj: SceneObject) -> np.ndarray:
        c = self._client
        if obj.material in (RIGID, STATIC):
            pos, quat = p.getBasePositionAndOrientation(obj.body, physicsClientId=c)
            rot = _rotation_matrices(np.asarray(quat)[None])[0]
            return obj.local_leaves @ rot.T + np.asarray(pos)
        _, verts = p.getMeshData(obj.body, -1, flags=p.MESH_DATA_SIMULATION_MESH, physicsClientId=c)
        return np.asarray(verts, dtype=np.float64)

    def _kick_deformable(self, obj: SceneObject, dv: np.ndarray, spin: np.ndarray) -> np.ndarray:
        r"""Set node velocities to ``v_mean + dv + spin x (x - x_mean)``; return the per-leaf forces
        :math:`f_i = m_i (v_i^{new} - v_i^{old}) / \Delta t`."""
        n = len(obj.local_leaves)
        if not np.any(dv != 0) and not np.any(spin != 0):
            return np.zeros((n, 3))
        x = self._object_positions(obj)
        v_old = np.zeros((n, 3)) if obj.velocity is None else obj.velocity
        v_lin = v_old.mean(axis=0) + dv
        v_new = v_lin + np.cross(spin, x - x.mean(axis=0))
        p.resetBaseVelocity(obj.body, v_lin.tolist(), spin.tolist(), physicsClientId=self._client)
        return (obj.mass / n) * (v_new - v_old) / self.dt

    def _add_soft_lattice(self, nodes: np.ndarray, tets: np.ndarray, mass: float, log10_mu: float, position,
                          orientation, friction: float) -> int:
        """A Neo-Hookean soft body of the tetrahedral mesh ``nodes [M, 3]``, ``tets [T, 4]``."""
        path = os.path.join(self._tmpdir.name, f"soft_{len(self._objects)}.vtk")
        write_tetrahedral_vtk(path, nodes, tets)
        mu = 10.0 ** log10_mu
        with quiet_stdout():
            body = p.loadSoftBody(
                path, basePosition=list(position), baseOrientation=list(orientation), mass=mass,
                useNeoHookean=1, NeoHookeanMu=mu, NeoHookeanLambda=NEO_HOOKEAN_LAMBDA_OVER_MU * mu,
                NeoHookeanDamping=NEO_HOOKEAN_DAMPING, useSelfCollision=0,
                frictionCoeff=friction, collisionMargin=SOFT_COLLISION_MARGIN,
                physicsClientId=self._client)
        self._objects.append(SceneObject(SOFT, body, mass, _log_stiffness(log10_mu, SOFT_LOG10_MU_RANGE),
                                     nodes))
        self._check_node_count(self._objects[-1])
        return len(self._objects) - 1

    def _add_cloth_mesh(self, vertices: np.ndarray, faces: np.ndarray, mass: float, log10_k: float, position,
                        orientation, friction: float) -> int:
        """A mass-spring cloth whose nodes are ``vertices [M, 3]`` (``orientation`` None: unrotated)."""
        path = os.path.join(self._tmpdir.name, f"cloth_{len(self._objects)}.obj")
        write_obj(path, vertices, faces)
        pose = {} if orientation is None else {"baseOrientation": list(orientation)}
        with quiet_stdout():
            body = p.loadSoftBody(
                path, basePosition=list(position), mass=mass, useMassSpring=1, useBendingSprings=1,
                springElasticStiffness=10.0 ** log10_k, springDampingStiffness=0.1,
                springBendingStiffness=0.05 * 10.0 ** log10_k, useSelfCollision=0,
                frictionCoeff=friction, collisionMargin=SOFT_COLLISION_MARGIN,
                useFaceContact=1, physicsClientId=self._client, **pose)
        self._objects.append(SceneObject(CLOTH, body, mass, _log_stiffness(log10_k, CLOTH_LOG10_K_RANGE),
                                     vertices))
        self._check_node_count(self._objects[-1])
        return len(self._objects) - 1

    def _check_node_count(self, obj: SceneObject) -> None:
        got = len(self._object_positions(obj))
        if got != len(obj.local_leaves):
            raise RuntimeError(f"pybullet made {got} nodes from a mesh of {len(obj.local_leaves)}")
