r"""Model-predictive control through the stochastic HRN: a cross-entropy planner that scores
every candidate action sequence on K Monte Carlo dropout futures, judged closed loop in pybullet.

**One planning step.** From the current state :math:`s_0` (leaf positions at :math:`t-2, t-1,
t`) and the goal :math:`g`, a candidate is an action sequence :math:`a_{0:H}` of shape
``(H, A)`` inside the force bounds. All ``N`` candidates and all ``K`` futures are one batched
graph of ``N K`` copies of the scene per model step (:func:`rollout_futures`); future :math:`j`
of every candidate steps with the same dropout masks :math:`m^{(j)}_h` (common random numbers:
candidates differ only by their actions, not by their luck), fresh masks at every model step:

.. math::
    s^{(i,j)}_{h+1} = f_\theta\big(s^{(i,j)}_h, a^{(i)}_h; m^{(j)}_h\big), \qquad
    R_{ij} = \sum_{h=1}^{H} \gamma^{h-1} r\big(s^{(i,j)}_h\big), \qquad
    r(s) = -\max\big(c_g(s), 0\big) - w\, d_{\text{reach}}(s)

with :math:`c_g` the task's goal clearance (:func:`~hrn_pyg.rl.tasks.goal_clearance`: metres
from meeting the goal, the speed bound included) and, for tasks whose goal object is not pushed
directly (``tower``, ``tower_aside``, ``tower_top_aside``), :math:`d_{\text{reach}}` the length of
the route the pushed object still has to travel (:func:`route_length`): around the goal object
to the approach point behind it, then through it to where it stands when the goal object sits on
the goal; :math:`w` = ``reach_weight``. With ``action_repeat`` :math:`r > 1` each of the ``H``
planned actions is held for :math:`r` model steps (the sum runs over :math:`H r` steps) and the
closed loop plans once per held action.

**Scores** of a candidate from its return row :math:`R_{i\cdot}` (:func:`score_returns`):

- ``deterministic``: the model without dropout, :math:`K = 1`, :math:`S_i = R_{i1}`;
- ``mean``: :math:`S_i = \frac1K \sum_j R_{ij}` at the sampling rate :math:`p` (the model's
  calibrated rate when its checkpoint has one, else the task's);
- ``risk``: :math:`S_i = \bar R_i - c\, \sigma_i` (mean minus ``risk_std`` times the standard
  deviation over the K futures, population form), which prefers a sequence whose futures agree.

**Cross-entropy method** (:func:`cem`, TorchRL's ``CEMPlanner`` in spirit, written out for the
K futures per candidate with shared masks), warm-started from the last plan shifted by one step;
then optionally **gradient refinement** (:func:`refine`) through the differentiable rollout. The
**closed loop** (:func:`plan_episode`) plans from pybullet's own leaves at every control step and
judges the goal there.

**Shapes:** state ``(S,)``; actions ``(N, H, A)``; roots ``(N, K, H, O, 6)``; returns
``(N, K)``; scores ``(N,)``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch
from torch import Tensor

from hrn_pyg.commands.plan import add_arguments, add_search_arguments  # noqa: F401  the command's arguments, here too
from hrn_pyg.data.graph import HISTORY
from hrn_pyg.rl.hrn_dynamics import HRNDynamics
from hrn_pyg.rl.tasks import (
    TaskConfig,
    action_to_forces,
    get_task,
    goal_clearance,
    sample_goal,
)
from hrn_pyg.sampling.sample import draw_masks
from hrn_pyg.utils.checks import check_rate
from hrn_pyg.utils.device import resolve_device
from hrn_pyg.utils.files import atomic_write_json

#: the ways to score a candidate from its K futures
SCORES = ("deterministic", "mean", "risk")
#: the reach route (:func:`route_length`), metres: the approach point lies this far behind the goal
#: object, away from the goal (the scripted ``aside_push`` of ``experiments/rl/planners.py``
#: drives the ball to the same point before it pushes)
APPROACH_DISTANCE = 0.24
#: the pushed object's centre lies this far from the goal object's axis when it touches the
#: stack: a cube's half edge plus the ball's radius
CONTACT_DISTANCE = 0.125
#: the route keeps this far from the goal object's axis until it is behind the object: past the
#: corner of a cube (half diagonal 7.1 cm) plus the ball's radius, with 2.5 cm to spare
CLEARANCE_RADIUS = 0.17
#: the pushed object is behind the goal object when it lies more than ``BEHIND`` behind it along
#: the push direction and at most ``LATERAL`` off the push line (``aside_push``'s test)
BEHIND, LATERAL = 0.1, 0.06

#: ``score_fn(actions (N, H, A)) -> scores (N,)``, higher is better
ScoreFn = Callable[[Tensor], Tensor]


@dataclass(frozen=True)
class PlannerConfig:
    """A model-predictive planner's settings.

    Attributes:
        score: how a candidate is scored over its futures (:data:`SCORES`).
        candidates: ``N``, action sequences per CEM iteration.
        elites: ``E``, best candidates that refit the sampling distribution.
        iterations: CEM iterations per control step.
        horizon: ``H``, model steps a candidate plans ahead.
        futures: ``K``, dropout futures per candidate for ``mean`` and ``risk`` (``deterministic``
            uses one, at rate 0).
        rate: dropout rate of the futures; None: the model's calibrated rate, else the task's.
        risk_std: ``c`` of the ``risk`` score, mean minus ``c`` standard deviations.
        init_std: the first sampling spread, a fraction of ``max_force``.
        min_std: the smallest sampling spread, a fraction of ``max_force``.
        discount: ``gamma`` of the planning return.
        reach_weight: ``w``, weight of the pushed object's distance to the push point (tasks
            whose goal objects are not pushed directly).
        refine_steps: Adam steps of gradient refinement after the search (0: none).
        refine_lr: Adam's step size, a fraction of ``max_force``.
        action_repeat: ``r``, model steps each planned action is held; a plan covers ``H r``
            model steps and the closed loop plans again every ``r`` control steps.
        horizontal: forces in the ground plane only, each controlled object's at most
            ``max_force`` in magnitude (the pushes the scenes were generated with); False: every
            action entry inside ``[-max_force, max_force]``.
        route_proposal: where the reach route applies, the first CEM draw also holds the
            full-force push along the route (:func:`route_push`) as a candidate.
    """

    score: str = "deterministic"
    candidates: int = 16
    elites: int = 4
    iterations: int = 2
    horizon: int = 6
    futures: int = 4
    rate: float | None = None
    risk_std: float = 1.0
    init_std: float = 0.5
    min_std: float = 0.05
    discount: float = 1.0
    reach_weight: float = 0.2
    refine_steps: int = 0
    refine_lr: float = 0.1
    action_repeat: int = 1
    horizontal: bool = False
    route_proposal: bool = False

    def __post_init__(self) -> None:
        if self.score not in SCORES:
            raise ValueError(f"score must be one of {SCORES}, got {self.score!r}")
        for name in ("candidates", "elites", "iterations", "horizon", "futures", "action_repeat"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.elites > self.candidates:
            raise ValueError(f"elites ({self.elites}) must not exceed candidates ({self.candidates})")
        if self.rate is not None:
            check_rate(self.rate)
        if self.risk_std < 0 or self.init_std <= 0 or self.min_std < 0 or self.refine_steps < 0:
            raise ValueError("need risk_std >= 0, init_std > 0, min_std >= 0 and refine_steps >= 0")
        if not 0 < self.discount <= 1 or self.refine_lr <= 0 or self.reach_weight < 0:
            raise ValueError("need 0 < discount <= 1, refine_lr > 0 and reach_weight >= 0")

    @property
    def num_futures(self) -> int:
        """Futures simulated per candidate: 1 for ``deterministic``, else ``futures``."""
        return 1 if self.score == "deterministic" else self.futures


def score_returns(returns: Tensor, score: str, risk_std: float = 1.0) -> Tensor:
    """A candidate's score from its returns over K futures, ``(N, K)`` -> ``(N,)``:
    ``deterministic`` the first column, ``mean`` the mean, ``risk`` the mean minus ``risk_std``
    population standard deviations (so ``risk <= mean``, equal when the futures agree)."""
    if returns.dim() != 2:
        raise ValueError(f"returns must be (N, K), got {tuple(returns.shape)}")
    if score == "deterministic":
        return returns[:, 0]
    if score == "mean":
        return returns.mean(1)
    if score == "risk":
        return returns.mean(1) - risk_std * returns.std(1, correction=0)
    raise ValueError(f"score must be one of {SCORES}, got {score!r}")


def push_direction(task: TaskConfig, roots: Tensor, goal: Tensor) -> Tensor:
    r""":math:`\hat u = (g - x_g) / \lVert g - x_g \rVert`, the ground direction from the first goal
    object :math:`x_g` to the goal. **Shapes:** roots ``(*, O, 6)``, goal ``(*, 2)`` -> ``(*, 2)``."""
    away = goal - roots[..., task.goal_objects[0], :2]
    return away / away.norm(dim=-1, keepdim=True).clamp_min(1e-6)


def detour_length(start: Tensor, end: Tensor, centre: Tensor, radius: float) -> Tensor:
    r"""The shortest ground path from ``start`` to ``end`` that stays out of the disc of ``radius``
    around ``centre``: the straight segment when it misses the disc, else the two tangents and
    the arc between them, :math:`\sqrt{p^2 - \rho^2} + \sqrt{q^2 - \rho^2} + \rho\,(\theta -
    \arccos\frac{\rho}{p} - \arccos\frac{\rho}{q})` (:math:`p, q` the ends' distances from the
    centre, at least :math:`\rho`; :math:`\theta` the angle between them).
    **Shapes:** all ``(*, 2)`` (broadcast) -> ``(*,)``."""
    p, q = start - centre, end - centre
    seg = q - p
    t = (-(p * seg).sum(-1) / (seg * seg).sum(-1).clamp_min(1e-12)).clamp(0.0, 1.0)
    closest = (p + t.unsqueeze(-1) * seg).norm(dim=-1)
    straight = seg.norm(dim=-1)
    # tangent lengths and angles in atan2 form: exact and with finite gradients at the ends
    tp = (p.norm(dim=-1).clamp_min(radius) ** 2 - radius**2).clamp_min(1e-12).sqrt()
    tq = (q.norm(dim=-1).clamp_min(radius) ** 2 - radius**2).clamp_min(1e-12).sqrt()
    cross = (p[..., 0] * q[..., 1] - p[..., 1] * q[..., 0]).abs()
    theta = torch.atan2(cross, (p * q).sum(-1))
    arc = (theta - torch.atan2(tp, torch.tensor(radius)) - torch.atan2(tq, torch.tensor(radius))).clamp_min(0.0)
    around = tp + tq + radius * arc
    return torch.where(closest >= radius, straight, around)


def route_object(task: TaskConfig, roots: Tensor) -> int:
    """The object the reach route runs around and pushes: of the objects not controlled, the
    lowest in ``roots`` ``(O, 6)`` (the tower's base, which the rolling ball meets; the goal
    object may sit on it)."""
    free = [o for o in range(task.num_objects) if o not in task.controlled_objects]
    return free[int(roots[free, 2].argmin())]


def route_length(task: TaskConfig, roots: Tensor, goal: Tensor, direction: Tensor,
                 pushed: int | None = None) -> Tensor:
    r"""How far the pushed object :math:`b` still has to travel to bring the goal object onto
    the goal :math:`g` by pushing the object :math:`x_g` (``pushed``, default the first goal
    object; :func:`route_object` for a stack) along :math:`\hat u` (``direction``, see
    :func:`push_direction`), the route of the scripted ``aside_push``:

    - behind the goal object (:math:`s = (b - x_g)\cdot\hat u < -` :data:`BEHIND` and at most
      :data:`LATERAL` off the line): straight to the end point :math:`T = g - D\hat u`, where it
      stands when the goal object sits on the goal (:math:`D` = :data:`CONTACT_DISTANCE`);
    - elsewhere: around the goal object (outside :data:`CLEARANCE_RADIUS`,
      :func:`detour_length`) to the approach point :math:`A = x_g - R\hat u`
      (:data:`APPROACH_DISTANCE`), then :math:`\lVert T - A \rVert`.

    **Shapes:** roots ``(*, O, 6)``, goal and direction broadcastable to ``(*, 2)`` -> ``(*,)``.
    """
    ball = roots[..., task.controlled_objects[0], :2]
    obj = roots[..., task.goal_objects[0] if pushed is None else pushed, :2]
    u = direction.expand_as(obj)
    rel = ball - obj
    along = (rel * u).sum(-1)
    lateral = (rel - along.unsqueeze(-1) * u).norm(dim=-1)
    end = goal - CONTACT_DISTANCE * u
    approach = obj - APPROACH_DISTANCE * u
    behind = (along < -BEHIND) & (lateral < LATERAL)
    direct = (ball - end).norm(dim=-1)
    around = detour_length(ball, approach, obj, CLEARANCE_RADIUS) + (end - approach).norm(dim=-1)
    return torch.where(behind, direct, around)


def uses_route(task: TaskConfig) -> bool:
    """Whether the task's planning reward has the reach route: no goal object is pushed directly."""
    return not set(task.goal_objects) & set(task.controlled_objects)


def route_push(task: TaskConfig, roots: Tensor, goal: Tensor, direction: Tensor,
               pushed: int | None = None) -> Tensor:
    r"""The action ``(A,)`` that pushes the (first) controlled object at ``max_force`` down the
    reach route: along :math:`-\nabla_b` :func:`route_length` (toward the end point when behind
    the goal object, else toward the approach point or along the tangent around the object),
    horizontal. **Shapes:** roots ``(O, 6)``, goal and direction ``(2,)`` -> ``(A,)``."""
    with torch.enable_grad():
        ball = roots[task.controlled_objects[0], :2].detach().clone().requires_grad_(True)
        moved = roots.detach().clone()
        moved = torch.cat([moved[:task.controlled_objects[0]],
                           torch.cat([ball, moved[task.controlled_objects[0], 2:]]).unsqueeze(0),
                           moved[task.controlled_objects[0] + 1:]])
        (grad,) = torch.autograd.grad(route_length(task, moved, goal, direction, pushed), ball)
    push = -grad / grad.norm().clamp_min(1e-9) * task.max_force
    force = torch.zeros(task.num_objects, 3)
    force[task.controlled_objects[0], :2] = push
    axes = list(task.force_axes)
    return force[list(task.controlled_objects)][:, axes].reshape(task.action_dim)


def planning_rewards(task: TaskConfig, roots: Tensor, goal: Tensor, reach_weight: float,
                     direction: Tensor | None = None, pushed: int | None = None) -> Tensor:
    r"""The per-step planning reward :math:`-\max(c_g, 0) - w\, d_{\text{reach}}` (module
    docstring); the reach term (:func:`route_length` along ``direction``, default
    :func:`push_direction` of each state, around ``pushed``) only where no goal object is pushed
    directly.

    **Shapes:** roots ``(*, O, 6)``, goal and direction broadcastable to ``(*, 2)`` -> ``(*,)``.
    """
    reward = -goal_clearance(task, roots, goal).clamp_min(0.0)
    if reach_weight > 0 and uses_route(task):
        if direction is None:
            direction = push_direction(task, roots, goal)
        reward = reward - reach_weight * route_length(task, roots, goal, direction, pushed)
    return reward


def project_actions(task: TaskConfig, actions: Tensor, horizontal: bool) -> Tensor:
    """Actions ``(..., A)`` into the planner's force bounds: each entry clipped to
    ``[-max_force, max_force]``, or with ``horizontal`` the vertical entries zeroed and each
    controlled object's horizontal force scaled down to at most ``max_force`` in magnitude."""
    if not horizontal:
        return actions.clamp(-task.max_force, task.max_force)
    parts = actions.reshape(*actions.shape[:-1], len(task.controlled_objects), len(task.force_axes))
    keep = torch.tensor([axis < 2 for axis in task.force_axes], dtype=actions.dtype)
    parts = parts * keep
    norm = parts.norm(dim=-1, keepdim=True)
    parts = parts * (task.max_force / norm.clamp_min(1e-9)).clamp(max=1.0)
    return parts.reshape(actions.shape)


def discounted_returns(rewards: Tensor, discount: float) -> Tensor:
    """``(..., H)`` -> ``(...)``: :math:`\\sum_h \\gamma^{h} r_h`."""
    weights = discount ** torch.arange(rewards.shape[-1], dtype=rewards.dtype, device=rewards.device)
    return (rewards * weights).sum(-1)


def shared_masks(dynamics: HRNDynamics, candidates: int, futures: int, rate: float,
                 generator: torch.Generator) -> dict[str, Tensor]:
    """One model step's dropout masks for ``candidates x futures`` copies: ``futures`` masks
    drawn once and repeated for every candidate (copy ``i K + j`` takes mask ``j``), on the
    dynamics' masked modules. **Shapes:** ``{module: (passes * N * K, hidden)}``."""
    out = {}
    for name, mask in draw_masks(dynamics.model, futures, rate, generator).items():
        if name in dynamics.dropout_modules:
            passes = mask.shape[0] // futures
            out[name] = mask.reshape(passes, 1, futures, -1).expand(passes, candidates, futures, -1) \
                .reshape(passes * candidates * futures, -1)
    return out


def rollout_futures(dynamics: HRNDynamics, state: Tensor, actions: Tensor, futures: int, rate: float,
                    generator: torch.Generator) -> Tensor:
    """Every candidate's K futures from one state, one batched graph of ``N K`` copies per model
    step (:meth:`~hrn_pyg.rl.hrn_dynamics.HRNDynamics.next_history`), differentiable in the
    actions. At rate 0 the futures are one deterministic prediction (``futures`` must be 1).

    **Shapes:** state ``(S,)``, actions ``(N, H, A)`` -> roots ``(N, K, H, O, 6)`` after each step.
    """
    check_rate(rate)
    if futures < 1 or (rate == 0 and futures != 1):
        raise ValueError(f"futures must be >= 1, and 1 at rate 0; got {futures} at rate {rate}")
    if actions.dim() != 3 or actions.shape[-1] != dynamics.task.action_dim:
        raise ValueError(f"actions must be (N, H, {dynamics.task.action_dim}), got {tuple(actions.shape)}")
    N, H, _ = actions.shape
    n = N * futures
    pos, index = dynamics.leaf_history(state.unsqueeze(0))             # (1, 3, L, 3), (1,)
    pos, index = pos.expand(n, *pos.shape[1:]), index.expand(n)
    forces = action_to_forces(dynamics.task, actions).repeat_interleave(futures, dim=0)  # (n, H, O, 3)
    roots = []
    for h in range(H):  # a loop over model steps
        masks = shared_masks(dynamics, N, futures, rate, generator) if rate > 0 else None
        pos = dynamics.next_history(pos, index, forces[:, h], masks)  # (n, 3, L, 3)
        roots.append(dynamics.roots(dynamics.state_of(pos, index)))     # (n, O, 6)
    return torch.stack(roots, 1).reshape(N, futures, H, *roots[0].shape[-2:])


def cem(score_fn: ScoreFn, mean: Tensor, std: Tensor, bound: float, config: PlannerConfig,
        generator: torch.Generator, project: Callable[[Tensor], Tensor] | None = None,
        proposals: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The cross-entropy method over action sequences ``(H, A)`` inside ``[-bound, bound]``
    (or ``project``'s set: a map of sequences into the bounds). ``proposals`` ``(P, H, A)``
    take the places after :math:`\\mu` in the first draw (``P < N``).

    Each of ``config.iterations`` draws ``config.candidates`` sequences from
    :math:`\\mathcal N(\\mu, \\sigma^2)` (the first is :math:`\\mu`), clipped; the
    ``config.elites`` best refit :math:`\\mu, \\sigma`. Returns the best sequence seen, its score,
    and the last :math:`\\mu, \\sigma`. **Shapes:** mean, std ``(H, A)`` -> ``(H, A)``, ``()``,
    ``(H, A)``, ``(H, A)``.
    """
    if mean.shape != std.shape or mean.dim() != 2:
        raise ValueError(f"mean and std must both be (H, A), got {tuple(mean.shape)}, {tuple(std.shape)}")
    if project is None:
        def project(a: Tensor) -> Tensor:
            return a.clamp(-bound, bound)
    best, best_score = project(mean), torch.tensor(-float("inf"))
    floor = config.min_std * bound
    if proposals is not None and not 0 < len(proposals) < config.candidates:
        raise ValueError(f"proposals must be 1 to candidates - 1 = {config.candidates - 1}, got {len(proposals)}")
    for it in range(config.iterations):  # a loop over CEM iterations
        noise = torch.randn((config.candidates, *mean.shape), generator=generator, dtype=mean.dtype)
        noise[0] = 0.0
        actions = project(mean + std * noise)                           # (N, H, A)
        if it == 0 and proposals is not None:
            actions[1:1 + len(proposals)] = project(proposals)
        scores = score_fn(actions)                                      # (N,)
        top = scores.topk(config.elites).indices
        if scores[top[0]] > best_score:
            best, best_score = actions[top[0]], scores[top[0]]
        elite = actions[top]
        mean, std = elite.mean(0), elite.std(0, correction=0).clamp_min(floor)
    return best, best_score, mean, std


def refine(loss_fn: Callable[[Tensor], Tensor], actions: Tensor, bound: float, steps: int,
           lr: float, project: Callable[[Tensor], Tensor] | None = None) -> tuple[Tensor, list[float]]:
    """Adam on an action sequence ``(H, A)`` through a differentiable ``loss_fn`` (a scalar),
    projected into ``[-bound, bound]`` (or by ``project``) after every step. Returns the sequence of lowest loss
    seen (the start included) and the loss of every evaluation (``steps + 1``; fewer when the
    loss has no gradient, as when every object sleeps through the rollout)."""
    if steps < 0:
        raise ValueError(f"steps must be >= 0, got {steps}")
    u = actions.detach().clone().requires_grad_(True)
    opt = torch.optim.Adam([u], lr=lr)
    best, best_loss, losses = u.detach().clone(), float("inf"), []
    for i in range(steps + 1):  # a loop over optimiser steps; the last one only evaluates
        with torch.enable_grad():
            loss = loss_fn(u)
        value = float(loss.detach())
        losses.append(value)
        if value < best_loss:
            best, best_loss = u.detach().clone(), value
        if i == steps or not loss.requires_grad:  # no gradient (nothing moves): nothing to follow
            break
        opt.zero_grad()
        loss.backward()
        opt.step()
        with torch.no_grad():
            u.copy_(project(u) if project is not None else u.clamp(-bound, bound))
    return best, losses


class MPCPlanner:
    """Plans an action for a state by :func:`cem` (and :func:`refine`) over the learned model.

    Args:
        dynamics: the learned physics (its model, pool masses and sleep settings).
        config: the planner's settings; ``config.rate`` None takes ``dynamics.calibrated_rate``,
            else the task's ``dropout_rate``.
        seed: seeds the planner's own generator (candidates and dropout masks).

    :meth:`act` keeps the last plan for the warm start (and, with ``action_repeat`` ``r``, holds
    its first action for ``r`` calls); :meth:`reset` forgets it.
    """

    def __init__(self, dynamics: HRNDynamics, config: PlannerConfig, seed: int = 0) -> None:
        self.dynamics, self.config, self.task = dynamics, config, dynamics.task
        rate = config.rate
        if rate is None:
            rate = dynamics.calibrated_rate if dynamics.calibrated_rate is not None else self.task.dropout_rate
        #: the dropout rate of the futures (0 for ``deterministic``)
        self.rate = 0.0 if config.score == "deterministic" else float(rate)
        if config.score != "deterministic" and self.rate == 0:
            raise ValueError(f"score {config.score!r} needs a dropout rate above 0")
        self.generator = torch.Generator().manual_seed(int(seed))
        self.reset()

    def __repr__(self) -> str:
        return f"{type(self).__name__}(task={self.task.name!r}, rate={self.rate:g}, {self.config})"

    def reset(self) -> None:
        self._plan = torch.zeros(self.config.horizon, self.task.action_dim)
        self._held = 0  # control steps the current first action is still to be held

    def project(self, actions: Tensor) -> Tensor:
        """Actions ``(..., A)`` into the planner's force bounds (:func:`project_actions`)."""
        return project_actions(self.task, actions, self.config.horizontal)

    def objective(self, state: Tensor, goal: Tensor, mask_seed: int) -> ScoreFn:
        """``actions (N, H, A) -> scores (N,)`` from ``state`` toward ``goal``; every call draws the
        same masks (a generator seeded with ``mask_seed``), so scores of one planning step compare."""
        cfg = self.config

        # the reach route's push direction and object, from the state the plan starts in
        start = self.dynamics.roots(state.unsqueeze(0))[0]
        direction = push_direction(self.task, start, goal)
        pushed = route_object(self.task, start) if uses_route(self.task) else None

        def score_fn(actions: Tensor) -> Tensor:
            generator = torch.Generator().manual_seed(mask_seed)
            held = actions.repeat_interleave(cfg.action_repeat, dim=1)          # (N, H r, A)
            roots = rollout_futures(self.dynamics, state, held, cfg.num_futures, self.rate, generator)
            rewards = planning_rewards(self.task, roots, goal, cfg.reach_weight, direction, pushed)  # (N, K, H r)
            return score_returns(discounted_returns(rewards, cfg.discount), cfg.score, cfg.risk_std)

        return score_fn

    def plan(self, state: Tensor, goal: Tensor) -> dict:
        """One planning step: ``{"actions": (H, A), "score": float, "refine_losses": [...]}``."""
        cfg, bound = self.config, self.task.max_force
        mask_seed = int(torch.randint(2**62, (), generator=self.generator))
        score_fn = self.objective(state, goal.reshape(2), mask_seed)
        mean = torch.cat([self._plan[1:], self._plan[-1:]])  # warm start: the last plan, shifted
        std = torch.full_like(mean, cfg.init_std * bound)
        proposals = None
        if cfg.route_proposal and uses_route(self.task) and cfg.candidates > 1:
            roots = self.dynamics.roots(state.unsqueeze(0))[0]
            goal2 = goal.reshape(2)
            push = route_push(self.task, roots, goal2, push_direction(self.task, roots, goal2),
                              route_object(self.task, roots))
            proposals = push.expand(1, cfg.horizon, -1)
        with torch.no_grad():
            best, score, _, _ = cem(score_fn, mean, std, bound, cfg, self.generator, self.project, proposals)
        losses: list[float] = []
        if cfg.refine_steps > 0:
            best, losses = refine(lambda u: -score_fn(u.unsqueeze(0))[0], best, bound,
                                  cfg.refine_steps, cfg.refine_lr * bound, self.project)
            score = torch.tensor(-min(losses))
        self._plan = best.detach()
        return {"actions": self._plan, "score": float(score), "refine_losses": losses}

    def act(self, state: Tensor, goal: Tensor) -> Tensor:
        """The first action of a fresh plan, ``(A,)``; with ``action_repeat`` ``r`` a fresh plan
        every ``r`` calls, its first action held in between."""
        if self._held == 0:
            self.plan(state, goal)
            self._held = self.config.action_repeat
        self._held -= 1
        return self._plan[0].clone()


def plan_episode(planner: MPCPlanner, seed: int, goal: Tensor, pool_index: int = 0) -> dict:
    """One closed-loop episode in the pybullet scene ``seed`` against ``goal`` ``(2,)``.

    The loop of :func:`~hrn_pyg.rl.evaluate.control_in_pybullet`: after the reset and
    ``HISTORY`` zero-force steps (as the learned episodes start), every control step rebuilds the
    learned state from pybullet's last three frames of leaves (masses of pool entry
    ``pool_index``, which must be scene ``seed``), plans, applies the first action in pybullet
    and judges the goal there, for up to ``task.max_steps`` steps.

    Returns ``success``, ``steps``, ``plan_seconds`` and ``physics_seconds`` (one per control
    step), ``actions`` ``(T, A)``, ``roots`` ``(T + 1, O, 6)`` and the ``goal``.
    """
    from hrn_pyg.rl.evaluate import control_in_pybullet

    dyn = planner.dynamics
    if int(dyn.pool_seeds[pool_index]) != seed:
        raise ValueError(f"pool entry {pool_index} is not pybullet scene {seed}")
    goal = torch.as_tensor(goal, dtype=torch.float32).reshape(2)
    planner.reset()
    index = torch.tensor(pool_index)

    def act(frames: list[Tensor], _roots: Tensor) -> Tensor:
        return planner.act(dyn.state_of(torch.stack(frames[-3:]), index), goal)

    out = control_in_pybullet(act, planner.task, seed, goal, HISTORY)
    out["plan_seconds"] = out.pop("act_seconds")
    return {**out, "goal": goal}


def episode_goal(task: TaskConfig, dynamics: HRNDynamics, pool_index: int, seed: int) -> Tensor:
    """A goal ``(2,)`` for pool entry ``pool_index``, drawn by :func:`~hrn_pyg.rl.tasks.sample_goal`
    from a generator seeded with ``seed``."""
    state = dynamics.state_of(dynamics.pool[pool_index], torch.tensor(pool_index))
    return sample_goal(task, dynamics.roots(state).unsqueeze(0), torch.Generator().manual_seed(seed))[0]


def episode_figure(result: dict, task: TaskConfig, path: str | Path, title: str = "") -> None:
    """Top view of the objects' paths with the goal disc, and planning vs pybullet time per step."""
    from hrn_pyg.viz import pyplot, save_figure

    plt = pyplot()
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 4.5))
    roots = result["roots"].numpy()
    for o in range(task.num_objects):
        kind = "pushed" if o in task.controlled_objects else "goal" if o in task.goal_objects else "object"
        ax.plot(roots[:, o, 0], roots[:, o, 1], "-o", ms=2, label=f"object {o} ({kind})")
    goal = result["goal"].numpy()
    ax.add_patch(plt.Circle(goal, task.goal_radius, color="g", alpha=0.3, label="goal"))
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(fontsize=7)
    ax.set_title(f"{'success' if result['success'] else 'failure'} in {result['steps']} steps")
    steps = range(1, result["steps"] + 1)
    bx.semilogy(steps, result["plan_seconds"], "-o", ms=3, label="planning")
    bx.semilogy(steps, result["physics_seconds"], "-o", ms=3, label="pybullet step")
    bx.set_xlabel("control step")
    bx.set_ylabel("seconds")
    bx.legend()
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)


def run(args: argparse.Namespace) -> int:
    config = PlannerConfig(score=args.score, candidates=args.candidates, elites=args.elites,
                           iterations=args.iterations, horizon=args.horizon, futures=args.k,
                           rate=args.rate, risk_std=args.risk_std,
                           refine_steps=args.refine_steps if args.refine else 0,
                           action_repeat=args.action_repeat, reach_weight=args.reach_weight,
                           horizontal=args.horizontal, route_proposal=args.route_proposal)
    if args.threads < 1:
        raise ValueError(f"--threads must be >= 1, got {args.threads}")
    if args.control_steps is not None and args.control_steps < 1:
        raise ValueError(f"--control-steps must be >= 1, got {args.control_steps}")
    task = get_task(args.task)
    if args.control_steps is not None:
        task = replace(task, max_steps=min(args.control_steps, task.max_steps),
                       hold_steps=min(task.hold_steps, args.control_steps))
    torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    dynamics = HRNDynamics.from_checkpoint(args.model, task, device, pool_seeds=(args.episode_seed,))
    planner = MPCPlanner(dynamics, config, seed=args.seed)
    goal = episode_goal(task, dynamics, 0, args.episode_seed)
    result = plan_episode(planner, args.episode_seed, goal)
    plan_s, physics_s = result["plan_seconds"], result["physics_seconds"]
    print(f"{task.name}: {'success' if result['success'] else 'failure'} after {result['steps']} steps "
          f"(score {config.score}{', refined' if config.refine_steps else ''}, rate {planner.rate:g})")
    print(f"planning per control step: {sum(plan_s) / len(plan_s):.3f} s "
          f"(max {max(plan_s):.3f} s); pybullet step: {sum(physics_s) / len(physics_s) * 1e3:.2f} ms")
    out = Path(args.out) if args.out else Path("runs") / "plan" / task.name
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "episode.json", {
        "task": task.name, "model": str(args.model), "episode_seed": args.episode_seed, "seed": args.seed,
        "device": str(device), "success": bool(result["success"]), "steps": int(result["steps"]),
        "rate": float(planner.rate), "plan_seconds": [float(s) for s in plan_s],
        "physics_seconds": [float(s) for s in physics_s], "planner": asdict(config)})
    picture = out / "episode.png"
    episode_figure(result, task, picture, title=f"{task.name}, model {args.model}, score {config.score}"
                   f"{' + refine' if config.refine_steps else ''}, N={config.candidates}, "
                   f"H={config.horizon}x{config.action_repeat}, K={config.num_futures}, rate {planner.rate:g}")
    print(f"picture: {picture}; record: {out / 'episode.json'}")
    return 0

