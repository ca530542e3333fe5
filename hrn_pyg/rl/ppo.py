"""``hrn-pyg rl``: one PPO run in the (stochastic) learned environment, trained and scored.

Built from TorchRL pieces: a :class:`~torchrl.modules.ProbabilisticActor` with a
:class:`~torchrl.modules.TanhNormal` head and a :class:`~torchrl.modules.ValueOperator`, a
single-process collector (``torchrl.collectors.Collector``, the 0.14 name of
``SyncDataCollector``), :class:`~torchrl.objectives.value.GAE` and
:class:`~torchrl.objectives.ClipPPOLoss`. A run has one of five modes (``--mode``):

- ``deterministic``: dropout rate 0.
- ``action_noise``: rate 0, Gaussian noise on the actions (``PPOConfig.action_noise_std`` of
  the force bound), the Plappert et al. baseline.
- ``stochastic``: the dropout rate held constant (cube_push: 0.1 on the force module).
- ``stochastic_annealed``: the rate brought linearly to 0 over ``anneal_updates`` PPO
  updates (tower: 0.1 -> 0 over 1200).
- ``stochastic_unrelaxed``: the constant rate of ``stochastic`` without reward relaxation: the
  next state is one of the ``k`` samples drawn at random and only its own goal test rewards
  (the ablation that separates a stochastic model from an optimistic reward).

Every update logs the partial-hit share of its batch (steps at which some but not all of the
``k`` samples met the goal, :func:`~hrn_pyg.rl.env.partial_hits`) and its near-miss share over
the goal-reaching steps (:func:`~hrn_pyg.rl.env.near_miss_share`). ``--init-policy PATH``
starts the actor from a policy checkpoint (its SHA-256 is part of the run's identity); the
stochastic modes' rate is ``--dropout-rate``, else the model's calibrated rate, else the task's.
Without ``--model`` the environment steps :class:`~hrn_pyg.rl.dynamics.PointMassDynamics`, a
development dynamics whose curves are not the paper's result.

Output (``--out``, default ``runs/rl/<task>/<mode>/seed<seed>``)::

    log.csv        one row per PPO update (CSVLog)
    policy.pt      actor, critic, optimiser, random states and the update count (atomic,
                   weights-only); running the command again continues the run from it; one of
                   another run (other settings or dynamics) stops the command with an error and
                   is kept (``--restart``: afresh)
    curve.png      the run's average episode length
    eval.csv       with --eval-every N: every N updates, the deterministic policy at rate 0 on
                   fixed evaluation scenes, in the learned model and in pybullet
                   (:mod:`hrn_pyg.rl.success_curve`)
    result.json    the final evaluation in the learned model (dropout off), the curve's metrics
                   (:func:`~hrn_pyg.rl.curves.curve_metrics`) and, with --model, the pybullet
                   ground-truth check

The sweeps over modes and seeds (``experiments/rl/sweep.py``) reuse :func:`add_training_arguments`,
:func:`setup_from_args` and :func:`train_from_args`.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from tensordict import TensorDictBase
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import Tensor, nn
from torchrl.collectors import Collector
from torchrl.envs import EnvBase
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from hrn_pyg.commands.rl import add_arguments, add_training_arguments  # noqa: F401  the command's arguments, here too
from hrn_pyg.rl.curves import curve_metrics, read_curve
from hrn_pyg.rl.dynamics import PointMassDynamics, StochasticDynamics
from hrn_pyg.rl.env import HRNEnv, near_miss_share, partial_hits
from hrn_pyg.rl.evaluate import evaluate_policy, ground_truth_success
from hrn_pyg.rl.success_curve import (
    EVAL_FIELDS,
    EvalConfig,
    curve_summary,
    evaluate_point,
    evaluation_env,
    read_eval,
)
from hrn_pyg.rl.tasks import MODES, UNRELAXED_MODES, TaskConfig, get_task
from hrn_pyg.sim.sleeping import DEFAULT_SLEEP
from hrn_pyg.utils.checkpoint import (
    load_checkpoint,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from hrn_pyg.utils.device import resolve_device
from hrn_pyg.utils.files import atomic_write_json, file_sha256, json_safe
from hrn_pyg.utils.metrics import CSVLog
from hrn_pyg.utils.options import progress_bar
from hrn_pyg.utils.schedules import LinearSchedule
from hrn_pyg.utils.stop import StopRequest
from hrn_pyg.viz import plot_curves

LOG_FIELDS = ["step", "update", "frames", "dropout_rate", "action_noise_std", "episodes",
              "mean_episode_length", "success_rate", "reward_mean", "loss_objective",
              "loss_critic", "loss_entropy", "partial_hit_share", "near_miss_share", "seconds"]


@dataclass(frozen=True)
class PPOConfig:
    """PPO hyper-parameters (standard clipped PPO; the seed paper does not give its own).

    ``frames_per_batch`` frames are collected per update from ``num_envs`` environments stepped
    together; the batch is used for ``epochs`` passes of ``frames_per_batch / minibatch`` gradient
    steps. ``threads`` caps torch's intra-op threads (the networks are tiny). ``gamma = 0.9``
    makes a shorter successful episode clearly worth more than a longer one. ``eval_every`` > 0
    evaluates the policy every that many updates on ``eval_scenes`` fixed scenes
    (:mod:`hrn_pyg.rl.success_curve`); neither is part of a run's identity.
    """

    updates: int = 100
    num_envs: int = 16
    frames_per_batch: int = 160
    epochs: int = 4
    minibatch: int = 64
    lr: float = 3e-3
    gamma: float = 0.9
    lmbda: float = 0.95
    clip_epsilon: float = 0.2
    entropy_coef: float = 1e-3
    critic_coef: float = 1.0
    max_grad_norm: float = 1.0
    hidden: int = 64
    action_noise_std: float = 0.1
    eval_episodes: int = 64
    ground_truth_episodes: int = 32
    checkpoint_every: int = 50
    threads: int = 1
    eval_every: int = 0
    eval_scenes: int = 32

    def __post_init__(self) -> None:
        for name in ("updates", "num_envs", "frames_per_batch", "epochs", "minibatch", "hidden",
                     "eval_episodes", "checkpoint_every", "threads"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.frames_per_batch % self.num_envs:
            raise ValueError(f"frames_per_batch ({self.frames_per_batch}) must be a multiple of "
                             f"num_envs ({self.num_envs})")
        if self.minibatch > self.frames_per_batch:
            raise ValueError(f"minibatch ({self.minibatch}) exceeds frames_per_batch "
                             f"({self.frames_per_batch})")
        if not (0 < self.gamma <= 1 and 0 <= self.lmbda <= 1 and self.lr > 0):
            raise ValueError("need 0 < gamma <= 1, 0 <= lmbda <= 1 and lr > 0")
        if self.action_noise_std < 0:
            raise ValueError(f"action_noise_std must be >= 0, got {self.action_noise_std}")
        if self.ground_truth_episodes < 0:
            raise ValueError(f"ground_truth_episodes must be >= 0, got {self.ground_truth_episodes}")
        EvalConfig(self.eval_every, self.eval_scenes)  # raises on bad evaluation settings

    @property
    def evaluation(self) -> EvalConfig:
        """The evaluation apart from training (:mod:`hrn_pyg.rl.success_curve`)."""
        return EvalConfig(every=self.eval_every, episodes=self.eval_scenes)


def mode_settings(mode: str, task: TaskConfig, config: PPOConfig,
                  anneal_updates: int | None = None, rate: float | None = None) -> tuple[LinearSchedule, float]:
    """The dropout schedule over PPO updates and the action-noise level of a mode; the
    stochastic modes start at ``rate`` (None: ``task.dropout_rate``). Whether a mode relaxes the
    reward is :data:`~hrn_pyg.rl.tasks.UNRELAXED_MODES` (:func:`mode_relaxes`)."""
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}; known: {', '.join(MODES)}")
    rate = task.dropout_rate if rate is None else float(rate)
    if not 0.0 <= rate < 1.0:
        raise ValueError(f"dropout rate must be in [0, 1), got {rate}")
    steps = task.anneal_updates if anneal_updates is None else anneal_updates
    if steps < 0:
        raise ValueError(f"anneal_updates must be >= 0, got {steps}")
    if mode == "deterministic":
        return LinearSchedule(0.0, 0.0, 0), 0.0
    if mode == "action_noise":
        return LinearSchedule(0.0, 0.0, 0), config.action_noise_std
    if mode in ("stochastic", "stochastic_unrelaxed"):
        return LinearSchedule(rate, rate, 0), 0.0
    return LinearSchedule(rate, 0.0, steps), 0.0


def mode_relaxes(mode: str) -> bool:
    """Whether a mode's environment relaxes the reward over the ``k`` samples."""
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}; known: {', '.join(MODES)}")
    return mode not in UNRELAXED_MODES


# ---------------------------------------------------------------------------- networks
def build_actor_critic(env: EnvBase, hidden: int) -> tuple[ProbabilisticActor, ValueOperator]:
    """Tanh-Gaussian policy and value MLPs (two hidden tanh layers) on ``"observation"``, on the
    environment's device."""
    obs_dim = env.observation_spec["observation"].shape[-1]
    act_dim = env.action_spec.shape[-1]
    actor_net = nn.Sequential(
        nn.Linear(obs_dim, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
        nn.Linear(hidden, 2 * act_dim), NormalParamExtractor(),
    ).to(env.device)
    actor = ProbabilisticActor(
        TensorDictModule(actor_net, in_keys=["observation"], out_keys=["loc", "scale"]),
        spec=env.action_spec, in_keys=["loc", "scale"], distribution_class=TanhNormal,
        distribution_kwargs={"low": env.action_spec.space.low[..., 0, :],
                             "high": env.action_spec.space.high[..., 0, :]},
        return_log_prob=True,
    )
    value_net = nn.Sequential(
        nn.Linear(obs_dim, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
        nn.Linear(hidden, 1),
    ).to(env.device)
    critic = ValueOperator(value_net, in_keys=["observation"])
    return actor, critic


def load_dynamics(task: TaskConfig, model: str | None,
                  device: str | torch.device = "cpu", sleep: bool = True, strict: bool = False) -> StochasticDynamics:
    """``None``: the point-mass development dynamics; a path or a shipped model's name: the
    learned HRN, on ``device``, with objects at rest asleep unless ``sleep=False``
    (:class:`~hrn_pyg.rl.hrn_dynamics.HRNDynamics`; ``strict``: a task scene outside the model's
    domain is an error)."""
    if model is None:
        return PointMassDynamics.for_task(task.scene_name, task.dropout_modules, device)
    from hrn_pyg.checkpoints import model_path
    from hrn_pyg.rl.hrn_dynamics import (
        HRNDynamics,  # pybullet and the model only when asked for
    )

    return HRNDynamics.from_checkpoint(model_path(model), task, device, sleep=DEFAULT_SLEEP if sleep else None,
                                       strict=strict)



# ---------------------------------------------------------------------------- training
def train(task: TaskConfig, mode: str, seed: int, config: PPOConfig, out_dir: Path,
          dynamics: StochasticDynamics | None = None, anneal_updates: int | None = None,
          progress: bool = True, device: str | torch.device | None = None,
          dropout_rate: float | None = None, restart: bool = False,
          init_policy: str | Path | None = None) -> dict:
    """One PPO run; writes ``log.csv``, ``policy.pt`` and ``curve.png`` under ``out_dir``.

    The environment, policy, critic and collector run on ``device`` (None: the dynamics'
    device, the CPU for the default point-mass dynamics), which must be the dynamics' device.
    The stochastic modes start at ``dropout_rate``; None: the dynamics' ``calibrated_rate``
    (a calibrated HRN), else the task's. Returns the final evaluation in the learned model
    with dropout off and no action noise.

    A run continues from ``out_dir/policy.pt`` when that holds the same run (:func:`resume_run`;
    written every ``checkpoint_every`` updates), also to extend a finished run to more
    ``updates``; a checkpoint of another run raises :class:`RunMismatch` and is kept;
    ``restart=True`` starts afresh.

    ``init_policy``: a policy checkpoint (:func:`load_init_policy`) whose actor
    the run starts from, the critic fresh; its SHA-256 is part of the run's identity.
    """
    if dynamics is None:
        dynamics = load_dynamics(task, None, "cpu" if device is None else device)
    if dropout_rate is None:
        dropout_rate = getattr(dynamics, "calibrated_rate", None)
    schedule, noise = mode_settings(mode, task, config, anneal_updates, dropout_rate)
    threads = torch.get_num_threads()
    torch.set_num_threads(config.threads)
    try:
        return _train(task, mode, seed, config, out_dir, dynamics, schedule, noise, progress, device, restart,
                      init_policy)
    finally:
        torch.set_num_threads(threads)


def _train(task: TaskConfig, mode: str, seed: int, config: PPOConfig, out_dir: Path,
           dynamics: StochasticDynamics, schedule: LinearSchedule, noise: float,
           progress: bool, device: str | torch.device | None, restart: bool = False,
           init_policy: str | Path | None = None) -> dict:
    torch.manual_seed(seed)
    env = HRNEnv(task, dynamics, batch_size=config.num_envs, dropout_rate=schedule(0),
                 action_noise_std=noise, relax=mode_relaxes(mode), seed=seed, device=device)
    actor, critic = build_actor_critic(env, config.hidden)
    init_sha = None
    if init_policy is not None:
        init_sha = load_init_policy(init_policy, actor, task)
    gae = GAE(gamma=config.gamma, lmbda=config.lmbda, value_network=critic, average_gae=True)
    loss_module = ClipPPOLoss(actor, critic, clip_epsilon=config.clip_epsilon,
                              entropy_bonus=config.entropy_coef > 0,
                              entropy_coeff=config.entropy_coef, critic_coeff=config.critic_coef,
                              loss_critic_type="smooth_l1")
    optim = torch.optim.Adam(loss_module.parameters(), lr=config.lr)
    out_dir.mkdir(parents=True, exist_ok=True)
    identity = run_identity(task, mode, seed, config, schedule, noise, dynamics, init_sha)
    meta = json.dumps({**identity, "ppo": asdict(config),
                       "init_policy": None if init_policy is None else str(init_policy)}, sort_keys=True)
    start_update = 0 if restart else resume_run(out_dir / "policy.pt", identity, actor, critic, optim, env)
    if start_update == 0:
        (out_dir / "log.csv").unlink(missing_ok=True)
        (out_dir / "eval.csv").unlink(missing_ok=True)
    log = CSVLog(out_dir / "log.csv", LOG_FIELDS)
    log.truncate_after(start_update - 1)  # rows past the checkpoint were never saved in it
    evaluation = config.evaluation
    eval_log, eval_env = None, None
    if evaluation.every:
        eval_log = CSVLog(out_dir / "eval.csv", EVAL_FIELDS)
        eval_log.truncate_after(start_update)  # keyed by updates done: the checkpoint's own row stays
        eval_env = evaluation_env(task, dynamics, evaluation, device=env.device)

    def evaluate(updates_done: int) -> None:
        row = evaluate_point(actor, eval_env, evaluation)
        eval_log.append({"step": updates_done, "update": updates_done,
                         "frames": updates_done * config.frames_per_batch, **row})

    if eval_log is not None and start_update == 0:
        evaluate(0)

    def checkpoint(update: int) -> None:
        save_checkpoint(out_dir / "policy.pt", {
            "model": {"actor": actor.state_dict(), "critic": critic.state_dict()},
            "optimizer": optim.state_dict(), "config": meta, "update": update,
            "rng": rng_state(), "env_rng": env.rng.get_state()})

    bar = _progress(config.updates, f"{task.name}/{mode}/seed{seed}", progress)
    if bar is not None:
        bar.update(start_update)
    start = time.perf_counter()
    env.dropout_rate = schedule(start_update)
    remaining = config.updates - start_update
    if remaining > 0:
        collector = Collector(env, actor, frames_per_batch=config.frames_per_batch,
                              total_frames=config.frames_per_batch * remaining,
                              device=env.device, auto_register_policy_transforms=False)
        # SIGINT / SIGTERM: finish the update under way, save it, then stop (rerun continues)
        with StopRequest() as stop:
            try:
                for update, batch in enumerate(collector, start=start_update):
                    rate = schedule(update)
                    stats = _ppo_update(batch, gae, loss_module, optim, config)
                    row = {"step": update, "update": update,
                           "frames": (update + 1) * config.frames_per_batch,
                           "dropout_rate": rate, "action_noise_std": noise,
                           **_episode_stats(batch, env.num_samples), **stats,
                           "seconds": time.perf_counter() - start}
                    log.append(row)
                    env.dropout_rate = schedule(update + 1)  # the rate the next batch is collected at
                    if eval_log is not None and evaluation.due(update + 1, config.updates):
                        evaluate(update + 1)
                    if (update + 1) % config.checkpoint_every == 0 or stop.requested:
                        checkpoint(update + 1)
                    if bar is not None:
                        bar.update(1)
                        bar.set_postfix(len=row.get("mean_episode_length", ""), p=f"{rate:.3f}")
                    if stop.requested:
                        raise KeyboardInterrupt(f"stopped after update {update + 1}; policy.pt holds it")
            finally:
                collector.shutdown()
                if bar is not None:
                    bar.close()
        checkpoint(config.updates)
    elif bar is not None:
        bar.close()
    plot_curves(out_dir / "log.csv", out_dir / "curve.png", x="update", ys=["mean_episode_length"],
                title=f"{task.name} / {mode} / seed {seed}", logy=False)
    env.dropout_rate, env.action_noise_std = 0.0, 0.0
    success, length = evaluate_policy(actor, env, config.eval_episodes)
    result = {"task": task.name, "mode": mode, "seed": seed, "updates": config.updates,
              "resumed_at": start_update, "init_policy_sha256": init_sha,
              "success_rate": success, "mean_episode_length": length,
              **curve_metrics(read_curve(out_dir / "log.csv"))}
    if eval_log is not None:
        result.update(json_safe(curve_summary(read_eval(out_dir / "eval.csv"))))  # None: never
    if hasattr(dynamics, "scene_seeds") and config.ground_truth_episodes > 0:
        result.update(ground_truth_success(actor, env, config.ground_truth_episodes, closed_loop=True))
    result["seconds"] = time.perf_counter() - start
    return result


def run_identity(task: TaskConfig, mode: str, seed: int, config: PPOConfig, schedule: LinearSchedule,
                 noise: float, dynamics: StochasticDynamics, init_policy_sha256: str | None = None) -> dict:
    """What a run is, for resuming: everything but the number of updates (so a finished run can
    be extended) and the evaluation sizes (they do not change training). ``init_policy_sha256``
    is the SHA-256 of the policy the actor started from, None for a fresh actor (a checkpoint
    written before the key existed reads as None, so its run still resumes)."""
    ppo = {k: v for k, v in asdict(config).items()
           if k not in ("updates", "eval_episodes", "ground_truth_episodes", "checkpoint_every",
                        "eval_every", "eval_scenes")}
    return {"task": task.to_dict(), "mode": mode, "seed": seed, "ppo_training": ppo,
            "schedule": asdict(schedule), "action_noise_std": noise, "dynamics": repr(dynamics),
            "init_policy_sha256": init_policy_sha256}


def load_init_policy(path: str | os.PathLike, actor: ProbabilisticActor,
                     task: str | TaskConfig) -> str:
    """Load the actor weights of a policy checkpoint (a clone, or a PPO run's ``policy.pt``)
    into ``actor`` and return the file's SHA-256.

    Raises ``FileNotFoundError`` or ``ValueError`` with a one-line message: a file that is not
    an hrn_pyg checkpoint, one without an actor, one made for another task, or whose actor
    does not fit (another hidden width or action size).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"--init-policy not found: {path}")
    task = get_task(task)
    digest = file_sha256(path)
    ckpt = load_checkpoint(path)
    weights = ckpt["model"].get("actor")
    if not isinstance(weights, dict):
        raise ValueError(f"{path} holds no actor (model.actor)")
    made_for = json.loads(ckpt["config"]).get("task")
    made_for = made_for.get("name") if isinstance(made_for, dict) else None
    if made_for is not None and made_for != task.name:
        raise ValueError(f"{path} is a policy for task {made_for!r}, not {task.name!r}")
    try:
        actor.load_state_dict(weights)
    except RuntimeError as exc:
        first = next((ln.strip() for ln in str(exc).splitlines()[1:] if ln.strip()), str(exc))
        raise ValueError(f"{path} does not fit this actor ({first})") from None
    return digest


class RunMismatch(ValueError):
    """A run folder's ``policy.pt`` belongs to another run than the one asked for."""


def resume_run(path: Path, identity: dict, actor: nn.Module, critic: nn.Module,
               optim: torch.optim.Optimizer, env: HRNEnv) -> int:
    """Load the checkpoint at ``path`` into the run when it is the same run (``identity``), and
    return the number of updates it holds; 0 (a fresh start) when there is none.

    A checkpoint of another run (any key of ``identity`` differs) or one without the random
    states raises :class:`RunMismatch` naming what differs: a run is never overwritten by
    accident (``restart=True`` of :func:`train`, ``--restart`` on the command line, starts
    afresh on purpose).

    Restored: actor, critic, Adam state, torch's random state and the environment's generator.
    Not restored: the episodes in flight when it was written. Like TorchRL's own collector
    (``Collector.load_state_dict``), a resumed run starts fresh episodes, so it is the same run
    in distribution, not bit for bit.
    """
    if not path.is_file():
        return 0
    ckpt = load_checkpoint(path)
    saved = json.loads(ckpt["config"])
    wanted = json.loads(json.dumps(identity, sort_keys=True))
    differ = sorted(k for k in wanted if saved.get(k) != wanted[k])
    if "rng" not in ckpt:
        differ.append("(no random states: written before runs could resume)")
    if differ:
        detail = "; ".join(f"{k}: saved {saved.get(k)!r}, now {wanted[k]!r}" for k in differ if k in wanted)
        raise RunMismatch(f"{path} holds another run ({', '.join(differ)} differ{': ' + detail if detail else ''}); "
                          "pass restart=True / --restart to overwrite it, or choose another output folder")
    actor.load_state_dict(ckpt["model"]["actor"])
    critic.load_state_dict(ckpt["model"]["critic"])
    optim.load_state_dict(ckpt["optimizer"])
    set_rng_state(ckpt["rng"])
    env.rng.set_state(ckpt["env_rng"])
    return int(ckpt["update"])


def _ppo_update(batch: TensorDictBase, gae: GAE, loss_module: ClipPPOLoss,
                optim: torch.optim.Optimizer, config: PPOConfig) -> dict[str, float]:
    """``epochs`` passes of clipped-PPO minibatch steps over one collected batch ``(B, T)``."""
    keys = ("loss_objective", "loss_critic", "loss_entropy")
    sums: dict[str, Tensor] = {}  # on the batch's device: read back once, after the update
    steps = 0
    for _ in range(config.epochs):
        with torch.no_grad():
            gae(batch)  # advantages from the current critic, along the time dimension
        flat = batch.reshape(-1)
        order = torch.randperm(flat.shape[0]).to(flat.device)  # the CPU stream on every device
        for idx in order.split(config.minibatch):
            losses = loss_module(flat[idx])
            total = losses["loss_objective"] + losses["loss_critic"] + losses.get(
                "loss_entropy", torch.zeros((), device=flat.device))
            optim.zero_grad()
            total.backward()
            nn.utils.clip_grad_norm_(loss_module.parameters(), config.max_grad_norm)
            optim.step()
            for key in keys:
                if key in losses.keys():
                    sums[key] = sums.get(key, 0.0) + losses[key].detach().double()
            steps += 1
    return {k: float(sums[k]) / steps if k in sums else 0.0 for k in keys}


def _episode_stats(batch: TensorDictBase, k: int) -> dict[str, float | int | str]:
    """Episodes that ended in this batch ``(B, T)``: count, mean length and success rate; and
    the batch's partial-hit share, the fraction of its ``B * T`` steps at which some but not
    all of the ``k`` samples met the goal, and its near-miss share, the same fraction of its
    steps with at least one sample in the goal (absent when there is none)."""
    done = batch["next", "done"].squeeze(-1)
    n = int(done.sum())
    hits = batch["next", "goal_hits"]
    share = partial_hits(hits, k).double().mean()
    out: dict[str, float | int | str] = {"episodes": n,
                                         "reward_mean": float(batch["next", "reward"].mean()),
                                         "partial_hit_share": float(share)}
    near = near_miss_share(hits, k)
    if near is not None:
        out["near_miss_share"] = near
    if n:
        out["mean_episode_length"] = float(batch["next", "t"].squeeze(-1)[done].float().mean())
        out["success_rate"] = float(batch["next", "terminated"].squeeze(-1)[done].float().mean())
    return out


def _progress(total: int, desc: str, enabled: bool):
    """The run's progress (:func:`~hrn_pyg.utils.options.progress_bar`: a bar on a terminal, lines
    in a log), or None with ``--no-progress``."""
    return progress_bar(total, desc, "upd") if enabled else None



# ---------------------------------------------------------------------------- CLI
@dataclass(frozen=True)
class RunSetup:
    """What every run of a command shares: the task, the PPO settings, the device and the
    dynamics (built once)."""

    task: TaskConfig
    config: PPOConfig
    device: torch.device
    dynamics: StochasticDynamics


def setup_from_args(args: argparse.Namespace) -> RunSetup:
    """Check the options of :func:`add_training_arguments` and build what the runs share."""
    task = get_task(args.task)
    if args.anneal_updates is not None and args.anneal_updates < 0:
        raise ValueError(f"--anneal-updates must be >= 0, got {args.anneal_updates}")
    if args.dropout_rate is not None and not 0.0 <= args.dropout_rate < 1.0:
        raise ValueError(f"--dropout-rate must be in [0, 1), got {args.dropout_rate}")
    if args.init_policy is not None and not Path(args.init_policy).is_file():
        raise FileNotFoundError(f"--init-policy not found: {args.init_policy}")
    config = PPOConfig(updates=args.updates, frames_per_batch=args.frames_per_batch,
                       num_envs=args.num_envs, epochs=args.epochs, minibatch=args.minibatch,
                       lr=args.lr, threads=args.threads, action_noise_std=args.action_noise_std,
                       eval_episodes=args.eval_episodes, ground_truth_episodes=args.ground_truth_episodes,
                       eval_every=args.eval_every, eval_scenes=args.eval_scenes)
    device = resolve_device(args.device)
    dynamics = load_dynamics(task, args.model, device, sleep=not args.no_sleep, strict=args.strict)
    return RunSetup(task, config, device, dynamics)


def train_from_args(args: argparse.Namespace, setup: RunSetup, mode: str, seed: int, out_dir: Path) -> dict:
    """One run of :func:`train` with the options of :func:`add_training_arguments`, its result
    printed in one line."""
    res = train(setup.task, mode, seed, setup.config, out_dir, setup.dynamics, args.anneal_updates,
                progress=not args.no_progress, device=setup.device, dropout_rate=args.dropout_rate,
                restart=args.restart, init_policy=args.init_policy)
    truth = (f", pybullet replay success {res['pybullet_success_rate']:.2f} length "
             f"{res['pybullet_mean_length']:.2f}, closed loop {res['closed_loop_success_rate']:.2f}"
             if "closed_loop_success_rate" in res else "")
    print(f"{setup.task.name} {mode} seed {seed}: success {res['success_rate']:.2f}, "
          f"mean length {res['mean_episode_length']:.2f}{truth} ({res['seconds']:.0f} s)", flush=True)
    return res


def run(args: argparse.Namespace) -> int:
    setup = setup_from_args(args)
    out = Path(args.out) if args.out else Path("runs/rl") / setup.task.name / args.mode / f"seed{args.seed}"
    result = train_from_args(args, setup, args.mode, args.seed, out)
    atomic_write_json(out / "result.json", json_safe(result))
    print(f"wrote {out}")
    return 0
