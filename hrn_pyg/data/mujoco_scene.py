r"""MuJoCo as a second ground-truth engine: a scene file's scene (``engine = "mujoco"``) built in
MuJoCo, stepped under the same pushes, giving the same episode arrays.

One MJCF model per seed from what the seed drew (:class:`MujocoScene` draws as
:class:`~hrn_pyg.data.scene_file.FileScene` does, so a seed is one scene in both engines):

* the ground is a plane at ``z = 0`` with the scene's ``rolling_friction`` (``condim = 6``);
  each body's friction is its own times the ground's and the ground's 0, since MuJoCo takes the
  larger of two where pybullet multiplies;
* a **rigid** or **static** object is a body (a free joint unless static) with its mesh's voxel
  leaves, colliding as its primitive, a convex mesh's hull or a concave one's convex parts
  (:func:`~hrn_pyg.data.meshes.convex_parts`), with the mesh's inertia;
* a **soft** object is a 3-D flex on pybullet's lattice tetrahedra
  (:func:`~hrn_pyg.data.scene_file.soft_lattice`), linear elastic with :math:`\lambda = 2\mu`:
  :math:`\nu = 1/3`, :math:`E = 2\mu(1 + \nu)`;
* a **cloth** is a 2-D flex whose edges keep their length (inextensible: its stiffness is
  recorded, not simulated);
* a push is a force on a rigid body's centre of mass, or the velocity change of a soft body's or
  cloth's nodes that pybullet's scene makes, recorded as :math:`m_i \Delta v_i / \Delta t`.

Flex elasticity needs the ``discrete`` integrator (stable at 240 Hz); other scenes use
``implicitfast``. What one engine cannot do is one line (:data:`LIMITS`, and a ValueError).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from hrn_pyg.data.kinds import CLOTH, MATERIALS, RIGID, SOFT, STATIC
from hrn_pyg.data.meshes import PRIMITIVES, convex_parts
from hrn_pyg.data.scene_file import (
    CACHE_DIR,
    ENGINE_SCENES,
    FileScene,
    ObjectSpec,
    SceneSpec,
    check_sheet,
    drawn_mesh,
    leaves_of,
    posed_mesh,
    primitive_extents,
    quaternion,
    soft_lattice,
    stiffness_exponent,
    surface_leaves,
)
from hrn_pyg.data.scenes import (
    CLOTH_LOG10_K_RANGE,
    GRAVITY,
    GROUND_HALF_SIDE,
    NEO_HOOKEAN_LAMBDA_OVER_MU,
    SOFT_COLLISION_MARGIN,
    SOFT_LOG10_MU_RANGE,
    STATIC_DENSITY,
    SceneObject,
)
from hrn_pyg.data.voxelise import grid_sheet

try:
    import mujoco
except ImportError:  # the optional `mujoco` extra
    mujoco = None

#: pybullet's Neo-Hookean lambda / mu as a Poisson ratio, and Young's modulus over mu
POISSON = NEO_HOOKEAN_LAMBDA_OVER_MU / (2.0 * (NEO_HOOKEAN_LAMBDA_OVER_MU + 1.0))
YOUNG_OVER_MU = 2.0 * (1.0 + POISSON)
#: flex damping (s, MuJoCo's Rayleigh stiffness-proportional damping): small, as pybullet's 0.02
FLEX_DAMPING = 0.002
#: a flex node's contact radius (m): pybullet's soft collision margin
FLEX_RADIUS = SOFT_COLLISION_MARGIN
#: the ground's contact time constant in physics steps (MuJoCo's ``solref``; 2 is the stiffest it
#: keeps stable): a 0.1 m cube dropped 0.1 m sinks 1.4 cm into the ground on impact at MuJoCo's
#: default 0.02 s, 0.9 cm at two steps of 1/240 s
CONTACT_TIME_STEPS = 2.0
#: the integrators: with flex elasticity, and without
FLEX_INTEGRATOR = "discrete"
RIGID_INTEGRATOR = "implicitfast"
#: what one engine does that the other cannot, one line each (docs/data.md lists them)
LIMITS = {
    "pass_through": "mujoco: pass_through pairs are rigid or static bodies only (a flex collides with every body)",
    "nudge": "mujoco: Scene.nudge (the perturbed starts of a ground-truth ensemble) is pybullet's only",
    "friction": "pybullet multiplies two bodies' friction, mujoco takes the larger: each mujoco body gets its "
                "product with the ground's, so ground contacts match and contacts between bodies differ",
    "static_concave": "mujoco collides a concave static mesh as its convex parts, pybullet as its triangles",
    "cloth_stiffness": "mujoco's cloth is inextensible (edge equality constraints): its stiffness is recorded, not simulated",
    "soft_model": "mujoco's flex is linear elastic (it can collapse where pybullet's Neo-Hookean body stands)",
}


def _numbers(values) -> str:
    return " ".join(f"{float(v):.10g}" for v in np.ravel(values))


def _quat(drawn: dict) -> str:
    """The drawn orientation as MJCF's ``w x y z``."""
    q = quaternion(drawn)
    return "1 0 0 0" if q is None else _numbers([q[3], q[0], q[1], q[2]])


def obj_parts(path: str | Path) -> list[np.ndarray]:
    """The vertices ``[V_k, 3]`` of each part (``o`` block) of an OBJ of convex parts."""
    vertices, parts = [], []
    with open(path) as f:
        for line in f:
            if line.startswith("v "):
                vertices.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("o "):
                parts.append([])
            elif line.startswith("f "):
                if not parts:
                    parts.append([])
                parts[-1].extend(int(tok.split("/")[0]) - 1 for tok in line.split()[1:])
    table = np.asarray(vertices, dtype=np.float64)
    return [table[np.unique(part)] for part in parts if len(np.unique(part)) >= 4]


def collision_geoms(name: str, obj: ObjectSpec, mesh: trimesh.Trimesh, drawn: dict, static: bool
                    ) -> tuple[list[str], list[str]]:
    """The MJCF ``<geom>`` elements of a rigid or static body and the ``<mesh>`` assets they use:
    a primitive's own shape, a convex mesh's hull, a concave one's convex parts."""
    kind = drawn_mesh(obj, drawn)
    if kind in PRIMITIVES:
        extents = primitive_extents(kind, drawn)
        if kind == "box":
            return [f'<geom type="box" size="{_numbers(np.asarray(mesh.extents) / 2)}"/>'], []
        if kind == "sphere":
            return [f'<geom type="sphere" size="{extents[0] / 2:.10g}"/>'], []
        if kind == "cylinder":
            return [f'<geom type="cylinder" size="{extents[0] / 2:.10g} {extents[2] / 2:.10g}"/>'], []
        if kind == "capsule":
            radius = extents[0] / 2
            return [f'<geom type="capsule" size="{radius:.10g} {max(extents[2] - 2 * radius, 1e-4) / 2:.10g}"/>'], []
        parts = [np.asarray(mesh.vertices)]
    else:
        hull = mesh.convex_hull
        if mesh.is_watertight and hull.volume - mesh.volume <= 0.02 * hull.volume:
            parts = [np.asarray(hull.vertices)]
        else:
            parts = obj_parts(convex_parts(mesh, CACHE_DIR))
    assets = [f'<mesh name="{name}_{k}" vertex="{_numbers(v)}"/>' for k, v in enumerate(parts)]
    return [f'<geom type="mesh" mesh="{name}_{k}"/>' for k in range(len(parts))], assets


def _inertial(mesh: trimesh.Trimesh, mass: float) -> str:
    """An ``<inertial>`` of ``mesh`` (its hull when it is not closed) at ``mass`` (kg), in the body frame."""
    solid = mesh if mesh.is_watertight and mesh.volume > 0 else mesh.convex_hull
    inertia = np.asarray(solid.moment_inertia) * mass / max(float(solid.mass), 1e-12)
    full = [inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]]
    return f'<inertial pos="{_numbers(solid.center_mass)}" mass="{mass:.10g}" fullinertia="{_numbers(full)}"/>'


class MujocoScene(FileScene):
    """The MuJoCo scene of a :class:`~hrn_pyg.data.scene_file.SceneSpec` and a seed: the life
    cycle, shapes and pushes of :class:`~hrn_pyg.data.scenes.Scene` (``reset``, ``step``,
    ``leaf_positions``, ``last_forces``, ``close``)."""

    def __init__(self, spec: SceneSpec, seed: int) -> None:
        if mujoco is None:
            raise ValueError(f"{spec.name}: the mujoco engine needs the mujoco package: pip install 'hrn_pyg[mujoco]'")
        self._model = None
        self._data = None
        self._flex_dofs: dict[int, np.ndarray] = {}
        super().__init__(spec, seed)

    # -- the model ----------------------------------------------------------------------------
    def model_xml(self) -> str:
        """The MJCF of this seed's world; fills ``self._objects`` (bodies named ``o<i>``, flexes ``f<i>``)."""
        cfg, bodies, assets, excluded = self.config, [], [], []
        self._objects = []
        for index, (obj, drawn) in enumerate(zip(self.spec.objects, self.params["objects"])):
            material, where = MATERIALS.index(obj.material), f"{self.spec.name}: objects[{index}]"
            friction = float(drawn.get("friction", cfg.friction)) * cfg.friction  # pybullet's product rule
            position = _numbers(drawn["position"])
            if material in (RIGID, STATIC):
                mesh = posed_mesh(obj, drawn)
                leaves = leaves_of(mesh, cfg.pitch, where)
                geoms, meshes = collision_geoms(f"o{index}", obj, mesh, drawn, material == STATIC)
                assets += meshes
                static = material == STATIC
                mass = STATIC_DENSITY * float(abs(mesh.volume) or mesh.convex_hull.volume) if static else float(drawn["mass"])
                inside = ("" if static else "<freejoint/>" + _inertial(mesh, mass)) + "".join(
                    g.replace("<geom ", f'<geom friction="{friction:.10g} 0 0" ') for g in geoms)
                bodies.append(f'<body name="o{index}" pos="{position}" quat="{_quat(drawn)}">{inside}</body>')
                self._objects.append(SceneObject(material, index, mass, 1.0, leaves))
                continue
            if material == SOFT:
                nodes, elements = soft_lattice(posed_mesh(obj, drawn), cfg.pitch, where)
                log10_mu = drawn["log10_mu"] if "log10_mu" in drawn else stiffness_exponent(drawn, SOFT_LOG10_MU_RANGE)
                elastic = (f'<elasticity young="{YOUNG_OVER_MU * 10.0 ** log10_mu:.10g}" poisson="{POISSON:.10g}" '
                           f'damping="{FLEX_DAMPING:.10g}"/>')
                stiffness = float(np.clip((log10_mu - SOFT_LOG10_MU_RANGE[0]) / np.ptp(SOFT_LOG10_MU_RANGE), 0, 1))
                dim = 3
            else:
                mesh = posed_mesh(obj, drawn)
                if mesh is None:
                    check_sheet(float(drawn["size"]), cfg.pitch, where)
                    nodes, elements = grid_sheet(float(drawn["size"]), cfg.pitch)
                else:
                    nodes, elements = surface_leaves(mesh, where), np.asarray(mesh.faces)
                log10_k = (drawn["log10_spring_k"] if "log10_spring_k" in drawn
                           else stiffness_exponent(drawn, CLOTH_LOG10_K_RANGE))
                elastic = '<edge equality="true"/>'  # the discrete integrator has no 2-D elasticity
                stiffness = float(np.clip((log10_k - CLOTH_LOG10_K_RANGE[0]) / np.ptp(CLOTH_LOG10_K_RANGE), 0, 1))
                dim = 2
            mass = float(drawn["mass"])
            bodies.append(
                f'<flexcomp name="f{index}" type="direct" dim="{dim}" point="{_numbers(nodes)}" '
                f'element="{_numbers(elements)}" pos="{position}" quat="{_quat(drawn)}" radius="{FLEX_RADIUS}" '
                f'mass="{mass:.10g}">{elastic}<contact condim="3" selfcollide="none" friction="{friction:.10g}"/>'
                "</flexcomp>")
            self._objects.append(SceneObject(material, index, mass, stiffness, np.asarray(nodes, dtype=np.float64)))
        for i, j in self.spec.pass_through:
            if any(self._objects[k].material in (SOFT, CLOTH) for k in (i, j)):
                raise ValueError(f"{self.spec.name}: {LIMITS['pass_through']}")
            excluded.append(f'<exclude body1="o{i}" body2="o{j}"/>')
        rolling = cfg.rolling_friction
        ground = (f'<geom name="ground" type="plane" size="{GROUND_HALF_SIDE} {GROUND_HALF_SIDE} 0.1" '
                  f'friction="0 {rolling:.10g} {rolling:.10g}" condim="{6 if rolling > 0 else 3}" '
                  f'solref="{CONTACT_TIME_STEPS / cfg.physics_hz:.10g} 1"/>')
        integrator = FLEX_INTEGRATOR if self.uses_deformables else RIGID_INTEGRATOR
        return (f'<mujoco model="{self.spec.name}"><option timestep="{1.0 / cfg.physics_hz:.12g}" '
                f'gravity="0 0 {-GRAVITY}" integrator="{integrator}"/>'
                f'<asset>{"".join(assets)}</asset><worldbody>{ground}{"".join(bodies)}</worldbody>'
                f'<contact>{"".join(excluded)}</contact></mujoco>')

    def reset(self) -> np.ndarray:
        """(Re)build this seed's world in MuJoCo; return leaf positions ``[L, 3]``."""
        self.close()
        self._schedules = {}
        xml = self.model_xml()
        try:
            self._model = mujoco.MjModel.from_xml_string(xml)
        except ValueError as exc:
            raise ValueError(f"{self.spec.name}: MuJoCo refused the scene ({str(exc).splitlines()[0]})") from None
        self._data = mujoco.MjData(self._model)
        model = self._model
        for obj in self._objects:  # a loop over the objects, not their leaves
            if obj.material in (SOFT, CLOTH):
                flex = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_FLEX, f"f{obj.body}")
                first, count = model.flex_vertadr[flex], model.flex_vertnum[flex]
                if count != len(obj.local_leaves):
                    raise RuntimeError(f"MuJoCo made {count} flex nodes from a mesh of {len(obj.local_leaves)}")
                bodies = model.flex_vertbodyid[first: first + count]
                self._flex_dofs[obj.body] = model.body_dofadr[bodies][:, None] + np.arange(3)
                obj.body = flex
            else:
                obj.body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, obj_name(obj.body))
        mujoco.mj_forward(model, self._data)
        for obj, drawn in zip(self._objects, self.params["objects"]):
            self._start_moving(obj, drawn)
        mujoco.mj_forward(model, self._data)
        self.t = 0
        self.last_forces = None
        return self.leaf_positions()

    def close(self) -> None:
        self._model = self._data = None
        self._flex_dofs = {}

    def _require_started(self) -> None:
        if self._data is None:
            raise RuntimeError("scene: call reset() first")

    # -- state --------------------------------------------------------------------------------
    def _dofs(self, obj: SceneObject) -> np.ndarray:
        """The velocity indices ``[n, 3]`` of a flex's nodes (each node a body of three slide joints)."""
        return self._flex_dofs[next(k for k, o in enumerate(self._objects) if o is obj)]

    def _object_positions(self, obj: SceneObject) -> np.ndarray:
        data = self._data
        if obj.material in (RIGID, STATIC):
            rotation = data.xmat[obj.body].reshape(3, 3)
            return obj.local_leaves @ rotation.T + data.xpos[obj.body]
        first, count = self._model.flex_vertadr[obj.body], self._model.flex_vertnum[obj.body]
        return np.array(data.flexvert_xpos[first: first + count], dtype=np.float64)

    def _start_moving(self, obj: SceneObject, drawn: dict) -> None:
        """The drawn start velocity and spin (a soft body's or cloth's nodes move as one rigid body)."""
        velocity, spin = np.asarray(drawn["velocity"], float), np.asarray(drawn["spin"], float)
        if obj.material == STATIC or not (np.any(velocity) or np.any(spin)):
            return
        qvel = self._data.qvel
        if obj.material == RIGID:
            first = self._model.body_dofadr[obj.body]
            rotation = self._data.xmat[obj.body].reshape(3, 3)
            qvel[first: first + 3] = velocity
            qvel[first + 3: first + 6] = rotation.T @ spin  # a free joint's angular velocity is in the body frame
            return
        x = self._object_positions(obj)
        qvel[self._dofs(obj)] = velocity + np.cross(spin, x - x.mean(axis=0))

    def _kick(self, obj: SceneObject, dv: np.ndarray, spin: np.ndarray) -> np.ndarray:
        r"""Set a flex's node velocities to :math:`\bar v + \Delta v + \omega \times (x - \bar x)`
        (as pybullet's ``resetBaseVelocity`` does to a soft body); the per-node force
        :math:`m_i (v_i^{new} - v_i^{old}) / \Delta t`, ``[n, 3]``."""
        n = len(obj.local_leaves)
        if not np.any(dv) and not np.any(spin):
            return np.zeros((n, 3))
        dofs, x = self._dofs(obj), self._object_positions(obj)
        v_old = np.array(self._data.qvel[dofs])
        v_new = v_old.mean(axis=0) + dv + np.cross(spin, x - x.mean(axis=0))
        self._data.qvel[dofs] = v_new
        return (obj.mass / n) * (v_new - v_old) / self.dt

    def step(self, action_forces: np.ndarray | None = None, action_spins: np.ndarray | None = None) -> np.ndarray:
        """Advance one model step under ``action_forces [O, 3]`` (N) and ``action_spins [O, 3]``
        (rad/s, soft and cloth); return the leaves ``[L, 3]`` (as :meth:`Scene.step`)."""
        self._require_started()
        n_obj = self.num_objects
        forces = self.zero_action() if action_forces is None else np.asarray(action_forces, float)
        spins = np.zeros((n_obj, 3)) if action_spins is None else np.asarray(action_spins, float)
        for name, value in (("action_forces", forces), ("action_spins", spins)):
            if value.shape != (n_obj, 3) or not np.all(np.isfinite(value)):
                raise ValueError(f"{name}: expected finite [{n_obj}, 3], got {value.shape}")
        leaf_forces = []
        applied = self._data.xfrc_applied
        for i, obj in enumerate(self._objects):  # a handful of objects, not particles
            n = len(obj.local_leaves)
            if obj.material == STATIC:
                if np.any(forces[i]) or np.any(spins[i]):
                    raise ValueError(f"action_forces: object {i} is static and cannot be pushed")
                leaf_forces.append(np.zeros((n, 3)))
            elif obj.material == RIGID:
                if np.any(spins[i]):
                    raise ValueError(f"action_spins: object {i} is rigid; spins are for soft bodies")
                applied[obj.body, :3] = forces[i]
                leaf_forces.append(np.broadcast_to(forces[i] / n, (n, 3)))
            else:
                leaf_forces.append(self._kick(obj, forces[i] * self.dt / obj.mass, spins[i]))
        self.last_forces = np.concatenate(leaf_forces)
        mujoco.mj_step(self._model, self._data, nstep=self.config.substeps)
        applied[:] = 0.0
        self.t += 1
        return self.leaf_positions()

    def nudge(self, offsets: np.ndarray, velocities: np.ndarray | None = None) -> np.ndarray:
        raise ValueError(LIMITS["nudge"])


def obj_name(index: int) -> str:
    """The MJCF name of object ``index``'s body."""
    return f"o{index}"


ENGINE_SCENES["mujoco"] = MujocoScene
