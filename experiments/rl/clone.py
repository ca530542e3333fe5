r"""``python -m experiments.rl.clone``: a task's scripted planner cloned into the PPO actor, the warm start of
every mode.

With the sparse reward (1 at the goal, else 0) a random policy never reaches the goals of the
tasks with room to learn, so PPO from scratch gets no reward and the ``k`` sampled futures never
straddle a goal (:mod:`experiments.rl.partial_hits`). Started from the task's planner
(:data:`experiments.rl.planners.PLANNERS`) cloned into the actor, every mode's update 0 already
reaches the goal in part of its episodes, where reward relaxation can act.

**Demonstrations** (:func:`collect_demonstrations`). ``episodes`` episodes in the given dynamics
at dropout rate 0, on the training pool only (:data:`~hrn_pyg.rl.hrn_dynamics.POOL_SEEDS`; never
:data:`~hrn_pyg.rl.hrn_dynamics.VALIDATION_SEEDS`, never the generator seed of the evaluation
scenes, :data:`~hrn_pyg.rl.success_curve.EVAL_SEED`). The environment applies the planner's action
plus Gaussian noise of ``collect_noise`` times the force bound, so the states cover small
departures from the planner's path (as the clone's own episodes make them); each state is
labelled with the planner's noise-free action :math:`a^*(o)`. Every step of every episode until
it ends: observations ``(N, O*6 + 2)``, actions ``(N, A)``.

**Mean** (:func:`fit_mean`). The actor (:func:`hrn_pyg.rl.ppo.build_actor_critic`) maps an
observation to the location :math:`\mu(o)` and scale :math:`\sigma(o)` of a TanhNormal on the
bounds :math:`\pm F` (``max_force``); its deterministic action is
:math:`\bar a(o) = F \tanh \mu(o)`. Full-batch Adam, from a network initialised with ``seed``,
for ``steps`` steps on

.. math::
    L = \frac{1}{N A} \sum_{i=1}^{N} \sum_{j=1}^{A}
        \Big(\frac{\bar a_j(o_i) - a^*_j(o_i)}{F}\Big)^2 .

**Exploration** (:func:`set_exploration`). The scale head is made state-independent (its
weights 0) with, per action entry :math:`j`, the scale

.. math::
    \sigma_j = \frac{\nu}{\frac1N \sum_i \big(1 - \tanh^2 \mu_j(o_i)\big)},

so that the action's standard deviation to first order, :math:`F\,(1 - \tanh^2 \mu)\,\sigma`,
averaged over the demonstration states, is :math:`\nu F` (``noise``; 0.1 is the
``action_noise`` mode's level). Where the mean saturates the noise is smaller. PPO may make
the scale state-dependent again as it trains.

**Checkpoint** (:func:`save_clone`; :func:`hrn_pyg.rl.ppo.load_init_policy` reads it): the ``hrn_pyg.checkpoint.v1``
layout of a PPO run's ``policy.pt`` (``model.actor``; ``config`` JSON holding ``ppo.hidden``,
the task, the settings and the fit), written atomically and read weights-only, so
:func:`hrn_pyg.rl.policy.load_actor` reads it too. ``hrn-pyg rl --init-policy PATH`` (and a
sweep's) starts each run's actor from it (critic fresh) and records its SHA-256 in the run's identity.

Command::

    python -m experiments.rl.clone --task cube_push_stop --out runs/clone/cube_push_stop.pt \
        [--episodes 256 --noise 0.1 --seed 0 --model PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor
from torch import Tensor, nn
from torchrl.envs.utils import step_mdp
from torchrl.modules import ProbabilisticActor

from experiments.command import script_main
from experiments.rl.planners import PLANNERS, Planner
from hrn_pyg.rl.dynamics import StochasticDynamics
from hrn_pyg.rl.env import HRNEnv
from hrn_pyg.rl.ppo import build_actor_critic, load_init_policy
from hrn_pyg.rl.tasks import TaskConfig, get_task
from hrn_pyg.utils.checkpoint import load_checkpoint, save_checkpoint
from hrn_pyg.utils.files import file_sha256
from hrn_pyg.utils.options import add_renamed

#: what the script does (its --help)
DESCRIPTION = "clone a task's scripted planner into a PPO actor (the initial policy of hrn-pyg rl --init-policy)"
#: what a clone checkpoint's config says it is
CLONE_KIND = "planner_clone"


@dataclass(frozen=True)
class CloneConfig:
    """Settings of a clone (module docstring).

    Attributes:
        episodes: demonstration episodes.
        collect_noise: action noise while collecting, fraction of the force bound (the labels
            are noise-free).
        noise: the clone's initial exploration, fraction of the force bound (:func:`set_exploration`).
        steps: full-batch Adam steps on the mean.
        lr: Adam's learning rate.
        hidden: hidden width of the actor; must equal PPO's (``PPOConfig.hidden``).
        num_envs: environments stepped together while collecting.
        seed: seeds the network's initialisation and the collecting environment's generator.
    """

    episodes: int = 256
    collect_noise: float = 0.1
    noise: float = 0.1
    steps: int = 2000
    lr: float = 3e-3
    hidden: int = 64
    num_envs: int = 32
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("episodes", "steps", "hidden", "num_envs"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.collect_noise < 0:
            raise ValueError(f"collect_noise must be >= 0, got {self.collect_noise}")
        if not 0 < self.noise <= 1:
            raise ValueError(f"noise must be in (0, 1] (a fraction of the force bound), got {self.noise}")
        if not self.lr > 0:
            raise ValueError(f"lr must be positive, got {self.lr}")
        _check_seed(self.seed)


def _check_seed(seed: int) -> None:
    from hrn_pyg.rl.success_curve import EVAL_SEED

    if seed == EVAL_SEED:
        raise ValueError(f"seed {seed} draws the evaluation scenes (EVAL_SEED); choose another")


def _check_training_scenes(dynamics: StochasticDynamics) -> None:
    """Raise when the dynamics' scene pool holds a validation scene."""
    from hrn_pyg.rl.hrn_dynamics import VALIDATION_SEEDS

    pool = getattr(dynamics, "pool_seeds", None)
    if pool is None:
        return
    shared = sorted(set(int(s) for s in pool.tolist()) & set(VALIDATION_SEEDS))
    if shared:
        raise ValueError(f"demonstrations must come from training scenes, but the pool holds "
                         f"validation seeds {shared[:3]}{'...' if len(shared) > 3 else ''}")


# ---------------------------------------------------------------------------- demonstrations
@torch.no_grad()
def collect_demonstrations(task: str | TaskConfig, dynamics: StochasticDynamics, planner: Planner,
                           episodes: int, *, num_envs: int = 32, collect_noise: float = 0.1,
                           seed: int = 0) -> tuple[Tensor, Tensor]:
    """States the planner visits and its noise-free action there, at dropout rate 0.

    Runs rounds of ``num_envs`` environments (seeded ``seed``, action noise ``collect_noise``)
    until ``episodes`` episodes have ended; every step of every counted episode until it ends
    is kept. Raises on a dynamics whose pool holds validation scenes or on ``seed`` =
    :data:`~hrn_pyg.rl.success_curve.EVAL_SEED`.

    **Shapes**: -> observations ``(N, O*6 + 2)``, actions ``(N, A)`` (CPU, float32).
    """
    task = get_task(task)
    if episodes < 1 or num_envs < 1:
        raise ValueError(f"episodes and num_envs must be >= 1, got {episodes}, {num_envs}")
    _check_seed(seed)
    _check_training_scenes(dynamics)
    B = min(num_envs, episodes)
    env = HRNEnv(task, dynamics, batch_size=B, dropout_rate=0.0, action_noise_std=collect_noise,
                 seed=seed)
    observations, actions = [], []
    for start in range(0, episodes, B):  # a loop over rounds of B episodes
        alive = torch.arange(B, device=env.device) < min(B, episodes - start)
        td = env.reset()
        for _ in range(task.max_steps):  # a loop over time steps
            action = planner(task, td["observation"])
            observations.append(td["observation"][alive].cpu())
            actions.append(action[alive].cpu())
            td["action"] = action
            td = env.step(td)
            alive &= ~td["next", "done"].squeeze(-1)
            if not alive.any():
                break
            td = step_mdp(td)
    return torch.cat(observations).float(), torch.cat(actions).float()


# ---------------------------------------------------------------------------- the actor
def policy_network(actor: ProbabilisticActor) -> nn.Sequential:
    """The MLP of an actor of :func:`~hrn_pyg.rl.ppo.build_actor_critic`: observation ->
    ``(loc, scale)``, its last layer a ``Linear`` followed by a ``NormalParamExtractor``."""
    for module in actor.modules():
        if (isinstance(module, nn.Sequential) and len(module) >= 2
                and isinstance(module[-1], NormalParamExtractor) and isinstance(module[-2], nn.Linear)):
            return module
    raise ValueError("not an actor of build_actor_critic: no MLP ending in Linear, NormalParamExtractor")


def action_distribution(actor: ProbabilisticActor, observations: Tensor):
    """The actor's TanhNormal at ``observations`` ``(N, D)`` (differentiable in the weights)."""
    td = TensorDict({"observation": observations}, batch_size=observations.shape[:1])
    return actor.get_dist(td)


def mean_action(actor: ProbabilisticActor, observations: Tensor) -> Tensor:
    """The deterministic action :math:`F \\tanh \\mu(o)`, ``(N, D)`` -> ``(N, A)``."""
    return action_distribution(actor, observations).deterministic_sample


def fit_mean(actor: ProbabilisticActor, observations: Tensor, actions: Tensor, max_force: float,
             steps: int, lr: float) -> Tensor:
    """Fit the actor's deterministic action to ``actions`` by full-batch Adam on the mean squared
    error in units of the force bound (module docstring); deterministic given the actor's
    initial weights. Returns the loss before each step and after the last, ``(steps + 1,)``.

    **Shapes**: observations ``(N, D)``, actions ``(N, A)``.
    """
    if observations.shape[0] != actions.shape[0] or observations.shape[0] == 0:
        raise ValueError(f"need as many observations as actions, at least one; got "
                         f"{observations.shape[0]}, {actions.shape[0]}")
    if steps < 1 or not lr > 0 or not max_force > 0:
        raise ValueError(f"need steps >= 1, lr > 0 and max_force > 0; got {steps}, {lr}, {max_force}")
    params = list(policy_network(actor).parameters())
    optim = torch.optim.Adam(params, lr=lr)
    losses = torch.empty(steps + 1)
    for i in range(steps):  # full-batch optimisation steps
        loss = ((mean_action(actor, observations) - actions) / max_force).pow(2).mean()
        losses[i] = loss.detach()
        optim.zero_grad()
        loss.backward()
        optim.step()
    with torch.no_grad():
        losses[steps] = ((mean_action(actor, observations) - actions) / max_force).pow(2).mean()
    return losses


def _inverse(mapping: nn.Module, target: float, lower: float = -50.0, upper: float = 50.0) -> float:
    """The input at which a monotone increasing ``mapping`` reaches ``target`` (bisection)."""
    lo, hi = lower, upper
    for _ in range(100):  # bisection to float64 precision
        mid = (lo + hi) / 2
        if float(mapping(torch.tensor(mid, dtype=torch.float64))) < target:
            lo = mid
        else:
            hi = mid
    return (lo + hi) / 2


@torch.no_grad()
def set_exploration(actor: ProbabilisticActor, observations: Tensor, noise: float) -> Tensor:
    """Make the actor's scale state-independent, :math:`\\sigma_j = \\nu / \\overline{1 -
    \\tanh^2 \\mu_j}` over ``observations`` (module docstring), and return it, ``(A,)``.

    Raises when that scale lies below the scale head's floor.
    """
    if not noise > 0:
        raise ValueError(f"noise must be positive, got {noise}")
    net = policy_network(actor)
    last, extractor = net[-2], net[-1]
    A = last.out_features // 2
    loc = action_distribution(actor, observations).loc                         # (N, A)
    slope = (1 - torch.tanh(loc).pow(2)).mean(0).clamp_min(1e-6)               # (A,)
    scale = noise / slope
    if bool((scale < extractor.scale_lb).any()):
        raise ValueError(f"noise {noise} gives a scale below the floor {extractor.scale_lb}")
    raw = torch.tensor([_inverse(extractor.scale_mapping, float(s)) for s in scale],
                       dtype=last.bias.dtype, device=last.bias.device)
    last.weight[A:] = 0.0
    last.bias[A:] = raw
    return action_distribution(actor, observations[:1]).scale[0].detach().clone()


class ActorPolicy:
    """An actor as a planner-like callable ``(task, observation (B, D)) -> action (B, A)``:
    its deterministic action, or with ``sample=True`` a draw from its TanhNormal made with the
    policy's own generator (:meth:`manual_seed`), so a measurement with it depends only on its
    seeds (:func:`experiments.rl.partial_hits.partial_hit_share` reseeds it)."""

    def __init__(self, actor: ProbabilisticActor, sample: bool = False, seed: int = 0) -> None:
        self.actor, self.sample = actor, bool(sample)
        self.generator = torch.Generator().manual_seed(seed)

    def manual_seed(self, seed: int) -> None:
        """Reset the generator of the sampled actions."""
        self.generator.manual_seed(int(seed))

    @torch.no_grad()
    def __call__(self, task: TaskConfig, observation: Tensor) -> Tensor:
        dist = action_distribution(self.actor, observation)
        if not self.sample:
            return dist.deterministic_sample
        z = torch.randn(dist.loc.shape, generator=self.generator).to(dist.loc.device)
        x = dist.loc + dist.scale * z
        for transform in dist.transforms:  # as the TanhNormal maps its base sample
            x = transform(x)
        return x


# ---------------------------------------------------------------------------- clone, save, load
def clone_planner(task: str | TaskConfig, dynamics: StochasticDynamics,
                  config: CloneConfig = CloneConfig(),
                  planner: Planner | None = None) -> tuple[ProbabilisticActor, dict]:
    """Collect, fit the mean, set the exploration: the task's planner (default:
    :data:`~experiments.rl.planners.PLANNERS`) as a PPO actor on the CPU, and a report of the fit
    (``states``, ``loss_initial``, ``loss_final``, ``max_abs_error`` in units of the force
    bound, ``exploration_scale`` per action entry, ``seconds``). Deterministic given
    ``config`` (the caller's random state is left as it was)."""
    task = get_task(task)
    if planner is None:
        if task.name not in PLANNERS:
            raise ValueError(f"no planner for task {task.name!r}; known: {', '.join(PLANNERS)}")
        planner = PLANNERS[task.name]
    start = time.perf_counter()
    observations, actions = collect_demonstrations(
        task, dynamics, planner, config.episodes, num_envs=config.num_envs,
        collect_noise=config.collect_noise, seed=config.seed)
    spec_env = HRNEnv(task, dynamics, batch_size=1, seed=config.seed, device="cpu")
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        actor, _ = build_actor_critic(spec_env, config.hidden)
    losses = fit_mean(actor, observations, actions, task.max_force, config.steps, config.lr)
    scale = set_exploration(actor, observations, config.noise)
    with torch.no_grad():
        error = (mean_action(actor, observations) - actions).abs().max() / task.max_force
    report = {"states": int(observations.shape[0]), "loss_initial": float(losses[0]),
              "loss_final": float(losses[-1]), "max_abs_error": float(error),
              "exploration_scale": [float(s) for s in scale],
              "seconds": time.perf_counter() - start}
    return actor, report


def save_clone(path: str | os.PathLike, actor: ProbabilisticActor, task: str | TaskConfig,
               config: CloneConfig, report: dict, dynamics: str = "") -> str:
    """Write the clone (module docstring) to ``path`` atomically; returns its SHA-256. The
    report's ``seconds`` is left out, so the same clone makes the same file (and SHA-256)."""
    task = get_task(task)
    fit = {k: v for k, v in report.items() if k != "seconds"}
    meta = {"kind": CLONE_KIND, "task": task.to_dict(), "clone": asdict(config),
            "ppo": {"hidden": config.hidden}, "fit": fit, "dynamics": dynamics}
    save_checkpoint(path, {"model": {"actor": actor.state_dict()},
                           "config": json.dumps(meta, sort_keys=True)})
    return file_sha256(path)


def load_policy_actor(path: str | os.PathLike, task: str | TaskConfig,
                      dynamics: StochasticDynamics) -> ProbabilisticActor:
    """A PPO actor for ``task`` on the dynamics' device, its weights from a policy checkpoint
    (a clone or a run's ``policy.pt``; its width from the checkpoint's ``ppo.hidden``), in eval
    mode. Raises as :func:`~hrn_pyg.rl.ppo.load_init_policy`."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"policy checkpoint not found: {path}")
    hidden = (json.loads(load_checkpoint(path)["config"]).get("ppo") or {}).get("hidden")
    if not isinstance(hidden, int):
        raise ValueError(f"{path} does not say its actor's width (config ppo.hidden)")
    actor, _ = build_actor_critic(HRNEnv(task, dynamics, batch_size=1, seed=0), hidden)
    load_init_policy(path, actor, task)
    return actor.eval()


# ---------------------------------------------------------------------------- CLI
def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = CloneConfig()
    parser.add_argument("--task", choices=sorted(PLANNERS), required=True, help="the task whose planner is cloned")
    parser.add_argument("--out", required=True, help="the clone checkpoint to write (.pt)")
    parser.add_argument("--model", default=None,
                        help="learned HRN checkpoint (default: the shipped model of the task's scene)")
    parser.add_argument("--episodes", type=int, default=d.episodes, help="demonstration episodes")
    parser.add_argument("--noise", type=float, default=d.noise,
                        help="initial exploration noise, fraction of the force bound")
    parser.add_argument("--collect-noise", type=float, default=d.collect_noise,
                        help="action noise while collecting demonstrations, fraction of the force bound")
    parser.add_argument("--train-steps", type=int, default=d.steps, dest="steps", help="full-batch Adam steps on the mean")
    parser.add_argument("--lr", type=float, default=d.lr, help="Adam's learning rate")
    parser.add_argument("--hidden", type=int, default=d.hidden, help="actor width (PPO's)")
    parser.add_argument("--seed", type=int, default=d.seed,
                        help="seeds the network's initialisation and the collecting environment's generator")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    add_renamed(parser, "--steps", "--train-steps")


def run(args: argparse.Namespace) -> int:
    from hrn_pyg.checkpoints import resolve_model
    from hrn_pyg.rl.hrn_dynamics import POOL_SEEDS, HRNDynamics
    from hrn_pyg.sim.sleeping import DEFAULT_SLEEP

    if args.threads < 1:
        raise ValueError(f"--threads must be >= 1, got {args.threads}")
    config = CloneConfig(episodes=args.episodes, collect_noise=args.collect_noise, noise=args.noise,
                         steps=args.steps, lr=args.lr, hidden=args.hidden, seed=args.seed)
    out = Path(args.out)
    if out.is_dir():
        raise ValueError(f"--out must be a file path, {out} is a folder")
    task = get_task(args.task)
    model = resolve_model(task.scene_name, args.model)
    torch.set_num_threads(args.threads)
    dynamics = HRNDynamics.from_checkpoint(model, task, "cpu", pool_seeds=POOL_SEEDS, sleep=DEFAULT_SLEEP)
    actor, report = clone_planner(task, dynamics, config)
    digest = save_clone(out, actor, task, config, report, repr(dynamics))
    print(f"{task.name}: cloned the planner from {report['states']} states of {config.episodes} episodes, "
          f"loss {report['loss_initial']:.4f} -> {report['loss_final']:.5f}, max error "
          f"{report['max_abs_error']:.3f} x max force ({report['seconds']:.0f} s); wrote {out} "
          f"(sha256 {digest[:12]})")
    return 0


def main(argv: list[str] | None = None) -> int:
    return script_main("python -m experiments.rl.clone", DESCRIPTION, add_arguments, run, argv)


if __name__ == "__main__":
    sys.exit(main())
