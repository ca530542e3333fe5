"""Ground-truth physics: the six pybullet scenes and the episode they produce.

Every scene runs headless (``pybullet.DIRECT``) in its own client, is seeded (one
``numpy.random.Generator`` per scene draws every parameter and every random action), and stores
what it drew together with its configuration in the episode (``params``, JSON).

Leaves (the particles the model sees), per material:

* **rigid / static**: the filled voxel centres of the body's trimesh mesh
  (:func:`hrn_pyg.data.voxelise.voxelise`), carried by the body's pose
  :math:`x_i = R(q)\\,\\ell_i + p`; pybullet simulates the matching primitive (box, sphere) or
  convex mesh (wedge).
* **soft**: the same voxel centres become the nodes of a tetrahedral mesh (``.vtk``) that
  pybullet simulates as a Neo-Hookean deformable body; leaves = its simulation nodes, in the
  ``.vtk``'s node order (pybullet keeps it), so ground truth is exact.
* **cloth**: a one-layer lattice loaded as a mass-spring soft body; leaves = its nodes.

The ground is a static box whose top face is ``z = 0`` (pybullet's ``GEOM_PLANE`` does not
collide properly with deformable bodies: a soft cube hovers ~0.1 m above it). It is not an
object: the model sees the height ``z``.

A model step is ``substeps`` physics steps of ``1 / physics_hz`` s. External forces (actions)
are constant over one model step; the episode records, per leaf, the force that acted on it:
total body force / leaf count for a rigid body; for soft bodies and cloth (pybullet cannot push
their nodes) an action is an instantaneous velocity change of all nodes, recorded as the
equivalent per-leaf force :math:`f_i = m_i\\,\\Delta v_i / \\Delta t`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np

from hrn_pyg.data.effects import SceneEffects
from hrn_pyg.data.graph import CLOTH, RIGID, SOFT, STATIC
from hrn_pyg.data.voxelise import (
    box_mesh,
    grid_sheet,
    lattice_tetrahedra,
    sphere_mesh,
    voxelise,
    wedge_mesh,
    write_obj,
    write_tetrahedral_vtk,
)
from hrn_pyg.utils.files import import_pybullet, quiet_stdout

p = import_pybullet()

GRAVITY = 9.81
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
# configurations: one frozen dataclass per scene, holding the ranges parameters are drawn from
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SceneConfig:
    """Settings shared by every scene.

    ``steps``: model steps per episode; ``substeps``: physics steps per model step;
    ``physics_hz``: physics rate; ``pitch``: voxel size (m) for leaves; ``friction``: lateral
    friction of every body and the ground; ``rolling_friction``: the ground's rolling and
    spinning friction (0: a ball on the ground rolls or spins forever; > 0: it slows down and
    comes to rest). A field named ``*_range`` is ``(low, high)``.

    Episodes are long (150-160 model steps; the wedge 140) and end in a rest phase: scripted
    pushes stop early enough (``last_push_step_range``) for the objects to settle and stay still
    for the last 40+ steps, so a model sees both contacts and long stretches of rest. (Resting
    soft bodies and cloth keep pybullet's small contact jitter: node speeds of mm/s to cm/s.)
    """

    steps: int = 150
    substeps: int = 8
    physics_hz: float = 240.0
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


@dataclass(frozen=True)
class SoftBounceConfig(SceneConfig):
    """Soft cube resting on the ground, kicked up and spun once, falls, bounces and rests."""

    steps: int = 160
    cube_side: float = 0.2
    mass_range: tuple[float, float] = (0.5, 1.5)
    log10_mu_range: tuple[float, float] = (2.8, 3.4)
    kick_step_range: tuple[int, int] = (2, 5)
    up_speed_range: tuple[float, float] = (2.0, 3.0)
    side_speed_range: tuple[float, float] = (0.0, 0.4)
    spin_range: tuple[float, float] = (3.0, 8.0)
    nonnegative_ranges: ClassVar[tuple[str, ...]] = (
        "mass_range", "kick_step_range", "up_speed_range", "side_speed_range", "spin_range")


@dataclass(frozen=True)
class CubeCollisionConfig(SceneConfig):
    """Two rigid cubes on the ground pushed into each other by repeated impulses.

    No impulse after the episode's ``last_push_step`` (drawn from ``last_push_step_range``):
    the cubes slide to a stop and rest for the remaining steps.
    """

    steps: int = 160
    cube_side: float = 0.1
    mass_range: tuple[float, float] = (0.5, 2.0)
    distance_range: tuple[float, float] = (0.35, 0.7)
    push_speed_range: tuple[float, float] = (1.2, 2.5)
    push_every_range: tuple[int, int] = (12, 20)
    first_push_range: tuple[int, int] = (2, 4)
    last_push_step_range: tuple[int, int] = (60, 80)
    nonnegative_ranges: ClassVar[tuple[str, ...]] = (
        "mass_range", "distance_range", "push_speed_range", "push_every_range", "first_push_range",
        "last_push_step_range")


@dataclass(frozen=True)
class WedgeConfig(SceneConfig):
    """A ball dropped onto the ridge of a static wedge; a small offset picks the side.

    The ground's rolling friction stops the ball once it has rolled off the wedge (after
    ~1.3 m, by step 76-91 over seeds 0-25), so it rests for the last ~50 steps.
    """

    steps: int = 140
    rolling_friction: float = 0.01
    ball_radius: float = 0.075
    ball_mass_range: tuple[float, float] = (0.3, 1.0)
    wedge_width: float = 0.4
    wedge_length: float = 0.3
    wedge_height_range: tuple[float, float] = (0.15, 0.25)
    drop_height_range: tuple[float, float] = (0.05, 0.2)
    offset_range: tuple[float, float] = (-0.01, 0.01)
    nonnegative_ranges: ClassVar[tuple[str, ...]] = (
        "ball_mass_range", "wedge_height_range", "drop_height_range")


@dataclass(frozen=True)
class MultiMaterialConfig(SceneConfig):
    """A rigid cube, a soft cube and a cloth falling onto the ground (the cloth on top)."""

    rigid_side: float = 0.1
    soft_side: float = 0.2
    cloth_size: float = 0.5
    rigid_mass_range: tuple[float, float] = (0.5, 1.5)
    soft_mass_range: tuple[float, float] = (0.5, 1.5)
    cloth_mass_range: tuple[float, float] = (0.1, 0.3)
    log10_mu_range: tuple[float, float] = (2.8, 3.4)
    log10_cloth_k_range: tuple[float, float] = (1.0, 2.0)
    cube_drop_range: tuple[float, float] = (0.02, 0.2)
    cloth_height_range: tuple[float, float] = (0.45, 0.6)
    nonnegative_ranges: ClassVar[tuple[str, ...]] = (
        "rigid_mass_range", "soft_mass_range", "cloth_mass_range", "cube_drop_range",
        "cloth_height_range")


@dataclass(frozen=True)
class CubePushConfig(SceneConfig):
    """Two rigid cubes that pass through each other, moved by random horizontal forces.

    Each push is held ``hold_range`` steps, then ``pause_range`` steps without force; no push
    after the episode's ``last_push_step`` (so the cubes settle and rest at the end).
    """

    cube_side: float = 0.1
    mass_range: tuple[float, float] = (0.8, 1.2)
    spread: float = 0.6
    force_range: tuple[float, float] = (0.0, 15.0)
    hold_range: tuple[int, int] = (3, 8)
    pause_range: tuple[int, int] = (5, 30)
    last_push_step_range: tuple[int, int] = (60, 80)
    nonnegative_ranges: ClassVar[tuple[str, ...]] = (
        "mass_range", "force_range", "hold_range", "pause_range", "last_push_step_range")


@dataclass(frozen=True)
class TowerConfig(SceneConfig):
    """Three stacked rigid cubes and a ball pushed by random forces (mostly towards them).

    Pushes are scheduled as in :class:`CubePushConfig` but follow each other without pauses (a
    ball that stops between pushes seldom topples the tower: 1 of 12 seeds with 5-30 step
    pauses, 5 of 12 without); the episode's rest phase comes after ``last_push_step``, and the
    ground's rolling friction stops the ball then.
    """

    rolling_friction: float = 0.05
    cube_side: float = 0.1
    #: each cube's horizontal offset from the stack's axis, per cube and axis (m; default a
    #: straight stack). With ``force_range = (0, 0)``: towers that stand a little off-centre for a
    #: whole episode, data for a model that must hold a stack at rest
    stack_offset_range: tuple[float, float] = (0.0, 0.0)
    ball_radius: float = 0.075
    cube_mass_range: tuple[float, float] = (0.2, 0.5)
    ball_mass_range: tuple[float, float] = (0.5, 1.0)
    ball_distance_range: tuple[float, float] = (0.25, 0.45)
    force_range: tuple[float, float] = (0.0, 8.0)
    aim_noise_range: tuple[float, float] = (-0.35, 0.35)
    hold_range: tuple[int, int] = (3, 8)
    pause_range: tuple[int, int] = (0, 0)
    last_push_step_range: tuple[int, int] = (60, 80)
    nonnegative_ranges: ClassVar[tuple[str, ...]] = (
        "cube_mass_range", "ball_mass_range", "ball_distance_range", "force_range", "hold_range",
        "pause_range", "last_push_step_range")


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
    """A seeded pybullet scene stepped one model step at a time.

    Life cycle: ``scene = make_scene(name, seed, config)``; ``x0 = scene.reset()``;
    ``x = scene.step(action_forces)`` any number of times; ``scene.close()``. ``reset`` rebuilds
    the same world (same drawn parameters) so a policy can be replayed from the start.

    **Shapes**
    - ``reset()``, ``step()`` return leaf positions ``[L, 3]`` float64.
    - ``action_forces``: ``[O, 3]`` force (N) on each object's centre of mass during the step.
      Rigid: applied as a force every substep. Soft / cloth: an equivalent velocity change
      :math:`\\Delta v = F \\Delta t / M` of all nodes at the start of the step. Static: must be 0.
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
        """Draw this episode's parameters from the config's ranges (JSON-able dict)."""
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
        """Advance one model step under ``action_forces [O, 3]`` (N); return leaves ``[L, 3]``.

        ``action_spins [O, 3]`` (rad/s, soft/cloth only) sets a rigid spin of the body's nodes
        about their centre of mass, together with the force's velocity change.
        """
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
        """Translate each object by ``offsets [O, 3]`` (m) and add ``velocities [O, 3]`` (m/s)
        to its linear velocity, at once; return the new leaf positions ``[L, 3]``.

        For perturbing an initial state (a soft body or cloth is translated rigidly and all its
        nodes get the mean node velocity plus the offset). Static objects' rows must be zero.
        """
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
        """Set node velocities to ``v_mean + dv + spin x (x - x_mean)``; return per-leaf forces.

        pybullet's ``resetBaseVelocity`` on a soft body overwrites every node's velocity with
        that rigid field, so the recorded force is the actual change per node,
        :math:`f_i = m_i (v_i^{new} - v_i^{old}) / \\Delta t`.
        """
        n = len(obj.local_leaves)
        if not np.any(dv != 0) and not np.any(spin != 0):
            return np.zeros((n, 3))
        x = self._object_positions(obj)
        v_old = np.zeros((n, 3)) if obj.velocity is None else obj.velocity
        v_lin = v_old.mean(axis=0) + dv
        v_new = v_lin + np.cross(spin, x - x.mean(axis=0))
        p.resetBaseVelocity(obj.body, v_lin.tolist(), spin.tolist(), physicsClientId=self._client)
        return (obj.mass / n) * (v_new - v_old) / self.dt

    def _add_rigid(self, mesh_kind: str, size, mass: float, position, orientation=(0, 0, 0, 1),
                   static: bool = False) -> int:
        """Add a rigid (or static, ``mass`` ignored) body whose leaves voxelise its mesh."""
        c, pitch = self._client, self.config.pitch
        if mesh_kind == "box":
            mesh = box_mesh(size)
            shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=(np.asarray(mesh.extents) / 2).tolist(),
                                           physicsClientId=c)
        elif mesh_kind == "sphere":
            mesh = sphere_mesh(size)
            shape = p.createCollisionShape(p.GEOM_SPHERE, radius=float(size), physicsClientId=c)
        elif mesh_kind == "wedge":
            mesh = wedge_mesh(*size)
            shape = p.createCollisionShape(p.GEOM_MESH, vertices=mesh.vertices.tolist(),
                                           physicsClientId=c)
        else:
            raise ValueError(f"mesh_kind: unknown {mesh_kind!r}")
        leaves = voxelise(mesh, pitch)
        body = p.createMultiBody(0.0 if static else mass, shape, basePosition=list(position),
                                 baseOrientation=list(orientation), physicsClientId=c)
        p.changeDynamics(body, -1, lateralFriction=self.config.friction, physicsClientId=c)
        if static:
            mass = STATIC_DENSITY * float(mesh.volume)
        self._objects.append(SceneObject(STATIC if static else RIGID, body, mass, 1.0, leaves))
        return len(self._objects) - 1

    def _add_soft_cube(self, side: float, mass: float, log10_mu: float, position,
                       orientation=(0, 0, 0, 1)) -> int:
        nodes, tets = lattice_tetrahedra(voxelise(box_mesh(side), self.config.pitch),
                                         self.config.pitch)
        return self._add_soft_lattice(nodes, tets, mass, log10_mu, position, orientation, self.config.friction)

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

    def _add_cloth(self, size: float, mass: float, log10_k: float, position) -> int:
        vertices, faces = grid_sheet(size, self.config.pitch)
        return self._add_cloth_mesh(vertices, faces, mass, log10_k, position, None, self.config.friction)

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


def _uniform(rng: np.random.Generator, rng_range) -> float:
    return float(rng.uniform(*rng_range))


def _integer(rng: np.random.Generator, rng_range) -> int:
    return int(rng.integers(rng_range[0], rng_range[1] + 1))


def _yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


class SoftBounce(Scene):
    """Soft cube kicked up (with spin) once, flies, lands and deforms."""

    name = "soft_bounce"
    effects = SceneEffects(forces=True, collisions=False)  # one body: nothing to collide with
    config_cls = SoftBounceConfig
    uses_deformables = True

    def draw_params(self, rng):
        cfg = self.config
        axis_angle = rng.uniform(0, 2 * np.pi)
        side_angle = rng.uniform(0, 2 * np.pi)
        spin = _uniform(rng, cfg.spin_range)
        side = _uniform(rng, cfg.side_speed_range)
        return {
            "mass": _uniform(rng, cfg.mass_range),
            "log10_mu": _uniform(rng, cfg.log10_mu_range),
            "yaw": float(rng.uniform(0, np.pi / 2)),
            "kick_step": _integer(rng, cfg.kick_step_range),
            "kick_velocity": [side * math.cos(side_angle), side * math.sin(side_angle),
                              _uniform(rng, cfg.up_speed_range)],
            "spin": [spin * math.cos(axis_angle), spin * math.sin(axis_angle), 0.0],
        }

    def build(self):
        half = self.config.cube_side / 2
        self._add_soft_cube(self.config.cube_side, self.params["mass"], self.params["log10_mu"],
                            (0, 0, half + SOFT_COLLISION_MARGIN), _yaw_quaternion(self.params["yaw"]))

    def scripted_action(self, t):
        forces, spins = self.zero_action(), np.zeros((1, 3))
        if t == self.params["kick_step"]:
            forces[0] = self.params["mass"] * np.asarray(self.params["kick_velocity"]) / self.dt
            spins[0] = self.params["spin"]
        return forces, spins


class CubeCollision(Scene):
    """Two rigid cubes, repeatedly given impulses towards each other."""

    name = "cube_collision"
    effects = SceneEffects(forces=True, collisions=True)
    config_cls = CubeCollisionConfig

    def draw_params(self, rng):
        cfg = self.config
        return {
            "masses": [_uniform(rng, cfg.mass_range), _uniform(rng, cfg.mass_range)],
            "distance": _uniform(rng, cfg.distance_range),
            "heading": float(rng.uniform(0, 2 * np.pi)),
            "yaws": rng.uniform(0, np.pi / 2, size=2).tolist(),
            "push_speeds": [_uniform(rng, cfg.push_speed_range) for _ in range(2)],
            "push_every": _integer(rng, cfg.push_every_range),
            "first_push": _integer(rng, cfg.first_push_range),
            "last_push_step": _integer(rng, cfg.last_push_step_range),
        }

    def build(self):
        pr, side = self.params, self.config.cube_side
        direction = np.array([math.cos(pr["heading"]), math.sin(pr["heading"]), 0.0])
        for sign, mass, yaw in zip((-1, 1), pr["masses"], pr["yaws"]):
            pos = sign * pr["distance"] / 2 * direction + [0, 0, side / 2]
            self._add_rigid("box", side, mass, pos, _yaw_quaternion(yaw))

    def scripted_action(self, t):
        pr, forces = self.params, self.zero_action()
        if t > pr["last_push_step"]:
            return forces, None
        if t >= pr["first_push"] and (t - pr["first_push"]) % pr["push_every"] == 0:
            x = np.stack([self._object_positions(o).mean(axis=0) for o in self._objects])
            towards = x[::-1] - x
            towards[:, 2] = 0.0
            towards /= np.maximum(np.linalg.norm(towards, axis=1, keepdims=True), 1e-9)
            forces = (np.asarray(pr["masses"]) * np.asarray(pr["push_speeds"]))[:, None] * towards / self.dt
        return forces, None


class Wedge(Scene):
    """A ball dropped onto a static wedge's ridge; the sign of a small offset picks a side."""

    name = "wedge"
    effects = SceneEffects(forces=False, collisions=True)  # dropped, never pushed
    config_cls = WedgeConfig

    def draw_params(self, rng):
        cfg = self.config
        return {
            "ball_mass": _uniform(rng, cfg.ball_mass_range),
            "wedge_height": _uniform(rng, cfg.wedge_height_range),
            "drop_height": _uniform(rng, cfg.drop_height_range),
            "offset": _uniform(rng, cfg.offset_range),
            "offset_y": float(rng.uniform(-0.25, 0.25) * cfg.wedge_length),
        }

    def build(self):
        cfg, pr = self.config, self.params
        self._add_rigid("sphere", cfg.ball_radius, pr["ball_mass"],
                        (pr["offset"], pr["offset_y"],
                         pr["wedge_height"] + cfg.ball_radius + pr["drop_height"]))
        self._add_rigid("wedge", (cfg.wedge_width, pr["wedge_height"], cfg.wedge_length), 0.0,
                        (0, 0, 0), static=True)


class MultiMaterial(Scene):
    """A rigid cube and a soft cube fall onto the ground, then a cloth drapes over them."""

    name = "multi_material"
    effects = SceneEffects(forces=False, collisions=True)  # falling, never pushed
    config_cls = MultiMaterialConfig
    uses_deformables = True

    def draw_params(self, rng):
        cfg = self.config
        return {
            "rigid_mass": _uniform(rng, cfg.rigid_mass_range),
            "soft_mass": _uniform(rng, cfg.soft_mass_range),
            "cloth_mass": _uniform(rng, cfg.cloth_mass_range),
            "log10_mu": _uniform(rng, cfg.log10_mu_range),
            "log10_cloth_k": _uniform(rng, cfg.log10_cloth_k_range),
            "drops": [_uniform(rng, cfg.cube_drop_range) for _ in range(2)],
            "yaws": rng.uniform(0, np.pi / 2, size=2).tolist(),
            "cloth_height": _uniform(rng, cfg.cloth_height_range),
            "cloth_offset": rng.uniform(-0.05, 0.05, size=2).tolist(),
            "gap": float(rng.uniform(0.02, 0.08)),
        }

    def build(self):
        cfg, pr = self.config, self.params
        x_rigid = -(cfg.rigid_side / 2 + pr["gap"] / 2)
        x_soft = cfg.soft_side / 2 + pr["gap"] / 2
        self._add_rigid("box", cfg.rigid_side, pr["rigid_mass"],
                        (x_rigid, 0, cfg.rigid_side / 2 + pr["drops"][0]), _yaw_quaternion(pr["yaws"][0]))
        self._add_soft_cube(cfg.soft_side, pr["soft_mass"], pr["log10_mu"],
                            (x_soft, 0, cfg.soft_side / 2 + SOFT_COLLISION_MARGIN + pr["drops"][1]),
                            _yaw_quaternion(pr["yaws"][1]))
        self._add_cloth(cfg.cloth_size, pr["cloth_mass"], pr["log10_cloth_k"],
                        (pr["cloth_offset"][0], pr["cloth_offset"][1], pr["cloth_height"]))


class _RandomForces(Scene):
    """Shared random-action script: a horizontal force on each actuated object, held for a
    random number of steps (so pushes have an effect), then a random pause without force (its
    length drawn from ``pause_range``; may be 0); from step ``last_push_step + 1`` on no force
    at all, so every episode ends at rest."""

    def draw_params(self, rng):
        return self._schedule_params(rng)

    def _schedule_params(self, rng: np.random.Generator) -> dict:
        """The pushes' schedule; drawn after the scene's own parameters, so those are the same
        for a seed whatever the schedule (the RL pools start from them)."""
        return {"last_push_step": _integer(rng, self.config.last_push_step_range)}

    def _aim(self, index: int) -> float:
        """Heading (rad) around which object ``index``'s random force is drawn; uniform here."""
        return float(self.rng.uniform(0, 2 * np.pi))

    def _draw_push(self) -> np.ndarray:
        """Forces ``[O, 3]`` of a new push (horizontal, random heading and magnitude)."""
        push = self.zero_action()
        for i in self.actuated:
            heading = self._aim(i)
            magnitude = _uniform(self.rng, self.config.force_range)
            push[i] = magnitude * np.array([math.cos(heading), math.sin(heading), 0.0])
        return push

    def scripted_action(self, t):
        if t == 0:
            self._current = self.zero_action()
            self._push_end = self._next_change = 0
        if t > self.params["last_push_step"]:
            return self.zero_action(), None
        if t >= self._next_change:
            self._current = self._draw_push()
            self._push_end = t + _integer(self.rng, self.config.hold_range)
            self._next_change = self._push_end + _integer(self.rng, self.config.pause_range)
        if t >= self._push_end:
            return self.zero_action(), None
        return self._current.copy(), None


class CubePush(_RandomForces):
    """Two rigid cubes that do not collide with each other, pushed by random forces."""

    name = "cube_push"
    # pybullet lets the cubes pass through each other, but the models were trained with the
    # collision edges the data graphs have when they overlap, so the search stays on
    effects = SceneEffects(forces=True, collisions=None)
    config_cls = CubePushConfig
    actuated = (0, 1)

    def draw_params(self, rng):
        cfg = self.config
        return {
            "masses": [_uniform(rng, cfg.mass_range) for _ in range(2)],
            "xy": rng.uniform(-cfg.spread / 2, cfg.spread / 2, size=(2, 2)).tolist(),
            "yaws": rng.uniform(0, np.pi / 2, size=2).tolist(),
            **self._schedule_params(rng),
        }

    def build(self):
        cfg, pr = self.config, self.params
        for (x, y), mass, yaw in zip(pr["xy"], pr["masses"], pr["yaws"]):
            self._add_rigid("box", cfg.cube_side, mass, (x, y, cfg.cube_side / 2), _yaw_quaternion(yaw))
        a, b = self._objects[0].body, self._objects[1].body
        p.setCollisionFilterPair(a, b, -1, -1, 0, physicsClientId=self._client)


class Tower(_RandomForces):
    """Three stacked rigid cubes and a ball pushed by random forces aimed roughly at them."""

    name = "tower"
    effects = SceneEffects(forces=True, collisions=True)
    config_cls = TowerConfig
    actuated = (3,)

    def draw_params(self, rng):
        cfg = self.config
        return {
            "cube_masses": [_uniform(rng, cfg.cube_mass_range) for _ in range(3)],
            "ball_mass": _uniform(rng, cfg.ball_mass_range),
            "yaws": rng.uniform(-0.2, 0.2, size=3).tolist(),
            "ball_distance": _uniform(rng, cfg.ball_distance_range),
            "ball_heading": float(rng.uniform(0, 2 * np.pi)),
            **self._schedule_params(rng),
            # drawn last and only when asked for, so the straight stacks' episodes do not change
            "stack_offsets": (rng.uniform(*cfg.stack_offset_range, size=(3, 2)).tolist()
                              if cfg.stack_offset_range != (0.0, 0.0) else [[0.0, 0.0]] * 3),
        }

    def build(self):
        cfg, pr = self.config, self.params
        offsets = pr.get("stack_offsets", [[0.0, 0.0]] * 3)
        for k, (mass, yaw, (dx, dy)) in enumerate(zip(pr["cube_masses"], pr["yaws"], offsets)):
            self._add_rigid("box", cfg.cube_side, mass, (dx, dy, cfg.cube_side * (k + 0.5)),
                            _yaw_quaternion(yaw))
        d, h = pr["ball_distance"], pr["ball_heading"]
        self._add_rigid("sphere", cfg.ball_radius, pr["ball_mass"],
                        (d * math.cos(h), d * math.sin(h), cfg.ball_radius))

    def _aim(self, index):
        ball = self._object_positions(self._objects[index]).mean(axis=0)
        base = self._object_positions(self._objects[0]).mean(axis=0)
        to_tower = base - ball
        return math.atan2(to_tower[1], to_tower[0]) + _uniform(self.rng, self.config.aim_noise_range)


SCENES: dict[str, type[Scene]] = {
    cls.name: cls for cls in (SoftBounce, CubeCollision, Wedge, MultiMaterial, CubePush, Tower)
}


def scene_config(scene: str, **overrides) -> SceneConfig:
    """The scene's default config with ``overrides`` (``None`` values ignored); validated."""
    cls = _scene_class(scene)
    names = {f.name for f in dataclasses.fields(cls.config_cls)}
    unknown = sorted(set(overrides) - names)
    if unknown:
        raise ValueError(f"config: unknown field(s) {unknown} for scene {scene!r}")
    return cls.config_cls(**{k: v for k, v in overrides.items() if v is not None})


def scene_effects(scene: str) -> SceneEffects:
    """The :class:`~hrn_pyg.data.effects.SceneEffects` scene ``scene`` declares (what to simulate)."""
    return _scene_class(scene).effects


def make_scene(scene: str, seed: int, config: SceneConfig | None = None) -> Scene:
    """A :class:`Scene` for ``scene`` (a key of :data:`SCENES`); call ``reset()`` to start it."""
    return _scene_class(scene)(seed, config)


def _scene_class(scene: str) -> type[Scene]:
    if scene not in SCENES:
        raise ValueError(f"scene: unknown {scene!r}; choose one of {sorted(SCENES)}")
    return SCENES[scene]


def config_to_dict(config: SceneConfig) -> dict:
    return {f.name: (list(v) if isinstance(v := getattr(config, f.name), tuple) else v)
            for f in dataclasses.fields(config)}


class SceneSource(Protocol):
    """Anything that makes a seeded :class:`Scene`, as a scene read from a file does
    (:class:`hrn_pyg.data.scene_file.SceneSpec`)."""

    name: str

    def make_scene(self, seed: int) -> Scene: ...


def simulate_episode(scene: str | SceneSource, seed: int, steps: int | None = None,
                     config: SceneConfig | None = None, *,
                     after_reset: Callable[[Scene], None] | None = None) -> dict[str, np.ndarray]:
    """Run one episode with the scene's scripted/random actions; return the episode arrays.

    ``scene`` is a built-in scene's name (with an optional ``config``) or a scene read from a
    file (:func:`hrn_pyg.data.scene_file.read_scene_file`, whose settings are its own).

    ``after_reset(scene)``, if given, runs once after ``reset()`` and before step 0 (e.g.
    :meth:`Scene.nudge` to perturb the initial state of a ground-truth ensemble); the recorded
    ``positions[0]`` is the state after it.

    **Shapes** (``S`` steps, ``L`` leaves, ``O`` objects, ``N`` hierarchy nodes)
    ``positions [S+1, L, 3]`` f32, ``forces [S, L, 3]`` f32, ``leaf_mass [L]`` f32,
    ``leaf_object [L]`` i64, ``object_material [O]`` i64, ``object_stiffness [O]`` f32,
    ``hierarchy_parent [N]`` i64, ``seed``/``scene``/``params``/``dt`` scalars.
    """
    from hrn_pyg.data.hierarchy import build_hierarchy

    if isinstance(scene, str):
        sim = make_scene(scene, seed, config)
    elif config is not None:
        raise ValueError("config: a scene file carries its own settings")
    else:
        sim = scene.make_scene(seed)
    if steps is not None:
        if not isinstance(steps, (int, np.integer)) or steps < 1:
            raise ValueError(f"steps: must be an integer >= 1, got {steps}")
        sim.config = dataclasses.replace(sim.config, steps=int(steps))
    n_steps = sim.config.steps
    try:
        x = sim.reset()
        if after_reset is not None:
            after_reset(sim)
            x = sim.leaf_positions()
        positions = np.empty((n_steps + 1, len(x), 3), dtype=np.float32)
        forces = np.empty((n_steps, len(x), 3), dtype=np.float32)
        positions[0] = x
        for t in range(n_steps):
            action, spins = sim.scripted_action(t)
            positions[t + 1] = sim.step(action, spins)
            forces[t] = sim.last_forces
        leaf_mass, leaf_object = sim.leaf_mass, sim.leaf_object
        episode = {
            "positions": positions,
            "forces": forces,
            "leaf_mass": leaf_mass,
            "leaf_object": leaf_object,
            "object_material": sim.object_material,
            "object_stiffness": sim.object_stiffness,
            "seed": np.array(sim.seed, dtype=np.int64),
            "scene": np.array(sim.name),
            "params": np.array(json.dumps({"params": sim.params, "config": config_to_dict(sim.config),
                                           **({} if isinstance(scene, str) else {"scene_file": scene.text})},
                                          sort_keys=True)),
            "dt": np.array(sim.dt, dtype=np.float64),
        }
    finally:
        sim.close()
    if not np.all(np.isfinite(positions)):
        raise RuntimeError(f"{sim.name} seed {seed}: pybullet produced non-finite positions")
    episode["hierarchy_parent"] = np.asarray(
        build_hierarchy(positions[0].astype(np.float64), leaf_mass.astype(np.float64), leaf_object),
        dtype=np.int64)
    return episode
