"""Ground-truth evaluation of a trained policy: its episodes in the learned environment and the
same actions replayed in pybullet.

- :func:`record_episodes` runs the policy's deterministic actions in an
  :class:`~hrn_pyg.rl.env.HRNEnv` and keeps everything a replay needs (start scene seed, goal,
  actions, states, outcome).
- :func:`evaluate_policy` scores those episodes: success rate and mean length in the
  environment as configured.
- :func:`replay_in_pybullet` applies one episode's actions open loop in the pybullet scene it
  started from and judges the task's goal there.
- :func:`closed_loop_in_pybullet` runs the policy itself in that pybullet scene: every step it
  sees pybullet's own object roots, so it is judged by what it does in physics, apart from the
  drift between the learned model and pybullet that an open-loop replay accumulates. Its loop,
  :func:`control_in_pybullet`, takes any acting function of pybullet's frames (the planners'
  too).
- :func:`ground_truth_success` puts them side by side (the check ``hrn-pyg rl --model`` runs
  after training).

Training lives in :mod:`hrn_pyg.rl.ppo`, the learning curve's metrics in
:mod:`hrn_pyg.rl.curves`.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import Tensor
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from hrn_pyg.data.graph import HISTORY, object_centres
from hrn_pyg.rl.env import HRNEnv
from hrn_pyg.rl.tasks import (
    TaskConfig,
    action_to_forces,
    get_task,
    goal_held,
    goal_reached,
    goal_streak,
)


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

    The ground-truth check of a policy: builds ``hrn_pyg.data.scene_file.make_scene(task, seed)``,
    applies one per-object force ``(O, 3)`` per step (the mapping the environment uses) and
    judges the task's goal on the object roots (mass-weighted leaf means; velocity = per-step
    displacement) after every step, stopping at the first success (the ``hold_steps``-th
    goal-reaching step in a row). ``goal`` ``(2,)`` is the
    episode's goal point; ``None`` is allowed only for ``tower``, whose goal point is the
    middle cube's initial position. For the comparison to mean anything the learned
    environment's episode must start from this scene's initial state (the learned dynamics'
    ``reset_states`` draws scenes by seed). ``history_steps`` zero-force steps are taken after
    the scene's reset before the first action: :class:`~hrn_pyg.rl.hrn_dynamics.HRNDynamics`
    starts its episodes after ``HISTORY`` such steps (it needs ``x_{t-2}, x_{t-1}``), so
    the replay of one of its episodes passes that number.

    Returns ``{"success": bool, "steps": int, "roots": (steps + 1, O, 6) tensor,
    "leaves": (steps + 1, L, 3) tensor}`` (index 0: the start, after the history steps).
    """
    task = get_task(task)
    if history_steps < 0:
        raise ValueError(f"history_steps must be >= 0, got {history_steps}")
    from hrn_pyg.data.scene_file import make_scene

    actions = torch.as_tensor(actions, dtype=torch.float32).cpu()  # pybullet takes numpy
    forces = action_to_forces(task, actions)                                  # (T, O, 3)
    scene = make_scene(task.scene_name, seed)
    try:
        leaves = torch.as_tensor(scene.reset(), dtype=torch.float32)
        before = leaves
        for _ in range(history_steps):  # a loop over time steps
            before, leaves = leaves, torch.as_tensor(scene.step(scene.zero_action()), dtype=torch.float32)
        obj = torch.as_tensor(scene.leaf_object)
        mass = torch.as_tensor(scene.leaf_mass, dtype=torch.float32)

        def centres(x: Tensor) -> Tensor:  # (L, 3) -> (O, 3), mass-weighted per object
            return object_centres(x, obj, task.num_objects, mass)

        prev = centres(leaves)
        roots = [torch.cat([prev, prev - centres(before)], -1)]
        frames = [leaves]
        if goal is None:
            if task.goal_kind != "displaced":
                raise ValueError(f"goal: task {task.name!r} needs the episode's goal point")
            goal = prev[task.goal_objects[0], :2]
        goal = torch.as_tensor(goal, dtype=torch.float32).cpu()
        success, held = False, 0
        for f in forces:
            frames.append(torch.as_tensor(scene.step(f.double().numpy()), dtype=torch.float32))
            now = centres(frames[-1])
            roots.append(torch.cat([now, now - prev], -1))
            prev = now
            held = goal_streak(held, bool(goal_reached(task, roots[-1], goal)))
            if goal_held(task, held):
                success = True
                break
    finally:
        scene.close()
    return {"success": success, "steps": len(roots) - 1, "roots": torch.stack(roots),
            "leaves": torch.stack(frames)}


#: a policy as a function of observations ``(B, O*6 + 2)`` -> actions ``(B, A)``
ActionFn = Callable[[Tensor], Tensor]


def deterministic_actions(policy: TensorDictModule) -> ActionFn:
    """The policy's deterministic action as a plain function of observations; the observations
    go to the policy's device, the actions come back to the CPU."""
    device = next(iter(policy.parameters()), torch.empty(0)).device

    @torch.no_grad()
    def act(observation: Tensor) -> Tensor:
        td = TensorDict({"observation": observation.to(device)}, batch_size=observation.shape[:1])
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            return policy(td)["action"].cpu()

    return act


#: an acting function of :func:`control_in_pybullet`: pybullet's frames of leaf positions so far
#: (each ``(L, 3)``) and the objects' roots now ``(O, 6)`` -> the action ``(A,)``
FrameActionFn = Callable[[list[Tensor], Tensor], Tensor]


def control_in_pybullet(act: FrameActionFn, task: str | TaskConfig, seed: int, goal: Tensor,
                        history_steps: int = HISTORY) -> dict:
    """Control the pybullet scene ``seed`` of ``task`` closed loop against ``goal`` ``(2,)``.

    After the scene's reset and ``history_steps`` zero-force steps (as the learned episodes
    start), every control step ``act`` sees pybullet's frames of leaves so far and the objects'
    roots (mass-weighted leaf means and their last displacement), its action is clipped to the
    force bound and applied, and the goal is judged on pybullet's roots, for up to
    ``task.max_steps`` steps or until the goal is held.

    Returns ``success``, ``steps`` (``max_steps`` when the goal was never held), ``actions``
    ``(T, A)``, ``roots`` ``(T + 1, O, 6)``, and per control step the seconds ``act`` took
    (``act_seconds``) and the seconds of pybullet's step (``physics_seconds``).
    """
    task = get_task(task)
    if history_steps < 0:
        raise ValueError(f"history_steps must be >= 0, got {history_steps}")
    from hrn_pyg.data.scene_file import make_scene

    goal = torch.as_tensor(goal, dtype=torch.float32).cpu().reshape(2)
    scene = make_scene(task.scene_name, seed)
    try:
        frames = [torch.as_tensor(scene.reset(), dtype=torch.float32)]  # the objects exist from here on
        obj = torch.as_tensor(scene.leaf_object)
        mass = torch.as_tensor(scene.leaf_mass, dtype=torch.float32)
        for _ in range(history_steps):  # a loop over time steps
            frames.append(torch.as_tensor(scene.step(scene.zero_action()), dtype=torch.float32))

        def roots_now() -> Tensor:  # (O, 6) from the last two frames (one at the start)
            c = object_centres(torch.stack(frames[-2:]), obj, task.num_objects, mass)
            return torch.cat([c[-1], c[-1] - c[0]], -1)

        roots, actions, act_s, physics_s = [roots_now()], [], [], []
        held, success = 0, False  # goal-reaching steps in a row
        for _ in range(task.max_steps):  # a loop over control steps
            start = time.perf_counter()
            action = act(frames, roots[-1]).reshape(task.action_dim).clamp(-task.max_force, task.max_force)
            act_s.append(time.perf_counter() - start)
            forces = action_to_forces(task, action.unsqueeze(0))[0]
            start = time.perf_counter()
            leaves = scene.step(forces.double().numpy())
            physics_s.append(time.perf_counter() - start)
            frames.append(torch.as_tensor(leaves, dtype=torch.float32))
            actions.append(action)
            roots.append(roots_now())
            held = goal_streak(held, bool(goal_reached(task, roots[-1], goal)))
            if goal_held(task, held):
                success = True
                break
    finally:
        scene.close()
    return {"success": success, "steps": len(actions) if success else task.max_steps,
            "actions": torch.stack(actions), "roots": torch.stack(roots),
            "act_seconds": act_s, "physics_seconds": physics_s}


@torch.no_grad()
def closed_loop_in_pybullet(act: ActionFn, task: str | TaskConfig, seed: int, goal: Tensor,
                            history_steps: int = HISTORY) -> dict:
    """Run a policy closed loop in the pybullet scene ``seed`` against ``goal`` ``(2,)``.

    The loop of :func:`control_in_pybullet`: every step the policy ``act`` sees the observation
    built from pybullet's own roots and the goal (the layout of :class:`~hrn_pyg.rl.env.HRNEnv`)
    and returns an action ``(1, A)``; the goal is judged as in :func:`replay_in_pybullet`.
    Returns ``{"success": bool, "steps": int}`` (``max_steps`` when the goal was never reached).
    """
    goal = torch.as_tensor(goal, dtype=torch.float32).cpu().reshape(2)

    def act_on_roots(_frames: list[Tensor], roots: Tensor) -> Tensor:
        return act(torch.cat([roots.flatten(), goal])[None])[0]

    out = control_in_pybullet(act_on_roots, task, seed, goal, history_steps)
    return {"success": out["success"], "steps": out["steps"]}


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


def ground_truth_success(policy: TensorDictModule, env: HRNEnv, episodes: int,
                         closed_loop: bool = False) -> dict[str, float]:
    """The ground-truth check: the policy's learned-model episodes replayed in pybullet.

    Runs ``episodes`` deterministic episodes in the learned environment with dropout 0 and no
    action noise (:func:`record_episodes`; the environment's settings are restored after),
    then replays each episode's actions open loop in the pybullet scene it started from, after
    the same ``HISTORY`` zero-force steps, against the same goal
    (:func:`replay_in_pybullet`). An episode that failed or ran to ``max_steps`` counts as
    length ``max_steps`` on either side (the convention of :func:`evaluate_policy`).

    Returns ``model_success_rate``, ``model_mean_length``, ``pybullet_success_rate``,
    ``pybullet_mean_length`` and ``agreement`` (fraction of episodes where both judge the same),
    plus ``ground_truth_episodes``; with ``closed_loop`` also ``closed_loop_success_rate`` and
    ``closed_loop_mean_length``: the policy run in each episode's pybullet scene against its
    goal, seeing pybullet's states (:func:`closed_loop_in_pybullet`).
    """

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
                                    history_steps=HISTORY)
        model_ok.append(rec["success"])
        model_len.append(rec["length"] if rec["success"] else max_steps)
        real_ok.append(replay["success"])
        real_len.append(replay["steps"] if replay["success"] else max_steps)
    n = len(records)
    out = {
        "ground_truth_episodes": n,
        "model_success_rate": sum(model_ok) / n,
        "model_mean_length": sum(model_len) / n,
        "pybullet_success_rate": sum(real_ok) / n,
        "pybullet_mean_length": sum(real_len) / n,
        "agreement": sum(a == b for a, b in zip(model_ok, real_ok)) / n,
    }
    if closed_loop:
        act = deterministic_actions(policy)
        runs = [closed_loop_in_pybullet(act, env.task, rec["seed"], rec["goal"]) for rec in records]
        out["closed_loop_success_rate"] = sum(r["success"] for r in runs) / n
        out["closed_loop_mean_length"] = sum(r["steps"] for r in runs) / n
    return out
