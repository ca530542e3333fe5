"""``hrn-pyg rl``: PPO in the (stochastic) learned environment, the seed paper's Figs. 7 and 8.

Built from TorchRL pieces: a :class:`~torchrl.modules.ProbabilisticActor` with a
:class:`~torchrl.modules.TanhNormal` head and a :class:`~torchrl.modules.ValueOperator`, a
single-process collector (``torchrl.collectors.Collector``, the 0.14 name of
``SyncDataCollector``), :class:`~torchrl.objectives.value.GAE` and
:class:`~torchrl.objectives.ClipPPOLoss`. Four modes:

- ``deterministic``: dropout rate 0.
- ``action_noise``: rate 0, Gaussian noise on the actions (``PPOConfig.action_noise_std`` of
  the force bound), the Plappert et al. baseline.
- ``stochastic``: the task's dropout rate held constant (cube_push: 0.1 on the force module).
- ``stochastic_annealed``: the task's rate brought linearly to 0 over ``anneal_updates`` PPO
  updates (tower: 0.1 -> 0 over 1200).

Without ``--model`` the environment steps :class:`~hrn_pyg.rl.dynamics.PointMassDynamics`, an
analytic **development / smoke-test** dynamics; its curves are not the paper's result.

Output (``--out``, default ``runs/rl/<task>``)::

    <mode>/seed<k>/log.csv        one row per PPO update (CSVLog)
    <mode>/seed<k>/policy.pt      actor + critic + optimiser (atomic, weights-only)
    <mode>/seed<k>/curve.png      this run's average episode length
    episode_length.png            every mode found under --out: median over seeds, range shaded
    summary.json                  per run: final evaluation in the learned model (dropout off),
                                  curve metrics (final average length, updates to reach it) and,
                                  with --model, the pybullet ground-truth check
    summary.csv, summary.md       the same per run, and per mode over seeds (median [min, max])

With ``--model``, each run ends with :func:`ground_truth_success`: the final policy's episodes
in the learned model (dropout 0) are replayed open loop in pybullet from the same start scene
and goal, and both success rates are reported side by side.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch
from tensordict import TensorDictBase
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import Tensor, nn
from torchrl.collectors import Collector
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from hrn_pyg.rl.dynamics import PointMassDynamics, StochasticDynamics
from hrn_pyg.rl.env import HRNEnv
from hrn_pyg.rl.tasks import TASKS, TaskConfig, action_to_forces, get_task, goal_reached
from hrn_pyg.utils.checkpoint import save_checkpoint
from hrn_pyg.utils.device import resolve_device
from hrn_pyg.utils.files import atomic_path, atomic_write_json, atomic_write_text
from hrn_pyg.utils.metrics import CSVLog, plot_curves
from hrn_pyg.utils.schedules import LinearSchedule
from hrn_pyg.viz import save_figure

MODES = ("deterministic", "action_noise", "stochastic", "stochastic_annealed")
#: trailing moving-average window (updates) of the episode-length curve for the summary metrics
#: and the figure
SMOOTH_UPDATES = 10
#: fraction of the last updates whose mean is a run's final average episode length
FINAL_FRACTION = 0.1
#: a run "reached its final length" when its smoothed curve has made this part of its drop
REACHED_FRACTION = 0.9
#: a drop (steps) smaller than this counts as no learning: updates_to_final is then None
MIN_DROP = 0.5
LOG_FIELDS = ["step", "update", "frames", "dropout_rate", "action_noise_std", "episodes",
              "mean_episode_length", "success_rate", "reward_mean", "loss_objective",
              "loss_critic", "loss_entropy", "seconds"]


@dataclass(frozen=True)
class PPOConfig:
    """PPO hyper-parameters (standard clipped PPO; the seed paper does not give its own).

    ``frames_per_batch`` frames are collected per update from ``num_envs`` environments stepped
    together (so ``frames_per_batch / num_envs`` steps each); the batch is then used for
    ``epochs`` passes of ``frames_per_batch / minibatch`` gradient steps. ``threads`` caps
    torch's intra-op threads during training: the networks are tiny, and more threads than free
    cores made one update ten times slower on the 2-core development machine.

    Defaults (docs/rl.md): one update collects one 10-step episode's worth of frames from 16
    environments (160 frames). With the learned cube_push HRN at k = 5 that was measured at
    about 0.8 s per update at rate 0.1 and 0.25 s at rate 0 (1 thread, 2 cores shared with a
    few other jobs), so a 100-update run takes under 2 minutes on a quiet core; on a machine
    oversubscribed ~5x it took ~4 s (rate 0) per update. ``gamma = 0.9`` makes a shorter
    successful episode clearly worth more than a longer one (0.9^3 vs 0.9^8 against 0.99^3 vs
    0.99^8) and ``lr = 3e-3``; with them PPO on the point-mass cube_push stand-in reached its
    final length in about 50 updates, where ``gamma = 0.99, lr = 1e-3`` had not started to
    learn after 150.
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


def mode_settings(mode: str, task: TaskConfig, config: PPOConfig,
                  anneal_updates: int | None = None) -> tuple[LinearSchedule, float]:
    """The dropout schedule over PPO updates and the action-noise level of a mode."""
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}; known: {', '.join(MODES)}")
    rate = task.dropout_rate
    steps = task.anneal_updates if anneal_updates is None else anneal_updates
    if steps < 0:
        raise ValueError(f"anneal_updates must be >= 0, got {steps}")
    if mode == "deterministic":
        return LinearSchedule(0.0, 0.0, 0), 0.0
    if mode == "action_noise":
        return LinearSchedule(0.0, 0.0, 0), config.action_noise_std
    if mode == "stochastic":
        return LinearSchedule(rate, rate, 0), 0.0
    return LinearSchedule(rate, 0.0, steps), 0.0


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
                  device: str | torch.device = "cpu") -> StochasticDynamics:
    """``None``: the point-mass development dynamics; a path: the learned HRN (when built); on
    ``device``."""
    if model is None:
        return PointMassDynamics.for_task(task.name, task.dropout_modules, device)
    path = Path(model)
    if not path.is_file():
        raise FileNotFoundError(f"--model checkpoint not found: {path}")
    try:
        from hrn_pyg.rl.hrn_dynamics import HRNDynamics  # added with the learned model
    except ModuleNotFoundError as exc:
        raise ValueError("--model needs hrn_pyg.rl.hrn_dynamics (the learned HRN dynamics), "
                         "which is not available in this version") from exc
    return HRNDynamics.from_checkpoint(path, task, device)


# ---------------------------------------------------------------------------- evaluation
@torch.no_grad()
def evaluate_policy(policy: TensorDictModule, env: HRNEnv, episodes: int) -> tuple[float, float]:
    """Success rate and mean episode length of the policy's deterministic actions.

    Runs rounds of ``B`` parallel episodes (:func:`record_episodes`), each for up to
    ``task.max_steps`` steps, and scores the first ``episodes``; an episode that never reaches the
    goal counts ``max_steps``. The environment is used as configured (set ``dropout_rate = 0``
    first to judge the deterministic model).
    """
    records = record_episodes(policy, env, episodes)
    success = sum(r["success"] for r in records) / len(records)
    length = sum(r["length"] for r in records) / len(records)
    return float(success), float(length)


def replay_in_pybullet(actions: Tensor, task: str | TaskConfig, seed: int,
                       goal: Tensor | None = None, history_steps: int = 0) -> dict:
    """Replay a policy's actions ``(T, A)`` in the ground-truth pybullet scene of ``task``.

    The ground-truth check of issue 6: builds ``hrn_pyg.data.scenes.make_scene(task, seed)``,
    applies one per-object force ``(O, 3)`` per step (the mapping the environment uses) and
    judges the task's goal on the object roots (mass-weighted leaf means; velocity = per-step
    displacement) after every step, stopping at the first success. ``goal`` ``(2,)`` is the
    episode's goal point; ``None`` is allowed only for ``tower``, whose goal point is the
    middle cube's initial position. For the comparison to mean anything the learned
    environment's episode must start from this scene's initial state (the learned dynamics'
    ``reset_states`` draws scenes by seed). ``history_steps`` zero-force steps are taken after
    the scene's reset before the first action: :class:`~hrn_pyg.rl.hrn_dynamics.HRNDynamics`
    starts its episodes after ``HISTORY_STEPS`` such steps (it needs ``x_{t-2}, x_{t-1}``), so
    the replay of one of its episodes passes that number.

    Returns ``{"success": bool, "steps": int, "roots": (steps + 1, O, 6) tensor,
    "leaves": (steps + 1, L, 3) tensor}`` (index 0: the start, after the history steps).
    """
    task = get_task(task)
    if history_steps < 0:
        raise ValueError(f"history_steps must be >= 0, got {history_steps}")
    from hrn_pyg.data.scenes import make_scene

    actions = torch.as_tensor(actions, dtype=torch.float32).cpu()  # pybullet takes numpy
    forces = action_to_forces(task, actions)                                  # (T, O, 3)
    scene = make_scene(task.name, seed)
    try:
        leaves = torch.as_tensor(scene.reset(), dtype=torch.float32)
        before = leaves
        for _ in range(history_steps):  # a loop over time steps
            before, leaves = leaves, torch.as_tensor(scene.step(scene.zero_action()), dtype=torch.float32)
        obj = torch.as_tensor(scene.leaf_object)
        mass = torch.as_tensor(scene.leaf_mass, dtype=torch.float32)

        def centres(x: Tensor) -> Tensor:  # (L, 3) -> (O, 3), mass-weighted per object
            num = torch.zeros(task.num_objects, 3).index_add_(0, obj, x * mass[:, None])
            den = torch.zeros(task.num_objects).index_add_(0, obj, mass)
            return num / den[:, None]

        prev = centres(leaves)
        roots = [torch.cat([prev, prev - centres(before)], -1)]
        frames = [leaves]
        if goal is None:
            if task.goal_kind != "displaced":
                raise ValueError(f"goal: task {task.name!r} needs the episode's goal point")
            goal = prev[task.goal_objects[0], :2]
        goal = torch.as_tensor(goal, dtype=torch.float32).cpu()
        success = False
        for f in forces:
            frames.append(torch.as_tensor(scene.step(f.double().numpy()), dtype=torch.float32))
            now = centres(frames[-1])
            roots.append(torch.cat([now, now - prev], -1))
            prev = now
            if bool(goal_reached(task, roots[-1], goal)):
                success = True
                break
    finally:
        scene.close()
    return {"success": success, "steps": len(roots) - 1, "roots": torch.stack(roots),
            "leaves": torch.stack(frames)}


@torch.no_grad()
def record_episodes(policy: TensorDictModule, env: HRNEnv, episodes: int) -> list[dict]:
    """Run the policy's deterministic actions in ``env`` and keep everything a replay needs.

    The environment is used as configured, on its device; the records are CPU tensors (ready
    for :func:`replay_in_pybullet` and numpy). Per episode: ``seed`` (the pybullet scene it started
    from, ``env.dynamics.scene_seeds``; -1 for dynamics without one), ``goal`` ``(2,)``,
    ``actions`` ``(T, A)`` (clipped to the action bounds, as the environment applies them),
    ``states`` ``(T + 1, S)`` (start, then after each action), ``success`` (bool: the episode
    ended by reaching the goal) and ``length`` ``T`` (steps until it ended).
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    B, bound = env.batch_size[0], env.task.max_force
    out: list[dict] = []
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        while len(out) < episodes:
            td = env.reset()
            seeds = (env.dynamics.scene_seeds(td["state"]) if hasattr(env.dynamics, "scene_seeds")
                     else torch.full((B,), -1, dtype=torch.long))
            goal = td["goal"].clone()
            states, actions = [td["state"].clone()], []
            finished = torch.zeros(B, dtype=torch.bool, device=env.device)
            success = torch.zeros_like(finished)
            length = torch.full((B,), env.task.max_steps, dtype=torch.int64, device=env.device)
            for _ in range(env.task.max_steps):  # a loop over time steps
                td = env.step(policy(td))
                actions.append(td["action"].clamp(-bound, bound).clone())
                states.append(td["next", "state"].clone())
                done = td["next", "done"].squeeze(-1) & ~finished
                success |= done & td["next", "terminated"].squeeze(-1)
                length = torch.where(done, td["next", "t"].squeeze(-1), length)
                finished |= done
                if finished.all():
                    break
                td = step_mdp(td)
            # back to the CPU once per round: (B, T, A), (B, T+1, S)
            actions_t, states_t = torch.stack(actions, 1).cpu(), torch.stack(states, 1).cpu()
            seeds, goal, success, length = seeds.cpu(), goal.cpu(), success.cpu(), length.cpu()
            for i in range(B):  # a loop over finished episodes, to split them by length
                n = int(length[i])
                out.append({"seed": int(seeds[i]), "goal": goal[i], "actions": actions_t[i, :n],
                            "states": states_t[i, :n + 1], "success": bool(success[i]), "length": n})
    return out[:episodes]


def ground_truth_success(policy: TensorDictModule, env: HRNEnv, episodes: int) -> dict[str, float]:
    """The ground-truth check: the policy's learned-model episodes replayed in pybullet.

    Runs ``episodes`` deterministic episodes in the learned environment with dropout 0 and no
    action noise (:func:`record_episodes`; the environment's settings are restored after),
    then replays each episode's actions open loop in the pybullet scene it started from, after
    the same ``HISTORY_STEPS`` zero-force steps, against the same goal
    (:func:`replay_in_pybullet`). An episode that failed or ran to ``max_steps`` counts as
    length ``max_steps`` on either side (the convention of :func:`evaluate_policy`).

    Returns ``model_success_rate``, ``model_mean_length``, ``pybullet_success_rate``,
    ``pybullet_mean_length`` and ``agreement`` (fraction of episodes where both judge the same),
    plus ``ground_truth_episodes``.
    """
    from hrn_pyg.rl.hrn_dynamics import HISTORY_STEPS

    saved = env.dropout_rate, env.action_noise_std
    env.dropout_rate, env.action_noise_std = 0.0, 0.0
    try:
        records = record_episodes(policy, env, episodes)
    finally:
        env.dropout_rate, env.action_noise_std = saved
    max_steps = env.task.max_steps
    model_ok, model_len, real_ok, real_len = [], [], [], []
    for rec in records:  # one pybullet scene per episode
        replay = replay_in_pybullet(rec["actions"], env.task, rec["seed"], rec["goal"],
                                    history_steps=HISTORY_STEPS)
        model_ok.append(rec["success"])
        model_len.append(rec["length"] if rec["success"] else max_steps)
        real_ok.append(replay["success"])
        real_len.append(replay["steps"] if replay["success"] else max_steps)
    n = len(records)
    return {
        "ground_truth_episodes": n,
        "model_success_rate": sum(model_ok) / n,
        "model_mean_length": sum(model_len) / n,
        "pybullet_success_rate": sum(real_ok) / n,
        "pybullet_mean_length": sum(real_len) / n,
        "agreement": sum(a == b for a, b in zip(model_ok, real_ok)) / n,
    }


# ---------------------------------------------------------------------------- training
def train(task: TaskConfig, mode: str, seed: int, config: PPOConfig, out_dir: Path,
          dynamics: StochasticDynamics | None = None, anneal_updates: int | None = None,
          progress: bool = True, device: str | torch.device | None = None) -> dict:
    """One PPO run; writes ``log.csv``, ``policy.pt`` and ``curve.png`` under ``out_dir``.

    The environment, policy, critic and collector run on ``device`` (None: the dynamics'
    device, the CPU for the default point-mass dynamics), which must be the dynamics' device.
    Returns the final evaluation in the learned model with dropout off and no action noise.
    """
    schedule, noise = mode_settings(mode, task, config, anneal_updates)
    if dynamics is None:
        dynamics = load_dynamics(task, None, "cpu" if device is None else device)
    threads = torch.get_num_threads()
    torch.set_num_threads(config.threads)
    try:
        return _train(task, mode, seed, config, out_dir, dynamics, schedule, noise, progress, device)
    finally:
        torch.set_num_threads(threads)


def _train(task: TaskConfig, mode: str, seed: int, config: PPOConfig, out_dir: Path,
           dynamics: StochasticDynamics, schedule: LinearSchedule, noise: float,
           progress: bool, device: str | torch.device | None) -> dict:
    torch.manual_seed(seed)
    env = HRNEnv(task, dynamics, batch_size=config.num_envs, dropout_rate=schedule(0),
                 action_noise_std=noise, seed=seed, device=device)
    actor, critic = build_actor_critic(env, config.hidden)
    collector = Collector(env, actor, frames_per_batch=config.frames_per_batch,
                          total_frames=config.frames_per_batch * config.updates,
                          device=env.device, auto_register_policy_transforms=False)
    gae = GAE(gamma=config.gamma, lmbda=config.lmbda, value_network=critic, average_gae=True)
    loss_module = ClipPPOLoss(actor, critic, clip_epsilon=config.clip_epsilon,
                              entropy_bonus=config.entropy_coef > 0,
                              entropy_coeff=config.entropy_coef, critic_coeff=config.critic_coef,
                              loss_critic_type="smooth_l1")
    optim = torch.optim.Adam(loss_module.parameters(), lr=config.lr)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "log.csv").unlink(missing_ok=True)
    log = CSVLog(out_dir / "log.csv", LOG_FIELDS)
    meta = json.dumps({"task": task.to_dict(), "mode": mode, "seed": seed, "ppo": asdict(config),
                       "schedule": asdict(schedule), "action_noise_std": noise,
                       "dynamics": repr(dynamics)}, sort_keys=True)

    def checkpoint(update: int) -> None:
        save_checkpoint(out_dir / "policy.pt", {
            "model": {"actor": actor.state_dict(), "critic": critic.state_dict()},
            "optimizer": optim.state_dict(), "config": meta, "update": update})

    bar = _progress(config.updates, f"{task.name}/{mode}/seed{seed}", progress)
    start = time.perf_counter()
    try:
        for update, batch in enumerate(collector):
            rate = schedule(update)
            stats = _ppo_update(batch, gae, loss_module, optim, config)
            row = {"step": update, "update": update, "frames": (update + 1) * config.frames_per_batch,
                   "dropout_rate": rate, "action_noise_std": noise,
                   **_episode_stats(batch), **stats, "seconds": time.perf_counter() - start}
            log.append(row)
            env.dropout_rate = schedule(update + 1)  # the rate the next batch is collected at
            if (update + 1) % config.checkpoint_every == 0:
                checkpoint(update + 1)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(len=row.get("mean_episode_length", ""), p=f"{rate:.3f}")
    finally:
        collector.shutdown()
        if bar is not None:
            bar.close()
    checkpoint(config.updates)
    plot_curves(out_dir / "log.csv", out_dir / "curve.png", x="update", ys=["mean_episode_length"],
                title=f"{task.name} / {mode} / seed {seed}", logy=False)
    env.dropout_rate, env.action_noise_std = 0.0, 0.0
    success, length = evaluate_policy(actor, env, config.eval_episodes)
    result = {"task": task.name, "mode": mode, "seed": seed, "updates": config.updates,
              "success_rate": success, "mean_episode_length": length,
              **curve_metrics(_read_curve(out_dir / "log.csv"))}
    if hasattr(dynamics, "scene_seeds") and config.ground_truth_episodes > 0:
        result.update(ground_truth_success(actor, env, config.ground_truth_episodes))
    result["seconds"] = time.perf_counter() - start
    return result


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


def _episode_stats(batch: TensorDictBase) -> dict[str, float | int | str]:
    """Episodes that ended in this batch: count, mean length and success rate."""
    done = batch["next", "done"].squeeze(-1)
    n = int(done.sum())
    out: dict[str, float | int | str] = {"episodes": n,
                                         "reward_mean": float(batch["next", "reward"].mean())}
    if n:
        out["mean_episode_length"] = float(batch["next", "t"].squeeze(-1)[done].float().mean())
        out["success_rate"] = float(batch["next", "terminated"].squeeze(-1)[done].float().mean())
    return out


def _progress(total: int, desc: str, enabled: bool):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="upd", leave=False)


# ---------------------------------------------------------------------------- figure
def plot_episode_length(out_root: str | Path, png_path: str | Path, title: str = "",
                        window: int = SMOOTH_UPDATES) -> list[str]:
    """Average episode length against PPO updates, one line per mode found under ``out_root``.

    Reads ``<mode>/seed*/log.csv`` and smooths each seed's curve with a trailing moving average
    over ``window`` updates (1: raw); the line is the median over seeds, the shaded band their
    range (min to max), over the updates every seed has reached. Returns the modes drawn.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_root = Path(out_root)
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=110)
    drawn = []
    for mode in MODES:
        curves = [_read_curve(p) for p in sorted((out_root / mode).glob("seed*/log.csv"))]
        curves = [smooth(c, window) for c in curves if c]
        if not curves:
            continue
        n = min(len(c) for c in curves)
        values = torch.tensor([c[:n] for c in curves], dtype=torch.float64)  # (seeds, updates)
        x = torch.arange(n)
        med = values.nanmedian(0).values
        lo = torch.where(values.isnan(), math.inf, values).min(0).values
        hi = torch.where(values.isnan(), -math.inf, values).max(0).values
        line, = ax.plot(x, med, lw=1.3, label=f"{mode} (n={len(curves)})")
        ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.2, lw=0)
        drawn.append(mode)
    ax.set_xlabel("PPO update")
    ax.set_ylabel("average episode length" + (f"\n({window}-update moving average)" if window > 1 else ""))
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if drawn:
        ax.legend(frameon=False, fontsize=8)
    fig.tight_layout()
    save_figure(fig, png_path)
    return drawn


def _read_curve(path: Path) -> list[float]:
    with open(path, newline="") as fh:
        return [float(r["mean_episode_length"]) if r.get("mean_episode_length") else math.nan
                for r in csv.DictReader(fh)]


# ---------------------------------------------------------------------------- summaries


def smooth(curve: list[float], window: int = SMOOTH_UPDATES) -> list[float]:
    """Trailing moving average that skips NaN (updates in which no episode ended)."""
    out = []
    for i in range(len(curve)):  # a loop over updates (a few hundred)
        part = [v for v in curve[max(0, i - window + 1):i + 1] if not math.isnan(v)]
        out.append(sum(part) / len(part) if part else math.nan)
    return out


def updates_to_reach(curve: list[float], level: float, window: int = SMOOTH_UPDATES) -> int | None:
    """First update at which the smoothed curve is at or below ``level``; None if never.

    Only full windows count (updates ``window - 1`` on): an average of the first one or two
    noisy updates would otherwise "reach" a level by chance.
    """
    smoothed = smooth(curve, window)
    for i in range(min(window, len(curve)) - 1, len(curve)):
        if smoothed[i] <= level:
            return i
    return None


def curve_metrics(curve: list[float]) -> dict[str, float | int | None]:
    r"""Final average episode length and the updates taken to reach it.

    With :math:`\bar L` the curve smoothed over :data:`SMOOTH_UPDATES`, :math:`L_0` the mean of
    its first :data:`SMOOTH_UPDATES` values and :math:`L_f` the mean of the last
    :data:`FINAL_FRACTION` of updates,
    ``updates_to_final`` is the first update with
    :math:`\bar L \le L_f + (1 - \rho)(L_0 - L_f)`, :math:`\rho` = :data:`REACHED_FRACTION`
    (None when :math:`L_0 - L_f <` :data:`MIN_DROP` steps: the run did not learn).
    """
    values = [v for v in curve if not math.isnan(v)]
    if not values:
        return {"final_length": None, "start_length": None, "updates_to_final": None}
    tail = max(1, round(FINAL_FRACTION * len(curve)))
    last = [v for v in curve[-tail:] if not math.isnan(v)] or values[-1:]
    final = sum(last) / len(last)
    head = [v for v in curve[:SMOOTH_UPDATES] if not math.isnan(v)] or values[:1]
    start = sum(head) / len(head)
    reached = None
    if start - final >= MIN_DROP:
        reached = updates_to_reach(curve, final + (1 - REACHED_FRACTION) * (start - final))
    return {"final_length": final, "start_length": start, "updates_to_final": reached}


SUMMARY_FIELDS = ["task", "mode", "seed", "updates", "start_length", "final_length",
                  "updates_to_final", "success_rate", "mean_episode_length", "model_success_rate",
                  "model_mean_length", "pybullet_success_rate", "pybullet_mean_length", "agreement",
                  "ground_truth_episodes", "seconds"]


def _stat(values: list) -> str:
    """``median [min, max]`` of the non-missing values; ``-`` if none."""
    vals = sorted(float(v) for v in values if v is not None and not math.isnan(float(v)))
    if not vals:
        return "-"
    n = len(vals)
    med = vals[n // 2] if n % 2 else 0.5 * (vals[n // 2 - 1] + vals[n // 2])
    return f"{med:.2f} [{vals[0]:.2f}, {vals[-1]:.2f}]"


def write_summary(out_root: str | Path, results: list[dict]) -> None:
    """``summary.csv`` (one row per run) and ``summary.md`` (per mode over seeds) under ``out_root``.

    Curve metrics are recomputed from each run's ``log.csv`` where it exists. The markdown
    table gives, per mode, the median over seeds with the range: the final average
    episode length of training, the updates to reach it (:func:`curve_metrics`; seeds whose
    curve dropped less than :data:`MIN_DROP` are counted as "no drop" and left out of the
    median), the updates for the smoothed curve to reach the deterministic mode's median final
    length ("never" counted the same way), and the final
    policy's success rate and mean length in the learned model and replayed in pybullet.
    """
    out_root = Path(out_root)
    rows = sorted(results, key=lambda r: (MODES.index(r["mode"]) if r["mode"] in MODES else 99,
                                          r["seed"]))
    for i, r in enumerate(rows):  # curve metrics from the logs, as they are now
        log = out_root / r["mode"] / f"seed{r['seed']}" / "log.csv"
        if log.is_file():
            rows[i] = {**r, **curve_metrics(_read_curve(log))}
    with atomic_path(out_root / "summary.csv", suffix=".csv") as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=SUMMARY_FIELDS, extrasaction="ignore")
            w.writeheader()
            w.writerows(rows)
    finals = [r.get("final_length") for r in rows if r["mode"] == "deterministic"]
    level = _stat(finals).split(" ")[0]
    level_f = float(level) if level != "-" else None
    lines = [f"# {rows[0]['task'] if rows else ''} RL summary (median [min, max] over seeds)", "",
             "| mode | seeds | final avg. length | updates to final | updates to det. final"
             f" ({level}) | success (model) | length (model) | success (pybullet) |"
             " length (pybullet) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for mode in MODES:
        runs = [r for r in rows if r["mode"] == mode]
        if not runs:
            continue
        to_level = []
        for r in runs:
            log = out_root / mode / f"seed{r['seed']}" / "log.csv"
            if level_f is not None and log.is_file():
                to_level.append(updates_to_reach(_read_curve(log), level_f))
        never = sum(v is None for v in to_level)
        reach = _stat(to_level) + (f" ({never} never)" if never else "")
        no_drop = sum(r.get("updates_to_final") is None for r in runs)
        flat = f" ({no_drop} no drop)" if no_drop else ""
        lines.append(
            f"| {mode} | {len(runs)} | {_stat([r.get('final_length') for r in runs])} | "
            f"{_stat([r.get('updates_to_final') for r in runs])}{flat} | {reach} | "
            f"{_stat([r.get('model_success_rate', r.get('success_rate')) for r in runs])} | "
            f"{_stat([r.get('model_mean_length', r.get('mean_episode_length')) for r in runs])} | "
            f"{_stat([r.get('pybullet_success_rate') for r in runs])} | "
            f"{_stat([r.get('pybullet_mean_length') for r in runs])} |")
    atomic_write_text(out_root / "summary.md", "\n".join(lines) + "\n")


# ---------------------------------------------------------------------------- CLI
def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = PPOConfig()
    parser.add_argument("--task", choices=sorted(TASKS), default="cube_push")
    parser.add_argument("--mode", nargs="+", choices=MODES, default=list(MODES),
                        help="one or more modes (default: all four)")
    parser.add_argument("--seeds", type=int, default=3, help="number of seeds per mode")
    parser.add_argument("--seed-start", type=int, default=0)
    parser.add_argument("--updates", type=int, default=d.updates, help="PPO updates per run")
    parser.add_argument("--frames-per-batch", type=int, default=d.frames_per_batch)
    parser.add_argument("--num-envs", type=int, default=d.num_envs)
    parser.add_argument("--epochs", type=int, default=d.epochs)
    parser.add_argument("--minibatch", type=int, default=d.minibatch)
    parser.add_argument("--lr", type=float, default=d.lr)
    parser.add_argument("--threads", type=int, default=d.threads, help="torch threads per run")
    parser.add_argument("--action-noise-std", type=float, default=d.action_noise_std,
                        help="action_noise mode: noise std as a fraction of the force bound")
    parser.add_argument("--anneal-updates", type=int, default=None,
                        help="stochastic_annealed: updates to reach rate 0 (default: the task's)")
    parser.add_argument("--eval-episodes", type=int, default=d.eval_episodes)
    parser.add_argument("--ground-truth-episodes", type=int, default=d.ground_truth_episodes,
                        help="with --model: final-policy episodes replayed in pybullet (0: none)")
    parser.add_argument("--model", default=None,
                        help="learned HRN checkpoint; absent: point-mass development dynamics")
    parser.add_argument("--out", default=None, help="output folder (default runs/rl/<task>)")
    parser.add_argument("--device", default=None,
                        help="torch device, e.g. cpu, cuda, cuda:1 (default: cuda if available, else cpu)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    task = get_task(args.task)
    if args.seeds < 1:
        raise ValueError(f"--seeds must be >= 1, got {args.seeds}")
    if args.anneal_updates is not None and args.anneal_updates < 0:
        raise ValueError(f"--anneal-updates must be >= 0, got {args.anneal_updates}")
    config = replace(PPOConfig(), updates=args.updates, frames_per_batch=args.frames_per_batch,
                     num_envs=args.num_envs, epochs=args.epochs, minibatch=args.minibatch,
                     lr=args.lr, threads=args.threads, action_noise_std=args.action_noise_std,
                     eval_episodes=args.eval_episodes,
                     ground_truth_episodes=args.ground_truth_episodes)
    device = resolve_device(args.device)
    modes = list(dict.fromkeys(args.mode))
    dynamics = load_dynamics(task, args.model, device)
    out = Path(args.out) if args.out else Path("runs/rl") / task.name
    results = []
    for mode in modes:
        for seed in range(args.seed_start, args.seed_start + args.seeds):
            res = train(task, mode, seed, config, out / mode / f"seed{seed}", dynamics,
                        args.anneal_updates, progress=not args.no_progress, device=device)
            results.append(res)
            truth = (f", pybullet success {res['pybullet_success_rate']:.2f} length "
                     f"{res['pybullet_mean_length']:.2f}" if "pybullet_success_rate" in res else "")
            print(f"{task.name} {mode} seed {seed}: success {res['success_rate']:.2f}, "
                  f"mean length {res['mean_episode_length']:.2f}{truth} ({res['seconds']:.0f} s)",
                  flush=True)
    summary_path = out / "summary.json"
    previous = json.loads(summary_path.read_text()) if summary_path.is_file() else []
    keep = [r for r in previous if (r.get("mode"), r.get("seed")) not in
            {(r2["mode"], r2["seed"]) for r2 in results}]
    atomic_write_json(summary_path, keep + results)
    write_summary(out, keep + results)
    drawn = plot_episode_length(out, out / "episode_length.png",
                                title=f"{task.name}: average episode length"
                                + ("" if args.model else " (point-mass dynamics)"))
    print(f"wrote {out / 'episode_length.png'} ({', '.join(drawn)})")
    return 0
