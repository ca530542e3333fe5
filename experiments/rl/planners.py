"""Scripted planners: the best known policy of a task, whose episode length sets its thresholds.

A planner maps an :class:`~hrn_pyg.rl.env.HRNEnv` observation ``(B, O*6 + 2)`` (root state
``[x, y, z, vx, vy, vz]`` per object, velocities in metres per step, then the goal ``(x, y)``)
to an action ``(B, A)`` inside the force bounds, closed loop, with no state of its own. All
forces are horizontal and at most ``task.max_force`` in magnitude (the forces the shipped models
were trained on: ``hrn_pyg.data.builtin_scenes`` ``force_range``), never the corners of the
action box.

- :func:`greedy_push`: push every controlled object at full force straight at its target (the
  goal disc for ``region`` goals, the first goal object otherwise). The baseline a task with
  room to learn must beat.
- :func:`stop_push` (``cube_push_stop``, ``cube_push_hold``): a saturated PD law on the cube
  nearest the goal,

  .. math:: F = \\operatorname{sat}_{F_{\\max}}\\big(k_p (g - x) - k_d v\\big),

  which accelerates, coasts and brakes so the cube stops in the small disc.
- :func:`aside_push` (``tower_aside``): drive the ball around the tower to the approach point
  :math:`A = c - R\\,\\hat u` behind the tower base :math:`c` (object 0) along the direction
  :math:`\\hat u` from the middle cube to the goal (the same PD law), then push along
  :math:`\\hat u` with a lateral correction, so the stack is shoved toward the disc.

:func:`planner_policy` wraps a planner as a TensorDict module (``observation`` -> ``action``)
for :func:`hrn_pyg.rl.evaluate.record_episodes` and the pybullet replay;
:data:`PLANNERS` names each new task's planner.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict.nn import TensorDictModule
from torch import Tensor, nn

from hrn_pyg.rl.tasks import GOAL_DIM, TaskConfig, get_task

#: A planner: ``(task, observation (B, O*6 + 2)) -> action (B, A)``.
Planner = Callable[[TaskConfig, Tensor], Tensor]


@dataclass(frozen=True)
class PDGains:
    """Gains of the saturated PD law :math:`F = \\operatorname{sat}(k_p e - k_d v)`.

    Attributes:
        kp: Newton per metre of position error.
        kd: Newton per (metre per step) of velocity.
    """

    kp: float
    kd: float

    def __post_init__(self) -> None:
        if self.kp <= 0 or self.kd < 0:
            raise ValueError(f"need kp > 0 and kd >= 0, got {self.kp}, {self.kd}")


#: ``stop_push`` gains (tuned on the shipped cube_push model, pool scenes, rate 0)
STOP_GAINS = PDGains(kp=300.0, kd=700.0)
#: ``aside_push`` gains for driving the ball to the approach point
ASIDE_GAINS = PDGains(kp=120.0, kd=300.0)
#: ``aside_push``: approach point distance behind the tower base, metres
ASIDE_BACKOFF = 0.24
#: ``aside_push``: the ball pushes once it lies behind the base (projection below this) and
#: within this lateral distance of the push line, metres
ASIDE_BEHIND, ASIDE_LATERAL = -0.1, 0.06


def split_observation(task: TaskConfig, observation: Tensor) -> tuple[Tensor, Tensor]:
    """``(B, O*6 + 2)`` -> roots ``(B, O, 6)`` and goal ``(B, 2)``; raises on a wrong width."""
    width = task.num_objects * 6 + GOAL_DIM
    if observation.shape[-1] != width:
        raise ValueError(f"observation must end in {width} for task {task.name!r}, "
                         f"got {tuple(observation.shape)}")
    roots = observation[..., :-GOAL_DIM].reshape(*observation.shape[:-1], task.num_objects, 6)
    return roots, observation[..., -GOAL_DIM:]


def saturate(force: Tensor, bound: float) -> Tensor:
    """Scale each horizontal force ``(..., 2)`` down to magnitude at most ``bound``."""
    norm = force.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    return force * (bound / norm).clamp(max=1.0)


def _unit(v: Tensor) -> Tensor:
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-9)


def to_action(task: TaskConfig, forces_xy: Tensor) -> Tensor:
    """Horizontal forces per controlled object ``(B, C, 2)`` -> the task's action ``(B, A)``
    (a z entry, when the task has one, is 0)."""
    B = forces_xy.shape[0]
    out = forces_xy.new_zeros(B, len(task.controlled_objects), len(task.force_axes))
    for j, axis in enumerate(task.force_axes):
        if axis < 2:
            out[..., j] = forces_xy[..., axis]
    return out.reshape(B, task.action_dim)


def greedy_push(task: str | TaskConfig, observation: Tensor) -> Tensor:
    """Every controlled object pushed at ``max_force`` straight at the target: the goal point
    for ``region`` goals, the first goal object's position for ``displaced`` and ``aside``."""
    task = get_task(task)
    roots, goal = split_observation(task, observation)
    pos = roots[:, list(task.controlled_objects), :2]                         # (B, C, 2)
    target = goal if task.goal_kind == "region" else roots[:, task.goal_objects[0], :2]
    return to_action(task, _unit(target.unsqueeze(1) - pos) * task.max_force)


def pd_force(pos: Tensor, vel: Tensor, target: Tensor, gains: PDGains, bound: float) -> Tensor:
    """:math:`\\operatorname{sat}_{\\text{bound}}(k_p (\\text{target} - x) - k_d v)`, all ``(..., 2)``."""
    return saturate(gains.kp * (target - pos) - gains.kd * vel, bound)


def stop_push(task: str | TaskConfig, observation: Tensor, gains: PDGains = STOP_GAINS) -> Tensor:
    """The PD law on the goal object nearest the goal (the others get no force); needs a task
    whose controlled objects are its goal objects (``cube_push`` and its variants)."""
    task = get_task(task)
    if task.goal_kind == "displaced" or set(task.goal_objects) - set(task.controlled_objects):
        raise ValueError(f"stop_push needs a region goal on controlled objects, not task {task.name!r}")
    roots, goal = split_observation(task, observation)
    ctrl = list(task.controlled_objects)
    pos, vel = roots[:, ctrl, :2], roots[:, ctrl, 3:5]                        # (B, C, 2)
    dist = (pos - goal.unsqueeze(1)).norm(dim=-1)                             # (B, C)
    is_goal = torch.tensor([o in task.goal_objects for o in ctrl], device=pos.device)
    nearest = dist.masked_fill(~is_goal, float("inf")).argmin(-1)             # (B,)
    force = pd_force(pos, vel, goal.unsqueeze(1), gains, task.max_force)
    chosen = torch.arange(len(ctrl), device=pos.device) == nearest.unsqueeze(-1)  # (B, C)
    return to_action(task, force * chosen.unsqueeze(-1))


def aside_push(task: str | TaskConfig, observation: Tensor, gains: PDGains = ASIDE_GAINS,
               backoff: float = ASIDE_BACKOFF) -> Tensor:
    r"""Ball around the tower, then a push toward the goal (``tower_aside``).

    With base :math:`c` (object 0), middle cube :math:`m` (the first goal object), ball
    :math:`b`, :math:`\hat u = (g - m)/\lVert g - m \rVert`, :math:`p = b - c`,
    :math:`s = p \cdot \hat u` and lateral offset :math:`l = p - s \hat u`: if
    :math:`s < -0.1` and :math:`\lVert l \rVert < 0.06` the ball is pushed with
    :math:`F_{\max}\, \widehat{(\hat u - 10\, l - 20\, v_\perp)}` (:math:`v_\perp`: the ball's
    velocity across :math:`\hat u`, metres per step), otherwise it is driven to
    :math:`A = c - R\hat u` by the PD law.
    """
    task = get_task(task)
    if task.goal_kind == "region" or len(task.controlled_objects) != 1:
        raise ValueError(f"aside_push needs one controlled object and a goal object, not task {task.name!r}")
    roots, goal = split_observation(task, observation)
    ball = task.controlled_objects[0]
    b, v = roots[:, ball, :2], roots[:, ball, 3:5]
    c, m = roots[:, 0, :2], roots[:, task.goal_objects[0], :2]
    u = _unit(goal - m)
    p = b - c
    s = (p * u).sum(-1, keepdim=True)
    lateral = p - s * u
    v_perp = v - (v * u).sum(-1, keepdim=True) * u
    pushing = (s < ASIDE_BEHIND) & (lateral.norm(dim=-1, keepdim=True) < ASIDE_LATERAL)
    push = _unit(u - 10.0 * lateral - 20.0 * v_perp) * task.max_force
    drive = pd_force(b, v, c - backoff * u, gains, task.max_force)
    return to_action(task, torch.where(pushing, push, drive).unsqueeze(1))


#: the best known policy of each task with room to learn
PLANNERS: dict[str, Planner] = {"cube_push_stop": stop_push, "cube_push_hold": stop_push,
                                "tower_aside": aside_push}


#: the thresholds are these multiples of the planner's mean in-model length ``L``: a run has
#: learned the task when its average episode length is at most ``1.5 L``, and matches the best
#: known policy at ``1.1 L``
THRESHOLD_FACTORS = {"learned": 1.5, "near_planner": 1.1}
#: the planner's mean episode length in the learned model at rate 0 (64 episodes from the RL
#: pool, failures counted as ``max_steps``), measured by ``experiments/rl/score_planners.py`` and kept in
#: ``benchmarks/results/planners_<task>.json``
PLANNER_LENGTHS: dict[str, float] = {"cube_push_stop": 9.9375, "cube_push_hold": 12.109375,
                                     "tower_aside": 21.484375}


def length_thresholds(planner_length: float,
                      factors: dict[str, float] = THRESHOLD_FACTORS) -> dict[str, float]:
    """Episode-length thresholds from a planner's mean length :math:`L`:
    ``{name: f L}`` for each factor (rounded to 0.01 step), e.g. ``learned`` = :math:`1.5 L`.
    Raises on a non-positive length or factor."""
    if not planner_length > 0:
        raise ValueError(f"planner_length must be positive, got {planner_length}")
    if any(not f > 0 for f in factors.values()):
        raise ValueError(f"factors must be positive, got {factors}")
    return {name: round(f * planner_length, 2) for name, f in factors.items()}


def task_thresholds(task: str | TaskConfig) -> dict[str, float]:
    """:func:`length_thresholds` of a task's measured planner length (:data:`PLANNER_LENGTHS`)."""
    task = get_task(task)
    if task.name not in PLANNER_LENGTHS:
        raise ValueError(f"no measured planner length for task {task.name!r}; known: "
                         f"{', '.join(PLANNER_LENGTHS)}")
    return length_thresholds(PLANNER_LENGTHS[task.name])


class _PlannerNet(nn.Module):
    def __init__(self, task: TaskConfig, planner: Planner) -> None:
        super().__init__()
        self.task, self.planner = task, planner

    def forward(self, observation: Tensor) -> Tensor:
        return self.planner(self.task, observation)


def planner_policy(task: str | TaskConfig, planner: Planner | None = None) -> TensorDictModule:
    """A planner (default: the task's in :data:`PLANNERS`) as a policy module reading
    ``observation`` and writing ``action``."""
    task = get_task(task)
    if planner is None:
        if task.name not in PLANNERS:
            raise ValueError(f"no planner for task {task.name!r}; known: {', '.join(PLANNERS)}")
        planner = PLANNERS[task.name]
    return TensorDictModule(_PlannerNet(task, planner), in_keys=["observation"], out_keys=["action"])
