"""The manipulation tasks: the seed paper's two (section 4.3), three with room to learn and one
with an uncertain outcome;
configs and goal tests.

``cube_push``: two rigid cubes that pass through each other; the agent pushes the cubes (one
horizontal force per cube) and succeeds when at least one cube's centre lies inside a goal
disc on the ground. At most 10 steps. Dropout 0.1 on the force module, held constant.

``tower``: three stacked cubes and a ball; the agent pushes only the ball (a 3-vector force, so
it can loft the ball) and succeeds when the middle cube's centre has left the tower axis by
more than ``goal_radius`` (one cube edge). At most 15 steps. Dropout on the force and
collision modules, annealed linearly 0.1 -> 0 over 1200 PPO updates.

``cube_push_stop`` (the cube_push scene and model): a cube must *stop* (slower than 5 mm per
step) inside a 3 cm disc drawn 0.15-0.3 m from the origin and at least 0.15 m from both cubes,
within 20 steps. A full-force push at the goal overshoots; a push that brakes in time
(:func:`experiments.rl.planners.stop_push`) succeeds. Dropout 0.3 on the force module.

``cube_push_hold`` (the cube_push scene and model): as ``cube_push_stop``, but the cube must
stay stopped (slower than 3 mm per step) inside the 3 cm disc for 3 steps in a row. A pass that
stops for one step does not count; the samples straddle the slower speed bound on most of the
steps spent holding, so reward relaxation acts on many steps of an episode, not only its last.

``tower_aside`` (the tower scene and model): the middle cube must reach a 4.5 cm disc 12-15 cm
beside the tower, on a side at least 45 degrees off the line from the ball to the tower, within
40 steps. Pushing the ball straight at the tower moves the stack along that line and never gets
there; driving the ball around the tower first (:func:`experiments.rl.planners.aside_push`) does.
Dropout 0.3 on the force and collision modules.

``tower_top_aside`` (the tower scene and model): the *top* cube must come to rest (slower than
1 cm per step) inside a 5 cm disc 12-16 cm beside the tower, off the line from the ball to the
tower, within 40 steps. The stack slides or topples when the ball strikes it, and where a
falling cube comes to rest is the part of the tower's physics the learned model is least sure
of: a task whose outcome is uncertain, for planners that weigh sampled futures.

A goal is a ``(B, 2)`` ground-plane point: the centre of the goal disc (``region``, ``aside``) or the
tower axis (``displaced``). Goal tests take root states with any leading dimensions, so one call
judges all ``k`` samples of all ``B`` environments.

**Goals need a policy.** :func:`sample_goal` never returns a goal that is already met at reset:
every goal starts at least ``goal_margin`` (5 cm, half a cube edge) away from being met
(:func:`goal_clearance`), whatever the training mode, since every mode draws its goals here.

Also the names of the five training modes (:data:`MODES`), shared by the PPO loop and the
summaries, and which of them train without reward relaxation (:data:`UNRELAXED_MODES`).
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
        force_axes: force components the action sets for each controlled object (0=x, 1=y, 2=z);
            the action has ``len(controlled_objects) * len(force_axes)`` entries.
        max_force: bound on every action entry, Newton; the top of the random-force range
            the task's training scenes were generated with (the ``force_range`` setting of the
            scene files ``cube_push.toml``, 15 N, and ``tower.toml``, 8 N), because the
            learned model is only trusted inside the forces it was trained on.
        goal_kind: ``"region"`` (an object inside the goal disc) or ``"displaced"`` (an object
            farther than ``goal_radius`` from the goal point).
        goal_objects: objects the goal test looks at; any one of them suffices.
        goal_radius: disc radius or displacement threshold, metres.
        goal_distance: for ``region``, the disc centre is drawn at this range of distances from
            the origin, in a uniformly random direction.
        goal_margin: how far, metres, every goal lies from being met at reset
            (:func:`goal_clearance` ``> goal_margin``): ``region`` discs are drawn at least
            ``goal_radius + goal_margin`` from every goal object; a ``displaced`` goal object must
            start within ``goal_radius - goal_margin`` of the goal point. The default, 5 cm (half
            a cube edge), is five times what resting cubes drift under a zero action in a whole
            episode of the learned model (``hrn_pyg/checkpoints/cube_push.pt``: at most 1.1 cm
            over 10 zero-force steps, any of 5 samples, dropout 0 or 0.1, 16 pool scenes), so no
            goal is met without acting, yet it takes only a disc of 0.15 m radius around each
            cube out of the goal ring.
        dropout_modules: HRN modules that get Monte Carlo dropout.
        dropout_rate: rate at the start of training (the ``stochastic`` modes).
        anneal_updates: PPO updates over which ``stochastic_annealed`` brings the rate to 0.
        num_samples: ``k``, futures sampled per step for reward relaxation.
        step_penalty: reward added on every step that does not reach the goal (<= 0).
        scene: the scene the task is played in (a built-in scene file, ``hrn_pyg.data.scene_file``
            ``make_scene``) and the point-mass layout; ``""``: the task's ``name``. Several tasks
            may share one scene (and so one trained model).
        goal_speed: for ``region`` and ``aside`` goals, if positive, a goal object counts only
            when it is also slower than this, metres per step (the root velocity is the
            per-step displacement): the object must *stop* in the disc, not pass through it.
            0: no speed condition.
        hold_steps: consecutive steps the goal test must hold for the episode to succeed and
            end; 1: the first goal-reaching step ends it (the seed paper's tasks). With more,
            the agent must keep the goal object in the goal, not touch it once.

    ``aside`` goals (:func:`sample_goal`): a disc of ``goal_radius`` for the goal objects whose
    centre lies ``goal_distance[0]`` to ``goal_distance[1]`` from the first goal object's start,
    along one of the two world axes (``±x``, ``±y``) that are 45-135 degrees off the line from
    the first controlled object to the first goal object: pushing the controlled object
    straight at the goal object moves it along that line, away from the disc.

    ``scene``, ``goal_speed`` and ``hold_steps`` are left out of :meth:`to_dict` at their
    defaults, so that the records of runs made before they existed still match.
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
    """A goal for each environment from its initial root states ``(B, O, 6)`` -> ``(B, 2)``,
    never met at reset.

    ``region``: :data:`GOAL_CANDIDATES` disc centres per environment, each at a distance drawn
    uniformly from ``goal_distance`` in a uniform direction; the first whose
    :func:`goal_clearance` exceeds ``goal_margin`` (farther than ``goal_radius + goal_margin``
    from every goal object) is kept. ``displaced``: the current ground-plane position of the
    (first) goal object. Drawn on ``generator``'s device (always the same number of draws),
    returned on ``roots``'.

    Raises ``ValueError`` if an environment has no such goal: every candidate lies near a goal
    object (a ``goal_distance`` range that the reset positions cover), or a displaced goal's
    objects start apart.
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
    position and :math:`d = g - c`, the sideways axis is :math:`e = \hat x` if
    :math:`|d_x| < |d_y|` else :math:`\hat y` (the world axis at least 45 degrees off
    :math:`d`), and the centre is :math:`g + s\, \rho\, e` with a sign
    :math:`s = \pm 1` and a distance :math:`\rho \sim \mathcal U[\text{goal\_distance}]`, two
    draws per environment from ``generator`` (on its device), returned on ``roots``' device.
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

    ``region`` and ``aside``: :math:`\min_{i \in G} \lVert x_i^{xy} - g \rVert - r` (distance
    of the nearest goal object to the disc's rim), with a ``goal_speed`` :math:`v_{\max} > 0`
    :math:`\min_{i \in G} \max(\lVert x_i^{xy} - g \rVert - r,\ \lVert v_i \rVert - v_{\max})`;
    ``displaced``: :math:`r - \max_{i \in G} \lVert x_i^{xy} - g
    \rVert` (room left before an object leaves the disc). :func:`goal_reached` is true exactly
    when the clearance is ``<= 0`` (``region``) or ``< 0`` (``displaced``).

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

    ``region`` and ``aside``: :math:`\exists i \in G: \lVert x_i^{xy} - g \rVert \le r`
    (and :math:`\lVert v_i \rVert \le v_{\max}` with a ``goal_speed`` :math:`v_{\max} > 0`);
    ``displaced``: :math:`\exists i \in G: \lVert x_i^{xy} - g \rVert > r`.

    **Shapes**: roots ``(*lead, O, 6)``, goal broadcastable to ``(*lead, 2)`` (e.g. ``(B, 1, 2)``
    against ``(B, k, O, 6)``) -> ``(*lead,)`` bool.
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
    r"""Goal-reaching steps in a row after one more step: :math:`c_{t+1} = (c_t + 1)\, h_t`.

    ``held`` the count so far and ``reached`` whether this step met the goal, as numbers or as
    tensors of one shape (int and bool); the episode of a task succeeds when the count reaches
    ``task.hold_steps`` (:func:`goal_held`). The one rule the environment and the pybullet
    judges (:mod:`hrn_pyg.rl.evaluate`) share.
    """
    return (held + 1) * reached


def goal_held(task: TaskConfig, held: int | Tensor) -> bool | Tensor:
    """Whether a count of goal-reaching steps in a row (:func:`goal_streak`) ends the episode
    with success: ``held >= task.hold_steps``; a number or a tensor, like ``held``."""
    return held >= task.hold_steps

