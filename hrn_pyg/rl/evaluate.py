"""Ground-truth evaluation of a trained policy: its episodes in the learned environment and the
same actions replayed in pybullet.

- :func:`record_episodes`: the policy's deterministic episodes in an
  :class:`~hrn_pyg.rl.env.HRNEnv`, with what a replay needs;
- :func:`evaluate_policy`: success rate and mean length in the environment;
- :func:`replay_in_pybullet`: one episode's actions open loop in its pybullet scene;
- :func:`closed_loop_in_pybullet`: the policy run in pybullet, seeing pybullet's states (its
  loop :func:`control_in_pybullet` takes any acting function, the planners' too);
- :func:`ground_truth_success`: them side by side (what ``hrn-pyg rl --model`` checks).
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
    """Success rate and mean episode length of the policy's deterministic actions over ``episodes``
    episodes (:func:`record_episodes`, rounds of ``B``); a failed episode counts ``max_steps``. The
    environment is used as configured (``dropout_rate = 0`` judges the deterministic model)."""
    records = record_episodes(policy, env, episodes)
    success = sum(r["success"] for r in records) / len(records)
    length = sum(r["length"] for r in records) / len(records)
    return float(success), float(length)


def replay_in_pybullet(actions: Tensor, task: str | TaskConfig, seed: int,
                       goal: Tensor | None = None, history_steps: int = 0) -> dict:
    """Replay a policy's actions ``(T, A)`` in the ground-truth pybullet scene of ``task``.

    Builds ``make_scene(task, seed)``, takes ``history_steps`` zero-force steps (the learned
    episodes start after ``HISTORY`` such steps), then applies one force ``(O, 3)`` per object per
    step and judges the goal on the object roots after each, stopping at the first success.
    ``goal`` ``(2,)``; None only for ``tower`` (the middle cube's start).

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
    """Control the pybullet scene ``seed`` of ``task`` closed loop against ``goal`` ``(2,)``: after
    ``history_steps`` zero-force steps, ``act`` sees pybullet's leaves and roots each step, its
    action is clipped and applied, and the goal judged, until it is held or ``max_steps``.

    Returns ``success``, ``steps``, ``actions`` ``(T, A)``, ``roots`` ``(T + 1, O, 6)``, and per
    step ``act_seconds`` and ``physics_seconds``.
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
    """Run a policy ``act`` closed loop in the pybullet scene ``seed`` (:func:`control_in_pybullet`),
    seeing the observation of :class:`~hrn_pyg.rl.env.HRNEnv`'s layout built from pybullet's roots;
    returns ``{"success": bool, "steps": int}``."""
    goal = torch.as_tensor(goal, dtype=torch.float32).cpu().reshape(2)

    def act_on_roots(_frames: list[Tensor], roots: Tensor) -> Tensor:
        return act(torch.cat([roots.flatten(), goal])[None])[0]

    out = control_in_pybullet(act_on_roots, task, seed, goal, history_steps)
    return {"success": out["success"], "steps": out["steps"]}


@torch.no_grad()
def record_episodes(policy: TensorDictModule, env: HRNEnv, episodes: int) -> list[dict]:
    """Run the policy's deterministic actions in ``env`` (as configured) and keep, per episode, on the
    CPU: ``seed`` (its pybullet scene, -1 if none), ``goal`` ``(2,)``, ``actions`` ``(T, A)``
    (clipped), ``states`` ``(T + 1, S)``, ``success`` and ``length`` ``T``."""
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

    ``episodes`` deterministic episodes with dropout 0 and no action noise (:func:`record_episodes`;
    settings restored after), each replayed open loop (:func:`replay_in_pybullet`); a failed
    episode counts ``max_steps``. Returns ``model_success_rate``, ``model_mean_length``,
    ``pybullet_success_rate``, ``pybullet_mean_length``, ``agreement`` and
    ``ground_truth_episodes``; with ``closed_loop`` also ``closed_loop_success_rate`` and
    ``closed_loop_mean_length`` (:func:`closed_loop_in_pybullet`).
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
