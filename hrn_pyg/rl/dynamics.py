"""What the RL environment needs from a physics predictor, and a cheap analytic one.

:class:`StochasticDynamics` is the small protocol :class:`hrn_pyg.rl.env.HRNEnv` steps through:
draw initial scenes, read each movable object's root state, and sample ``k`` next states under
Monte Carlo dropout at a given rate. The learned HRN wraps into it (:class:`hrn_pyg.rl.hrn_dynamics.HRNDynamics`:
the flattened state is the leaf positions at ``t-2, t-1, t``, the roots are mass-weighted leaf
means, ``hrn_pyg.sampling`` gives the ``k`` batched futures).

:class:`PointMassDynamics` is a **development and smoke-test dynamics, not the paper's model**:
every object is a sphere-like point mass under the applied force, gravity, ground friction and
(optionally) position-projected contacts. Its "dropout" is Gaussian noise whose spread follows
the relative standard deviation of an inverted-dropout unit, so rate 0 is exactly deterministic.
Velocities are per-step displacements, ``v_t = x_t - x_{t-1}``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial
from typing import Protocol, runtime_checkable

import torch
from torch import Tensor

from hrn_pyg.utils.checks import check_count, check_rate

#: Per-object root state: position (3) then per-step velocity (3).
ROOT_DIM = 6
#: Relative approach speed (m/step) at which collision noise reaches half its full size; resting
#: contacts (stacked cubes) move far slower than this, so dropout on collisions leaves them quiet.
IMPACT_SPEED = 0.005
#: Guard against dividing by a zero distance between two coincident objects.
DIST_EPS = 1e-9
#: An object counts as touching the ground (and feels friction) within this height margin (m).
GROUND_TOL = 1e-4
#: Steps a tower is left to settle under gravity (once, at construction) so that resets start
#: at rest; the projected contacts sag a few millimetres and come to rest within ~25 steps.
SETTLE_STEPS = 40
#: Modules whose dropout the point-mass model imitates.
MODULES = ("force", "collision")


def dropout_spread(rate: float) -> float:
    r"""Relative standard deviation of one inverted-dropout unit at drop ``rate`` ``p``.

    A unit ``h`` becomes ``h / (1 - p)`` with probability ``1 - p`` and ``0`` otherwise, so its
    relative standard deviation is :math:`\sqrt{p / (1 - p)}`; 0 at ``p = 0``.
    """
    check_rate(rate, "dropout rate")
    return math.sqrt(rate / (1.0 - rate))


def _rand(generator: torch.Generator, *shape: int) -> Tensor:
    """Uniform ``[0, 1)`` draws on the generator's own device (a generator draws nowhere else)."""
    return torch.rand(*shape, generator=generator, device=generator.device)


def _randn(generator: torch.Generator, *shape: int) -> Tensor:
    """Standard normal draws on the generator's own device."""
    return torch.randn(*shape, generator=generator, device=generator.device)


@runtime_checkable
class StochasticDynamics(Protocol):
    """A physics predictor the environment can step.

    Attributes:
        num_objects: ``O``, movable objects whose root states the observation shows.
        object_dim: size of one object's root state in observations (6: position, velocity).
        state_dim: ``S``, length of the flattened per-environment scene state.

    **Shapes**

    - ``reset_states(B, generator)`` -> ``(B, S)``: whatever the dynamics needs to continue
      (point masses: positions and velocities; HRN: leaf positions at ``t-2, t-1, t``).
    - ``roots(states)``: ``(..., S)`` -> ``(..., O, 6)``, any leading dimensions.
    - ``sample_next(states, forces, k, rate, generator)``: ``(B, S)``, ``(B, O, 3)`` (Newton,
      one force per object, spread over its leaves by the dynamics) -> ``(B, k, S)``, ``k``
      futures each with its own dropout masks at ``rate`` on the dynamics' configured modules.
      ``rate = 0`` must return ``k`` identical copies of the deterministic prediction.

    States and forces live on the dynamics' device (the environment's); a ``generator`` draws on
    its own device, and the dynamics moves what it draws.
    """

    num_objects: int
    object_dim: int
    state_dim: int

    def reset_states(self, batch: int, generator: torch.Generator) -> Tensor: ...

    def roots(self, states: Tensor) -> Tensor: ...

    def sample_next(self, states: Tensor, forces: Tensor, k: int, rate: float,
                    generator: torch.Generator) -> Tensor: ...


@dataclass(frozen=True)
class PointMassConfig:
    """Objects, their layout at reset, and the noise that stands in for dropout.

    ``layout`` names the initial-state distribution: ``"cube_push"`` (the objects scattered on
    the ground around the origin within ``spawn_half_width``) or ``"tower"`` (objects ``0..O-2``
    stacked at the origin, the last object, the ball, on the ground at a distance drawn from
    ``ball_distance`` in a random direction). ``ground_friction`` is the fraction of horizontal
    velocity an object on the ground loses per step. ``collide=False`` makes objects pass
    through each other (the cube-push task).
    """

    layout: str
    radius: tuple[float, ...]
    mass: tuple[float, ...]
    ground_friction: tuple[float, ...]
    collide: bool
    dropout_modules: tuple[str, ...] = ("force",)
    dt: float = 1.0 / 30.0
    gravity: float = 9.81
    force_spread: float = 1.0
    collision_spread: float = 1.0
    contact_iterations: int = 8
    spawn_half_width: float = 0.15
    ball_distance: tuple[float, float] = (0.3, 0.45)

    def __post_init__(self) -> None:
        n = len(self.radius)
        if n < 1:
            raise ValueError("radius must name at least one object")
        if len(self.mass) != n or len(self.ground_friction) != n:
            raise ValueError(f"radius, mass and ground_friction must all have {n} entries")
        if any(r <= 0 for r in self.radius) or any(m <= 0 for m in self.mass):
            raise ValueError("radius and mass must be positive")
        if not all(0.0 <= f <= 1.0 for f in self.ground_friction):
            raise ValueError("ground_friction must lie in [0, 1]")
        if self.layout not in ("cube_push", "tower"):
            raise ValueError(f"layout must be 'cube_push' or 'tower', got {self.layout!r}")
        if self.layout == "tower" and n < 2:
            raise ValueError("the tower layout needs at least one cube and the ball")
        unknown = set(self.dropout_modules) - set(MODULES)
        if unknown:
            raise ValueError(f"dropout_modules has unknown entries {sorted(unknown)}; known {MODULES}")
        if self.dt <= 0 or self.contact_iterations < 1:
            raise ValueError("dt must be positive and contact_iterations >= 1")


def point_mass_config(task: str, dropout_modules: tuple[str, ...] | None = None) -> PointMassConfig:
    """The point-mass stand-in of a task scene (``"cube_push"`` or ``"tower"``)."""
    if task == "cube_push":
        # two 10 cm, 1 kg cubes sliding on the ground, transparent to each other
        return PointMassConfig(layout="cube_push", radius=(0.05, 0.05), mass=(1.0, 1.0),
                               ground_friction=(0.1, 0.1), collide=False,
                               dropout_modules=dropout_modules or ("force",))
    if task == "tower":
        # three stacked 10 cm, 0.35 kg cubes and a 7.5 cm, 0.75 kg ball that rolls with little
        # loss (the middles of the pybullet tower scene's ranges)
        return PointMassConfig(layout="tower", radius=(0.05, 0.05, 0.05, 0.075),
                               mass=(0.35, 0.35, 0.35, 0.75), ground_friction=(0.2, 0.2, 0.2, 0.02),
                               collide=True,
                               dropout_modules=dropout_modules or ("force", "collision"))
    raise ValueError(f"no point-mass scene for task {task!r}; known: cube_push, tower")


class PointMassDynamics:
    r"""Point masses under force, gravity, ground friction and projected contacts.

    One step for every object :math:`i` (all objects and all ``k`` samples at once):

    .. math::
        \tilde F_i = F_i + \sigma_F\, s(p)\, \lVert F_i \rVert\, \epsilon_i, \qquad
        \tilde v_i = v_i + \Big(\frac{\tilde F_i}{m_i} - g e_z\Big)\Delta t^2,

    horizontal :math:`\tilde v_i` scaled by :math:`1 - \mu_i` when the object touches the ground,
    :math:`\tilde x_i = x_i + \tilde v_i`, then ``contact_iterations`` Jacobi projections that
    push overlapping pairs apart along their centre line in inverse-mass proportion (noise
    :math:`\sigma_C s(p)` times the overlap, scaled by the pair's impact speed, when dropout is
    on the collision module) and lift objects out of the ground :math:`z \ge r_i`. Finally
    :math:`v_{t+1} = x_{t+1} - x_t`. Here :math:`s(p) = \sqrt{p/(1-p)}` (:func:`dropout_spread`)
    and :math:`\epsilon` are standard normal draws from the given generator, one per sample.

    **Shapes**

    - state: ``(B, O * 6)``, per object ``[x, y, z, vx, vy, vz]``
    - ``sample_next``: states ``(B, O*6)``, forces ``(B, O, 3)`` -> ``(B, k, O*6)``

    States live on ``device``; the noise is drawn on the generator's device and moved there.
    """

    object_dim = ROOT_DIM

    def __init__(self, config: PointMassConfig, device: str | torch.device = "cpu"):
        self.config = config
        self.device = torch.device(device)
        self.num_objects = len(config.radius)
        self.state_dim = self.num_objects * ROOT_DIM
        as_tensor = partial(torch.tensor, dtype=torch.float32, device=self.device)
        self._radius = as_tensor(config.radius)
        self._mass = as_tensor(config.mass)
        self._friction = as_tensor(config.ground_friction)
        self._gravity = as_tensor([0.0, 0.0, config.gravity])
        self._horizontal = as_tensor([1.0, 1.0, 0.0])
        self._stack_height = self._settled_stack() if config.layout == "tower" else None

    @classmethod
    def for_task(cls, task: str, dropout_modules: tuple[str, ...] | None = None,
                 device: str | torch.device = "cpu") -> PointMassDynamics:
        return cls(point_mass_config(task, dropout_modules), device)

    def __repr__(self) -> str:
        c = self.config
        return (f"{type(self).__name__}(layout={c.layout!r}, objects={self.num_objects}, "
                f"collide={c.collide}, dropout_modules={c.dropout_modules})")

    # ------------------------------------------------------------------ state layout
    def roots(self, states: Tensor) -> Tensor:
        """``(..., O*6)`` -> ``(..., O, 6)``: the state already is the root states."""
        if states.shape[-1] != self.state_dim:
            raise ValueError(f"states must end in {self.state_dim}, got shape {tuple(states.shape)}")
        return states.reshape(*states.shape[:-1], self.num_objects, ROOT_DIM)

    def reset_states(self, batch: int, generator: torch.Generator) -> Tensor:
        """Initial scenes at rest, drawn from ``generator``: ``(B, O*6)``."""
        if batch < 1:
            raise ValueError(f"batch must be >= 1, got {batch}")
        c, O = self.config, self.num_objects
        pos = torch.zeros(batch, O, 3, device=self.device)
        if c.layout == "cube_push":
            xy = (_rand(generator, batch, O, 2) * 2 - 1) * c.spawn_half_width
            pos[..., :2] = xy.to(self.device)
            pos[..., 2] = self._radius
        else:  # tower: cubes 0..O-2 stacked at the origin, ball O-1 on the ground nearby
            cubes = O - 1
            pos[:, :cubes, 2] = self._stack_height
            angle = _rand(generator, batch) * 2 * math.pi
            lo, hi = c.ball_distance
            dist = lo + (hi - lo) * _rand(generator, batch)
            pos[:, -1, 0] = (dist * torch.cos(angle)).to(self.device)
            pos[:, -1, 1] = (dist * torch.sin(angle)).to(self.device)
            pos[:, -1, 2] = self._radius[-1]
        vel = torch.zeros_like(pos)
        return torch.cat([pos, vel], -1).reshape(batch, self.state_dim)

    def _settled_stack(self) -> Tensor:
        """Rest heights of the stacked cubes: stack them touching, let gravity settle them."""
        cubes = self.num_objects - 1
        pos = torch.zeros(1, self.num_objects, 3, device=self.device)
        pos[0, :cubes, 2] = torch.cumsum(self._radius[:cubes] * 2, 0) - self._radius[:cubes]
        pos[0, -1, 0] = 10.0  # the ball out of reach, on the ground
        pos[0, -1, 2] = self._radius[-1]
        state = torch.cat([pos, torch.zeros_like(pos)], -1).reshape(1, self.state_dim)
        still = torch.zeros(1, self.num_objects, 3, device=self.device)
        unused = torch.Generator(device=self.device)  # rate 0 draws nothing
        for _ in range(SETTLE_STEPS):  # a loop over time steps
            state = self.sample_next(state, still, 1, 0.0, unused)[:, 0]
        return self.roots(state)[0, :cubes, 2].clone()

    # ------------------------------------------------------------------ one step
    def sample_next(self, states: Tensor, forces: Tensor, k: int, rate: float,
                    generator: torch.Generator) -> Tensor:
        """``k`` noisy next states per environment; rate 0 gives ``k`` identical copies."""
        B, O = states.shape[0], self.num_objects
        if states.shape != (B, self.state_dim):
            raise ValueError(f"states must be (B, {self.state_dim}), got {tuple(states.shape)}")
        if forces.shape != (B, O, 3):
            raise ValueError(f"forces must be ({B}, {O}, 3), got {tuple(forces.shape)}")
        check_count(k, "k")
        spread = dropout_spread(rate)
        c = self.config
        roots = self.roots(states).unsqueeze(1).expand(B, k, O, ROOT_DIM)
        x, v = roots[..., :3], roots[..., 3:]
        force = forces.unsqueeze(1).expand(B, k, O, 3)
        if spread > 0 and "force" in c.dropout_modules:
            eps = _randn(generator, B, k, O, 3).to(force.device)
            force = force + c.force_spread * spread * force.norm(dim=-1, keepdim=True) * eps
        dt2 = c.dt ** 2
        accel = force / self._mass[:, None]
        accel = accel - self._gravity
        v_new = v + accel * dt2
        on_ground = (x[..., 2] <= self._radius + GROUND_TOL).unsqueeze(-1)
        keep = torch.where(on_ground, 1.0 - self._friction[:, None], 1.0)
        horizontal = self._horizontal
        v_new = v_new * (keep * horizontal + (1 - horizontal))
        x_new = self._ground(x + v_new)
        if c.collide and O > 1:
            x_new = self._contacts(x_new, v, spread, generator)
        v_out = x_new - x
        return torch.cat([x_new, v_out], -1).reshape(B, k, self.state_dim)

    def _ground(self, x: Tensor) -> Tensor:
        z = torch.maximum(x[..., 2], self._radius)
        return torch.cat([x[..., :2], z.unsqueeze(-1)], -1)

    def _contacts(self, x: Tensor, v_prev: Tensor, spread: float, generator: torch.Generator) -> Tensor:
        """Jacobi projection of overlapping pairs; ``x`` ``(B, k, O, 3)``."""
        c, O = self.config, self.num_objects
        reach = self._radius[:, None] + self._radius[None, :]              # (O, O)
        not_self = ~torch.eye(O, dtype=torch.bool, device=x.device)
        inv_m = 1.0 / self._mass
        share = inv_m[:, None] / (inv_m[:, None] + inv_m[None, :])          # i's part of pair (i, j)
        noise = None
        if spread > 0 and "collision" in c.dropout_modules:
            rel_speed = (v_prev[..., :, None, :] - v_prev[..., None, :, :]).norm(dim=-1)
            impact = rel_speed / (rel_speed + IMPACT_SPEED)                 # 0 at rest, -> 1 at impact
            eps = _randn(generator, *x.shape[:-2], O, O, 3).to(x.device)
            noise = c.collision_spread * spread * impact.unsqueeze(-1) * eps
        # a loop over solver iterations, each one vectorised over all pairs
        for _ in range(c.contact_iterations):
            d = x[..., :, None, :] - x[..., None, :, :]                     # from j to i
            dist = d.norm(dim=-1).clamp_min(DIST_EPS)
            overlap = ((reach - dist).clamp_min(0.0) * not_self)
            push = (overlap * share / dist).unsqueeze(-1) * d
            if noise is not None:
                push = push + overlap.unsqueeze(-1) * share.unsqueeze(-1) * noise
            x = self._ground(x + push.sum(-2))
        return x
