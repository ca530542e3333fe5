"""The manipulation tasks: the seed paper's two (section 4.3), three with room to learn and one
with an uncertain outcome; configs and goal tests.

- ``cube_push``: two rigid cubes; one horizontal force per cube; success when a cube's centre is
  inside a goal disc. 10 steps; dropout 0.1 on the force module.
- ``tower``: three stacked cubes and a ball; a 3-vector force on the ball; success when the
  middle cube has left the tower axis by more than ``goal_radius``. 15 steps; dropout on force
  and collision, annealed 0.1 -> 0 over 1200 PPO updates.
- ``cube_push_stop``: a cube must stop (< 5 mm per step) inside a 3 cm disc 0.15-0.3 m from the
  origin, within 20 steps (a full push overshoots, :func:`experiments.rl.planners.stop_push`
  brakes). Dropout 0.3 on force.
- ``cube_push_hold``: as ``cube_push_stop``, but stopped (< 3 mm per step) for 3 steps in a row.
- ``tower_aside``: the middle cube must reach a 4.5 cm disc 12-15 cm beside the tower, at least
  45 degrees off the ball-tower line, within 40 steps (the ball must go around,
  :func:`experiments.rl.planners.aside_push`). Dropout 0.3 on force and collision.
- ``tower_top_aside``: the top cube must come to rest (< 1 cm per step) in a 5 cm disc 12-16 cm
  beside the tower within 40 steps: an uncertain outcome, for planners that weigh futures.

A goal is a ``(B, 2)`` ground point (the disc centre, or the tower axis for ``displaced``).
Goal tests take root states with any leading dimensions. :func:`sample_goal` never returns a
goal met at reset: each starts ``goal_margin`` away (:func:`goal_clearance`). Also the training
modes (:data:`MODES`) and those without reward relaxation (:data:`UNRELAXED_MODES`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import Tensor

#: Size of the goal entry in observations: a point on the ground plane (x, y).
GOAL_DIM = 2
#: The training modes (``hrn_pyg.rl.ppo.mode_settings``), in the order of tables and figures.
MODES = ("deterministic", "action_noise", "stochastic", "stochastic_annealed", "stochastic_unrelaxed")
#: Modes whose environment takes one drawn sample as the next state and rewards only that sample
#: (no reward relaxation): the ablation that tells the stochastic model from the relaxed reward.
UNRELAXED_MODES = ("stochastic_unrelaxed",)
#: Goal kinds: a goal object inside a disc drawn around the origin (``region``) or beside the
#: goal object's start off the controlled object's line (``aside``), or farther than the radius
#: from its start (``displaced``).
GOAL_KINDS = ("region", "displaced", "aside")
#: Candidate goals drawn per environment for a ``region`` task; the first one far enough from
#: every goal object is kept. A fixed number, so the random stream does not depend on the scene.
GOAL_CANDIDATES = 128


@dataclass(frozen=True)
class TaskConfig:
    """One RL task.

    Attributes:
        name: task and scene name.
        max_steps: episode length limit; the episode is truncated when reached.
        num_objects: ``O``, movable objects in the scene (root states in the observation).
        controlled_objects: objects the action pushes, in action order.
        force_axes: force components the action sets per controlled object (0=x, 1=y, 2=z); the
            action has ``len(controlled_objects) * len(force_axes)`` entries.
        max_force: bound on every action entry (N): the top of the training scenes' ``force_range``,
            where the learned model is trusted.
        goal_kind: ``"region"`` (an object inside the disc), ``"aside"`` (a region beside the first
            goal object) or ``"displaced"`` (an object farther than ``goal_radius`` from the point).
        goal_objects: objects the goal test looks at; any one of them suffices.
        goal_radius: disc radius or displacement threshold, metres.
        goal_distance: range of the disc centre's distance from the origin (``region``) or from the
            first goal object (``aside``).
        goal_margin: metres every goal lies from being met at reset (:func:`goal_clearance`); 5 cm
            is five times the zero-action drift of the learned model over an episode.
        dropout_modules: HRN modules that get Monte Carlo dropout.
        dropout_rate: rate at the start of training (the ``stochastic`` modes).
        anneal_updates: PPO updates over which ``stochastic_annealed`` brings the rate to 0.
        num_samples: ``k``, futures sampled per step for reward relaxation.
        step_penalty: reward added on every step that does not reach the goal (<= 0).
        scene: the built-in scene file the task is played in; ``""``: the task's ``name``.
        goal_speed: if positive, a goal object counts only when slower than this (m per step).
        hold_steps: consecutive goal steps needed to succeed (1: the first one ends the episode).

    ``scene``, ``goal_speed`` and ``hold_steps`` are left out of :meth:`to_dict` at their defaults,
    so older run records still match.
    """

    name: str
    max_steps: int
    num_objects: int
    controlled_objects: tuple[int, ...]
    force_axes: tuple[int, ...]
    max_force: float
    goal_kind: str
    goal_objects: tuple[int, ...]
    goal_radius: float
    goal_distance: tuple[float, float] = (0.0, 0.0)
    goal_margin: float = 0.05
    dropout_modules: tuple[str, ...] = ("force",)
    dropout_rate: float = 0.1
    anneal_updates: int = 0
    num_samples: int = 5
    step_penalty: float = 0.0
    scene: str = ""
    goal_speed: float = 0.0
    hold_steps: int = 1

    def __post_init__(self) -> None:
        if self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {self.max_steps}")
        if not 1 <= self.hold_steps <= self.max_steps:
            raise ValueError(f"hold_steps must lie in [1, max_steps={self.max_steps}], "
                             f"got {self.hold_steps}")
        objs = set(self.controlled_objects) | set(self.goal_objects)
        if not self.controlled_objects or not self.goal_objects:
            raise ValueError("controlled_objects and goal_objects must not be empty")
        if min(objs) < 0 or max(objs) >= self.num_objects:
            raise ValueError(f"object indices must lie in [0, {self.num_objects})")
        if not self.force_axes or not set(self.force_axes) <= {0, 1, 2} or \
                len(set(self.force_axes)) != len(self.force_axes):
            raise ValueError(f"force_axes must be distinct entries of (0, 1, 2), got {self.force_axes}")
        if self.max_force <= 0 or self.goal_radius <= 0:
            raise ValueError("max_force and goal_radius must be positive")
        if self.goal_kind not in GOAL_KINDS:
            raise ValueError(f"goal_kind must be one of {GOAL_KINDS}, got {self.goal_kind!r}")
        if self.goal_speed < 0 or (self.goal_speed > 0 and self.goal_kind == "displaced"):
            raise ValueError(f"goal_speed must be >= 0 and only set for a region or aside goal, "
                             f"got {self.goal_speed} for {self.goal_kind!r}")
        lo, hi = self.goal_distance
        if not 0 <= lo <= hi:
            raise ValueError(f"goal_distance must be 0 <= low <= high, got {self.goal_distance}")
        if self.goal_kind == "aside" and lo < self.goal_radius + self.goal_margin:
            raise ValueError(f"an aside goal's disc must start clear of the goal object: "
                             f"goal_distance[0] ({lo}) < goal_radius + goal_margin "
                             f"({self.goal_radius + self.goal_margin:g})")
        if self.goal_margin < 0:
            raise ValueError(f"goal_margin must be >= 0, got {self.goal_margin}")
        if self.goal_kind == "displaced" and self.goal_margin >= self.goal_radius:
            raise ValueError(f"goal_margin ({self.goal_margin}) must be below goal_radius "
                             f"({self.goal_radius}) for a displaced goal")
        if not 0.0 <= self.dropout_rate < 1.0:
            raise ValueError(f"dropout_rate must be in [0, 1), got {self.dropout_rate}")
        if self.anneal_updates < 0 or self.num_samples < 1:
            raise ValueError("anneal_updates must be >= 0 and num_samples >= 1")
        if self.step_penalty > 0:
            raise ValueError(f"step_penalty must be <= 0, got {self.step_penalty}")

    @property
    def action_dim(self) -> int:
        return len(self.controlled_objects) * len(self.force_axes)

    @property
    def scene_name(self) -> str:
        """The scene the task is played in: ``scene``, else ``name``."""
        return self.scene or self.name

    def to_dict(self) -> dict:
        """The fields, without ``scene``, ``goal_speed`` and ``hold_steps`` at their defaults."""
        out = asdict(self)
        for key, default in (("scene", ""), ("goal_speed", 0.0), ("hold_steps", 1)):
            if out[key] == default:
                del out[key]
        return out


CUBE_PUSH = TaskConfig(
    name="cube_push", max_steps=10, num_objects=2, controlled_objects=(0, 1), force_axes=(0, 1),
    max_force=15.0, goal_kind="region", goal_objects=(0, 1), goal_radius=0.1,
    goal_distance=(0.15, 0.3), dropout_modules=("force",), dropout_rate=0.1, anneal_updates=1200,
)
TOWER = TaskConfig(
    name="tower", max_steps=15, num_objects=4, controlled_objects=(3,), force_axes=(0, 1, 2),
    max_force=8.0, goal_kind="displaced", goal_objects=(1,), goal_radius=0.1,
    dropout_modules=("force", "collision"), dropout_rate=0.1, anneal_updates=1200,
)
CUBE_PUSH_STOP = TaskConfig(
    name="cube_push_stop", scene="cube_push", max_steps=20, num_objects=2,
    controlled_objects=(0, 1), force_axes=(0, 1), max_force=15.0, goal_kind="region",
    goal_objects=(0, 1), goal_radius=0.03, goal_speed=0.005, goal_distance=(0.15, 0.3),
    goal_margin=0.12, dropout_modules=("force",), dropout_rate=0.3, anneal_updates=1200,
)
CUBE_PUSH_HOLD = TaskConfig(
    name="cube_push_hold", scene="cube_push", max_steps=20, num_objects=2,
    controlled_objects=(0, 1), force_axes=(0, 1), max_force=15.0, goal_kind="region",
    goal_objects=(0, 1), goal_radius=0.03, goal_speed=0.003, hold_steps=3,
    goal_distance=(0.15, 0.3), goal_margin=0.12, dropout_modules=("force",), dropout_rate=0.5,
    anneal_updates=1200,
)
TOWER_ASIDE = TaskConfig(
    name="tower_aside", scene="tower", max_steps=40, num_objects=4, controlled_objects=(3,),
    force_axes=(0, 1, 2), max_force=8.0, goal_kind="aside", goal_objects=(1,), goal_radius=0.045,
    goal_distance=(0.12, 0.15), dropout_modules=("force", "collision"), dropout_rate=0.3,
    anneal_updates=1200,
)
TOWER_TOP_ASIDE = TaskConfig(
    name="tower_top_aside", scene="tower", max_steps=40, num_objects=4, controlled_objects=(3,),
    force_axes=(0, 1, 2), max_force=8.0, goal_kind="aside", goal_objects=(2,), goal_radius=0.05,
    goal_speed=0.01, goal_distance=(0.12, 0.16), dropout_modules=("force", "collision"),
    dropout_rate=0.3, anneal_updates=1200,
)
TASKS: dict[str, TaskConfig] = {t.name: t for t in (CUBE_PUSH, TOWER, CUBE_PUSH_STOP, CUBE_PUSH_HOLD,
                                                     TOWER_ASIDE, TOWER_TOP_ASIDE)}


def get_task(task: str | TaskConfig) -> TaskConfig:
    if isinstance(task, TaskConfig):
        return task
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; known: {', '.join(TASKS)}")
    return TASKS[task]


def action_to_forces(task: TaskConfig, action: Tensor) -> Tensor:
    """Scatter an action into one force per object; uncontrolled objects get zero.

    **Shapes**: action ``(..., len(controlled) * len(axes))`` -> forces ``(..., O, 3)``.
    """
    if action.shape[-1] != task.action_dim:
        raise ValueError(f"action must end in {task.action_dim}, got shape {tuple(action.shape)}")
    lead = action.shape[:-1]
    parts = action.reshape(*lead, len(task.controlled_objects), len(task.force_axes))
    forces = action.new_zeros(*lead, task.num_objects, 3)
    obj = torch.tensor(task.controlled_objects, device=action.device)
    axes = torch.tensor(task.force_axes, device=action.device)
    forces[..., obj[:, None], axes[None, :]] = parts
    return forces


def sample_goal(task: TaskConfig, roots: Tensor, generator: torch.Generator) -> Tensor:
    """A goal for each environment from its initial root states ``(B, O, 6)`` -> ``(B, 2)``, never met
    at reset.

    ``region``: the first of :data:`GOAL_CANDIDATES` centres (distance uniform in
    ``goal_distance``, uniform direction) whose :func:`goal_clearance` exceeds ``goal_margin``;
    ``aside``: :func:`aside_goal`; ``displaced``: the first goal object's ground position. Drawn on
    ``generator``'s device with a fixed number of draws. ValueError if no such goal exists.
    """
    B = roots.shape[0]
    if task.goal_kind == "displaced":
        goal = roots[:, task.goal_objects[0], :2].clone()
        if not bool((goal_clearance(task, roots, goal) > task.goal_margin).all()):
            raise ValueError(f"task {task.name!r}: goal objects {task.goal_objects} start more than "
                             f"goal_radius - goal_margin = {task.goal_radius - task.goal_margin:g} m "
                             "apart, so the displaced goal would be met at reset")
        return goal
    if task.goal_kind == "aside":
        goal = aside_goal(task, roots, generator)
        if not bool((goal_clearance(task, roots, goal) > task.goal_margin).all()):
            raise ValueError(f"task {task.name!r}: a goal object starts within goal_radius + "
                             f"goal_margin = {task.goal_radius + task.goal_margin:g} m of its "
                             "aside goal, which would be (nearly) met at reset")
        return goal
    lo, hi = task.goal_distance
    shape, dev = (B, GOAL_CANDIDATES), generator.device
    angle = torch.rand(shape, generator=generator, device=dev) * 2 * math.pi
    dist = lo + (hi - lo) * torch.rand(shape, generator=generator, device=dev)
    candidates = torch.stack([dist * torch.cos(angle), dist * torch.sin(angle)], -1)  # (B, C, 2)
    candidates = candidates.to(roots.device)
    clear = goal_clearance(task, roots.unsqueeze(1), candidates) > task.goal_margin     # (B, C)
    if not bool(clear.any(-1).all()):
        raise ValueError(f"task {task.name!r}: none of {GOAL_CANDIDATES} goals drawn at "
                         f"{lo:g}-{hi:g} m from the origin lies more than goal_radius + goal_margin "
                         f"= {task.goal_radius + task.goal_margin:g} m from every goal object; the "
                         "reset positions leave no goal that needs acting")
    first = clear.to(torch.int8).argmax(-1)                                             # (B,)
    return candidates[torch.arange(B, device=roots.device), first]


def aside_goal(task: TaskConfig, roots: Tensor, generator: torch.Generator) -> Tensor:
    r"""Disc centres beside the first goal object, off the controlled object's line: ``(B, 2)``.

    With :math:`g` the first goal object's and :math:`c` the first controlled object's ground
    position and :math:`d = g - c`: :math:`g + s\, \rho\, e` with :math:`e = \hat x` if
    :math:`|d_x| < |d_y|` else :math:`\hat y`, :math:`s = \pm 1` and
    :math:`\rho \sim \mathcal U[\text{goal\_distance}]` drawn from ``generator``.
    """
    B = roots.shape[0]
    g = roots[:, task.goal_objects[0], :2]
    d = g - roots[:, task.controlled_objects[0], :2]
    dev = generator.device
    sign = torch.where(torch.rand(B, generator=generator, device=dev) < 0.5, -1.0, 1.0)
    lo, hi = task.goal_distance
    rho = lo + (hi - lo) * torch.rand(B, generator=generator, device=dev)
    along_x = d[:, 0].abs() < d[:, 1].abs()                                   # (B,)
    axis = torch.stack([along_x, ~along_x], -1).to(g.dtype)                  # (B, 2)
    return g + (sign * rho).to(g.device, g.dtype).unsqueeze(-1) * axis


def goal_clearance(task: TaskConfig, roots: Tensor, goal: Tensor) -> Tensor:
    r"""How far, metres, each state is from meeting the goal (``<= 0``: met, for ``region``).

    ``region`` and ``aside``: :math:`\min_{i \in G} \lVert x_i^{xy} - g \rVert - r`, with a
    ``goal_speed`` :math:`v_{\max} > 0`
    :math:`\min_{i \in G} \max(\lVert x_i^{xy} - g \rVert - r,\ \lVert v_i \rVert - v_{\max})`;
    ``displaced``: :math:`r - \max_{i \in G} \lVert x_i^{xy} - g \rVert` (met when ``< 0``).

    **Shapes**: roots ``(*lead, O, 6)``, goal broadcastable to ``(*lead, 2)`` -> ``(*lead,)``.
    """
    xy = roots[..., list(task.goal_objects), :2]                # (*lead, G, 2)
    dist = (xy - goal.unsqueeze(-2)).norm(dim=-1)               # (*lead, G)
    if task.goal_kind == "displaced":
        return task.goal_radius - dist.amax(-1)
    gap = dist - task.goal_radius
    if task.goal_speed > 0:
        speed = roots[..., list(task.goal_objects), 3:6].norm(dim=-1)   # (*lead, G)
        gap = torch.maximum(gap, speed - task.goal_speed)
    return gap.amin(-1)


def goal_reached(task: TaskConfig, roots: Tensor, goal: Tensor) -> Tensor:
    r"""Whether each state meets the task's goal.

    ``region`` and ``aside``: :math:`\exists i \in G: \lVert x_i^{xy} - g \rVert \le r` (and
    :math:`\lVert v_i \rVert \le v_{\max}` with a ``goal_speed``); ``displaced``:
    :math:`\exists i \in G: \lVert x_i^{xy} - g \rVert > r`.

    **Shapes**: roots ``(*lead, O, 6)``, goal broadcastable to ``(*lead, 2)`` -> ``(*lead,)`` bool.
    """
    xy = roots[..., list(task.goal_objects), :2]                # (*lead, G, 2)
    dist = (xy - goal.unsqueeze(-2)).norm(dim=-1)               # (*lead, G)
    if task.goal_kind == "displaced":
        return (dist > task.goal_radius).any(-1)
    inside = dist <= task.goal_radius
    if task.goal_speed > 0:
        inside &= roots[..., list(task.goal_objects), 3:6].norm(dim=-1) <= task.goal_speed
    return inside.any(-1)


def goal_streak(held: int | Tensor, reached: bool | Tensor) -> int | Tensor:
    r"""Goal-reaching steps in a row after one more step: :math:`c_{t+1} = (c_t + 1)\, h_t`, numbers or
    tensors of one shape; success when it reaches ``task.hold_steps`` (:func:`goal_held`)."""
    return (held + 1) * reached


def goal_held(task: TaskConfig, held: int | Tensor) -> bool | Tensor:
    """Whether a count of goal-reaching steps in a row (:func:`goal_streak`) ends the episode
    with success: ``held >= task.hold_steps``; a number or a tensor, like ``held``."""
    return held >= task.hold_steps

