"""A TorchRL environment whose step is a (learned, stochastic) physics predictor.

Each step samples ``k`` next states (5 in the seed paper) with Monte Carlo dropout and applies
**reward relaxation** (seed paper, section 3.3; :func:`choose_next`): a step rewards 1 and ends
the episode if any sample reaches the goal, else one sample drawn at random is the next state
(:class:`HRNEnv` gives the rule, the unrelaxed variant and ``hold_steps``). ``goal_hits`` counts
the samples in the goal, for :func:`partial_hits` and :func:`near_miss_share`.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from hrn_pyg.rl.dynamics import StochasticDynamics, dropout_spread
from hrn_pyg.rl.tasks import (
    GOAL_DIM,
    TaskConfig,
    action_to_forces,
    get_task,
    goal_held,
    goal_reached,
    goal_streak,
    sample_goal,
)


class HRNEnv(EnvBase):
    r"""Batched environment over a :class:`~hrn_pyg.rl.dynamics.StochasticDynamics`.

    One step from state :math:`s_t` with action :math:`a_t` (forces, plus Gaussian noise of
    standard deviation ``action_noise_std * max_force`` for the action-noise baseline, clipped
    to the bounds):

    .. math::
        s^{(1..k)}_{t+1} \sim f_\theta(s_t, a_t; p), \qquad
        r_t = \mathbb 1\big[\exists j: \mathrm{goal}(s^{(j)}_{t+1})\big], \qquad
        s_{t+1} = \begin{cases} s^{(j^*)}_{t+1}, & j^* = \text{first sample in the goal} \\
                                s^{(u)}_{t+1},\ u \sim \mathcal U\{1..k\} & \text{otherwise} \end{cases}

    with dropout rate :math:`p` = :attr:`dropout_rate`, an attribute a schedule may change
    between PPO updates (:meth:`set_dropout_rate` does the same through ``ParallelEnv``).
    With ``relax=False`` the next state is always the drawn sample
    :math:`s^{(u)}_{t+1}` and :math:`r_t = \mathbb 1[\mathrm{goal}(s^{(u)}_{t+1})]`. With
    ``task.hold_steps`` :math:`H > 1` the goal event :math:`h_t` (the indicator above) feeds a
    count :math:`c_{t+1} = (c_t + 1)\, h_t`, and the episode terminates with reward 1 when
    :math:`c_{t+1} \ge H` (``step_penalty`` otherwise).

    Specs (``B`` = ``batch_size``, ``O`` objects, ``S`` = ``dynamics.state_dim``,
    ``A`` = ``task.action_dim``; ``env.specs`` prints them in full)::

        observation_spec: Composite(shape=(B,))
            observation: Unbounded((B, O*6 + 2), float32)  # root [x, y, z, vx, vy, vz] per object, goal (x, y)
            state:       Unbounded((B, S), float32)        # what the dynamics continues from
            goal:        Unbounded((B, 2), float32)
            t:           Unbounded((B, 1), int64)          # steps taken in this episode
            held:        Unbounded((B, 1), int64)          # goal-reaching steps in a row, up to now
            goal_hits:   Unbounded((B, 1), int64)          # samples of the last step in the goal (0 at reset)
        state_spec:      Composite(state, goal, t, held)    # read back by _step
        action_spec:     Bounded((B, A), float32, low=-max_force, high=max_force)   # Newton
        reward_spec:     Unbounded((B, 1), float32)
        done_spec:       Composite(done, terminated, truncated: Categorical((B, 1), bool))

    Args:
        task: a :class:`~hrn_pyg.rl.tasks.TaskConfig` or its name.
        dynamics: the predictor. ``None`` builds
            :class:`~hrn_pyg.rl.dynamics.PointMassDynamics` for the task (development only).
        batch_size: ``B``, environments stepped together.
        num_samples: ``k``; defaults to ``task.num_samples``.
        dropout_rate: defaults to ``task.dropout_rate``.
        action_noise_std: Gaussian action noise as a fraction of ``max_force`` (0: none).
        relax: reward relaxation over the ``k`` samples (True, the seed paper's); False: the
            next state and the reward are those of one sample drawn at random.
        seed: seeds the environment's own generator (on ``device``: the same seed draws other
            numbers on CUDA than on the CPU).
        device: where states, actions and rewards live; must be the dynamics' device. None:
            ``dynamics.device`` when it has one, else the CPU.
    """

    batch_locked = True

    def __init__(self, task: str | TaskConfig, dynamics: StochasticDynamics | None = None, *,
                 batch_size: int = 1, num_samples: int | None = None,
                 dropout_rate: float | None = None, action_noise_std: float = 0.0,
                 relax: bool = True, seed: int | None = None,
                 device: str | torch.device | None = None):
        task = get_task(task)
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if device is None:
            device = getattr(dynamics, "device", "cpu")
        if dynamics is None:
            from hrn_pyg.rl.dynamics import PointMassDynamics

            dynamics = PointMassDynamics.for_task(task.scene_name, task.dropout_modules, device)
        if dynamics.num_objects != task.num_objects:
            raise ValueError(f"dynamics has {dynamics.num_objects} objects, task {task.name!r} "
                             f"expects {task.num_objects}")
        k = task.num_samples if num_samples is None else num_samples
        if k < 1:
            raise ValueError(f"num_samples must be >= 1, got {k}")
        super().__init__(device=device, batch_size=torch.Size([batch_size]))
        self.task = task
        self.dynamics = dynamics
        self.num_samples = k
        self.dropout_rate = task.dropout_rate if dropout_rate is None else dropout_rate
        self.action_noise_std = action_noise_std
        self.relax = bool(relax)
        self._make_spec()
        if seed is None:
            seed = int(torch.empty((), dtype=torch.int64).random_().item())
        self.set_seed(seed)

    # ------------------------------------------------------------------ knobs
    @property
    def dropout_rate(self) -> float:
        return self._dropout_rate

    @dropout_rate.setter
    def dropout_rate(self, rate: float) -> None:
        dropout_spread(rate)  # raises ValueError outside [0, 1)
        self._dropout_rate = float(rate)

    @property
    def action_noise_std(self) -> float:
        return self._action_noise_std

    @action_noise_std.setter
    def action_noise_std(self, std: float) -> None:
        if std < 0:
            raise ValueError(f"action_noise_std must be >= 0, got {std}")
        self._action_noise_std = float(std)

    def set_dropout_rate(self, rate: float) -> None:
        """Method form of the setter, callable on every worker of a ``ParallelEnv``."""
        self.dropout_rate = rate

    # ------------------------------------------------------------------ specs
    def _make_spec(self) -> None:
        B, task, dyn = self.batch_size, self.task, self.dynamics
        obs_dim = task.num_objects * dyn.object_dim + GOAL_DIM
        state = Composite(
            state=Unbounded(shape=(*B, dyn.state_dim), dtype=torch.float32),
            goal=Unbounded(shape=(*B, GOAL_DIM), dtype=torch.float32),
            t=Unbounded(shape=(*B, 1), dtype=torch.int64),
            held=Unbounded(shape=(*B, 1), dtype=torch.int64),
            shape=B,
        )
        self.observation_spec = Composite(
            observation=Unbounded(shape=(*B, obs_dim), dtype=torch.float32),
            **{key: spec.clone() for key, spec in state.items()},
            goal_hits=Unbounded(shape=(*B, 1), dtype=torch.int64),
            shape=B,
        )
        self.state_spec = state
        self.action_spec = Bounded(low=-task.max_force, high=task.max_force,
                                   shape=(*B, task.action_dim), dtype=torch.float32)
        self.reward_spec = Unbounded(shape=(*B, 1), dtype=torch.float32)
        self.done_spec = Composite(
            done=Categorical(2, shape=(*B, 1), dtype=torch.bool),
            terminated=Categorical(2, shape=(*B, 1), dtype=torch.bool),
            truncated=Categorical(2, shape=(*B, 1), dtype=torch.bool),
            shape=B,
        )

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            seed = int(torch.empty((), dtype=torch.int64).random_().item())
        self.rng = torch.Generator(device=self.device).manual_seed(int(seed))

    # ------------------------------------------------------------------ dynamics
    def _observation(self, state: Tensor, goal: Tensor) -> Tensor:
        roots = self.dynamics.roots(state)
        return torch.cat([roots.flatten(-2), goal], -1)

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        # Fresh scenes for the whole batch; TorchRL keeps the entries whose "_reset" is False.
        B = self.batch_size[0]
        state = self.dynamics.reset_states(B, self.rng).to(torch.float32)
        goal = sample_goal(self.task, self.dynamics.roots(state), self.rng).to(torch.float32)
        false = torch.zeros(B, 1, dtype=torch.bool, device=self.device)
        return TensorDict(
            {
                "observation": self._observation(state, goal),
                "state": state,
                "goal": goal,
                "t": torch.zeros(B, 1, dtype=torch.int64, device=self.device),
                "held": torch.zeros(B, 1, dtype=torch.int64, device=self.device),
                "goal_hits": torch.zeros(B, 1, dtype=torch.int64, device=self.device),
                "done": false,
                "terminated": false.clone(),
                "truncated": false.clone(),
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        state, goal, t = tensordict["state"], tensordict["goal"], tensordict["t"]
        action = tensordict["action"]
        bound = self.task.max_force
        if self.action_noise_std > 0:
            noise = torch.randn(action.shape, generator=self.rng, device=self.rng.device)
            action = action + noise.to(action.device) * (self.action_noise_std * bound)
        action = action.clamp(-bound, bound)
        forces = action_to_forces(self.task, action)
        samples = self.dynamics.sample_next(state, forces, self.num_samples, self.dropout_rate,
                                            self.rng)                          # (B, k, S)
        in_goal = goal_reached(self.task, self.dynamics.roots(samples), goal.unsqueeze(1))  # (B, k)
        next_state, hit = choose_next(in_goal, samples, self.rng, self.relax)
        t_next = t + 1
        held = goal_streak(tensordict["held"], hit.unsqueeze(-1))
        terminated = goal_held(self.task, held)
        truncated = (t_next >= self.task.max_steps) & ~terminated
        reward = torch.where(terminated, 1.0, self.task.step_penalty).to(torch.float32)
        return TensorDict(
            {
                "observation": self._observation(next_state, goal),
                "state": next_state,
                "goal": goal,
                "t": t_next,
                "held": held,
                "goal_hits": in_goal.sum(-1, keepdim=True),
                "reward": reward,
                "done": terminated | truncated,
                "terminated": terminated,
                "truncated": truncated,
            },
            batch_size=self.batch_size,
            device=self.device,
        )


def choose_next(in_goal: Tensor, samples: Tensor, generator: torch.Generator,
                relax: bool = True) -> tuple[Tensor, Tensor]:
    r"""The next state and the reward event from ``k`` samples and their goal tests.

    One index :math:`u \sim \mathcal U\{1..k\}` is drawn per environment from ``generator``
    (on its device) in either case, so relaxed and unrelaxed environments consume the same
    random stream. With ``relax``: :math:`\text{hit} = \exists j\, g_j` and the next state is the
    first sample in the goal, else sample :math:`u`. Without: the next state is sample
    :math:`u` and :math:`\text{hit} = g_u`.

    **Shapes**: in_goal ``(B, k)`` bool, samples ``(B, k, S)`` -> next state ``(B, S)``, hit
    ``(B,)`` bool (on ``samples``' device).
    """
    B, k = samples.shape[:2]
    if in_goal.shape != (B, k):
        raise ValueError(f"in_goal must be ({B}, {k}) like the samples, got {tuple(in_goal.shape)}")
    rows = torch.arange(B, device=samples.device)
    drawn = torch.randint(k, (B,), generator=generator, device=generator.device).to(samples.device)
    in_goal = in_goal.to(samples.device)
    if relax:
        hit = in_goal.any(-1)
        choice = torch.where(hit, in_goal.to(torch.int8).argmax(-1), drawn)
    else:
        choice = drawn
        hit = in_goal[rows, drawn]
    return samples[rows, choice], hit


def partial_hits(goal_hits: Tensor, k: int) -> Tensor:
    r"""Whether some but not all of the ``k`` samples of a step met the goal:
    :math:`0 < h < k` for the count :math:`h` of samples in the goal (the env's ``goal_hits``).

    Only at such a step can relaxation change a reward; at rate 0 (``k`` identical samples) it
    is never true. **Shapes**: any -> the same, bool.
    """
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    return (goal_hits > 0) & (goal_hits < k)


def near_miss_share(goal_hits: Tensor, k: int, mask: Tensor | None = None) -> float | None:
    r"""The near-miss share: among the steps at which at least one of the ``k`` samples met the
    goal (:math:`h > 0`), the fraction at which not all did (:math:`h < k`),

    .. math:: \frac{\#\{0 < h < k\}}{\#\{h > 0\}},

    counted over the steps where ``mask`` is True (None: all). None when no step met the goal.

    **Shapes**: goal_hits any, mask the same (bool) -> a number.
    """
    hit = goal_hits > 0
    if mask is not None:
        if mask.shape != goal_hits.shape:
            raise ValueError(f"mask must have goal_hits' shape {tuple(goal_hits.shape)}, got {tuple(mask.shape)}")
        hit = hit & mask
    reached = int(hit.sum())
    if reached == 0:
        return None
    return int((partial_hits(goal_hits, k) & hit).sum()) / reached
