"""One model, one scene of each material, every path: the same positions.

The shipped ``shapes`` model with the rules after the network on (:mod:`hrn_pyg.sim.rules`: the
energy limit, solid and cloth clearance; static friction off, see ``model``) is started from the third frame of a pybullet episode
and stepped by the plain rollout, the sleeping rollout, the sampler at rate 0 (one copy and three
identical ones), the fixed-shape rollout, the RL environment's dynamics
(:meth:`~hrn_pyg.rl.hrn_dynamics.HRNDynamics.sample_next`, which carries each object's sleep
state in the environment's state as a sleeping rollout carries it, and ``next_positions``) and
the planner's model step (:func:`~hrn_pyg.rl.planning.rollout_futures`). The environment's pool
entry is the same pybullet start, and its graph is built by the same function as the rollout's
(:func:`~hrn_pyg.data.graph.episode_structure`), so every path gives one answer up to float
rounding. Scenes: ``cube_collision`` (two rigid cubes), ``soft_bounce`` (a soft body),
``multi_material`` (a cloth falling onto a rigid and a soft cube).
"""

from __future__ import annotations

import pytest
import torch

from hrn_pyg.checkpoints import load_model, with_applied_options
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import HISTORY, NODE
from hrn_pyg.rl.hrn_dynamics import HRNDynamics
from hrn_pyg.rl.planning import rollout_futures
from hrn_pyg.rl.tasks import TaskConfig
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sampling.sample import sample
from hrn_pyg.sim.fixed_shape import fixed_shape_rollout
from hrn_pyg.sim.rollout import rollout, unroll
from hrn_pyg.sim.sleeping import DEFAULT_SLEEP

STEPS = 4
#: the pybullet seed of every scene's episode and of the environment's one-scene pool
SEED = 10_000
#: float rounding of a few steps (the paths batch and order their sums differently)
ATOL = 1e-5
#: scene -> its movable objects
SCENES = {"cube_collision": 2, "soft_bounce": 1, "multi_material": 3}


@pytest.fixture(scope="module")
def model():
    """``shapes`` with every rule after the network on but static friction: two of the three starts
    are at rest, where friction holds every object and every path would agree trivially (the
    rule is applied by the same :class:`~hrn_pyg.sim.rules.StepRules` call on every path)."""
    return with_applied_options(load_model("shapes"), energy_limit=True, solid_clearance=0.3, cloth_clearance=0.3,
                                rest_friction=0.0)


@pytest.fixture(scope="module", params=list(SCENES))
def scene(request, model):
    """``(name, episode, start graph, plain rollout [STEPS, N, 3])`` of one scene."""
    name = request.param
    episode = simulate_episode(name, SEED, steps=STEPS + HISTORY + 1)
    graph = episode_state(episode, start=HISTORY, steps=STEPS)
    with torch.no_grad():
        plain = rollout(model, graph, STEPS, sleep=None)
    return name, episode, graph, plain


def dynamics(model, name: str, sleep=None) -> HRNDynamics:
    """The environment's dynamics on ``name`` with a one-scene pool: the episode's start."""
    task = TaskConfig(name=f"{name}_every_path", scene=name, max_steps=STEPS, num_objects=SCENES[name],
                      controlled_objects=(0,), force_axes=(0,), max_force=1.0, goal_kind="displaced",
                      goal_objects=(0,), goal_radius=0.1, dropout_modules=("force",))
    return HRNDynamics(model, task, pool_seeds=(SEED,), sleep=sleep)


def leaves_of(graph, positions: torch.Tensor) -> torch.Tensor:
    return positions[..., graph[NODE].is_leaf, :]


def test_the_plain_rollout_moves_every_scene(scene):
    """The reference the other paths are held to: finite, and not standing still."""
    _, _, graph, plain = scene
    assert bool(torch.isfinite(plain).all())
    assert float((plain[-1] - graph[NODE].pos).abs().max()) > 1e-4


def test_the_environment_builds_the_rollouts_graph(scene, model):
    name, episode, graph, _ = scene
    env = dynamics(model, name).structure_graph(0)
    start = graph[NODE]
    for key in ("mass", "material", "stiffness", "object", "rest_pos", "is_leaf", "is_static"):
        assert torch.equal(env[NODE][key], start[key]), key
    assert torch.equal(env.pitch, graph.pitch)
    for edge_type in env.edge_types:
        if edge_type[1] != "collision":
            assert torch.equal(env[edge_type].edge_index, graph[edge_type].edge_index), edge_type


def test_the_sleeping_rollout_holds_only_what_sleeps(scene, model):
    """Rows that never sleep move as in the plain rollout; a row asleep in a step stays put."""
    _, _, graph, plain = scene
    with torch.no_grad():
        steps = unroll(model, graph, STEPS)
    asleep = torch.stack([s.asleep if s.asleep is not None else torch.zeros_like(graph[NODE].is_leaf)
                          for s in steps])  # [STEPS, N]
    awake = ~asleep.any(0)
    sleeping = torch.stack([s.pos for s in steps])
    assert torch.allclose(sleeping[:, awake], plain[:, awake], atol=ATOL)
    before = torch.cat([graph[NODE].pos[None], sleeping[:-1]])
    assert torch.equal(sleeping[asleep], before[asleep])


@pytest.mark.parametrize("k", [1, 3])
@pytest.mark.parametrize("sleep", [None, DEFAULT_SLEEP], ids=["awake", "sleeping"])
def test_sampling_at_rate_zero_gives_the_rollout(scene, model, k, sleep):
    _, _, graph, plain = scene
    with torch.no_grad():
        reference = plain if sleep is None else rollout(model, graph, STEPS)
        futures = sample(model, graph, k=k, steps=STEPS, rate=0.0, sleep=sleep)
    assert futures.shape == (k, STEPS, int(graph[NODE].is_leaf.sum()), 3)
    for copy in futures:
        assert torch.allclose(copy, leaves_of(graph, reference), atol=ATOL)


def test_the_fixed_shape_rollout_gives_the_rollout_with_every_rule(scene):
    """Clearance needs the step's contacts: fixed-shape steps run it, with every other rule, after
    their network, and give the rollout's positions bit for bit. The energy limit alone runs inside
    the fixed-shape part (every row computed) and agrees to rounding."""
    _, _, graph, _ = scene
    every_rule = with_applied_options(load_model("shapes"), energy_limit=True, solid_clearance=0.3,
                                      cloth_clearance=0.3, rest_friction=0.0)
    energy_only = with_applied_options(load_model("shapes"), energy_limit=True, cloth_clearance=0.0,
                                       solid_clearance=0.0, rest_friction=0.0)
    with torch.no_grad():
        assert torch.equal(fixed_shape_rollout(every_rule, graph, STEPS).pos,
                           rollout(every_rule, graph, STEPS, sleep=None))
        expected = rollout(energy_only, graph, STEPS, sleep=None)
    assert torch.allclose(fixed_shape_rollout(energy_only, graph, STEPS).pos, expected, atol=ATOL)


def env_steps(env: HRNDynamics, steps: int, push: torch.Tensor | None = None) -> torch.Tensor:
    """``[steps, L, 3]``: the environment's leaves after each step (:meth:`sample_next`, one
    sample at rate 0) with the per-object force ``push`` ``(O, 3)`` (None: zero)."""
    states = env.reset_states(1, torch.Generator().manual_seed(0))
    force = torch.zeros(1, env.num_objects, 3) if push is None else push[None]
    out = []
    for _ in range(steps):
        states = env.sample_next(states, force, 1, 0.0, torch.Generator().manual_seed(0))[:, 0]
        out.append(env.leaf_history(states)[0][0, 2])
    return torch.stack(out)


def node_forces(env: HRNDynamics, graph, push: torch.Tensor) -> torch.Tensor:
    """``[STEPS, N, 3]``: the per-object force ``push`` ``(O, 3)`` spread evenly over each
    object's leaves, as the environment spreads it, zero on the ancestors."""
    leaf_object = env.leaf_object
    count = torch.bincount(leaf_object, minlength=env.num_objects).float()
    forces = torch.zeros(STEPS, graph[NODE].num_nodes, 3)
    forces[:, graph[NODE].is_leaf] = push[leaf_object] / count[leaf_object, None]
    return forces


def test_the_environment_steps_as_the_rollout(scene, model):
    name, episode, graph, plain = scene
    env = dynamics(model, name)
    history, index = env.leaf_history(env.reset_states(1, torch.Generator().manual_seed(0)))
    assert torch.equal(history[0], torch.from_numpy(episode["positions"][:HISTORY + 1]))
    expected = leaves_of(graph, plain)
    assert torch.allclose(env_steps(env, STEPS), expected, atol=ATOL)
    with torch.no_grad():
        first = env.next_positions(history, index, torch.zeros(1, env.num_objects, 3))
    assert torch.allclose(first[0], expected[0], atol=ATOL)


def test_a_pushed_environment_steps_as_the_pushed_rollout(scene, model):
    """A push on the first object (its force spread over its leaves): the same positions, and
    not those without the push."""
    name, _, graph, plain = scene
    env = dynamics(model, name)
    push = torch.zeros(env.num_objects, 3)
    push[0] = torch.tensor([3.0, 0.0, 2.0])
    with torch.no_grad():
        pushed = rollout(model, graph, STEPS, node_forces(env, graph, push), sleep=None)
    assert not torch.allclose(pushed, plain, atol=1e-3)
    assert torch.allclose(env_steps(env, STEPS, push), leaves_of(graph, pushed), atol=ATOL)


@pytest.mark.parametrize("name", list(SCENES))
def test_the_sleeping_environment_steps_as_the_sleeping_rollout(name, model):
    episode = simulate_episode(name, SEED, steps=STEPS + HISTORY + 1)
    graph = episode_state(episode, start=HISTORY, steps=STEPS)
    with torch.no_grad():
        expected = leaves_of(graph, rollout(model, graph, STEPS))
    assert torch.allclose(env_steps(dynamics(model, name, DEFAULT_SLEEP), STEPS), expected, atol=ATOL)


def test_the_planners_model_step_is_the_rollouts(scene, model):
    """Zero actions through :func:`rollout_futures`: the roots (centre, per-step velocity) of
    the rollout's graphs after each step (whose ``x_t`` is the one the ground lift moved)."""
    name, _, graph, _ = scene
    env = dynamics(model, name)
    state = env.reset_states(1, torch.Generator().manual_seed(0))[0]
    with torch.no_grad():
        roots = rollout_futures(env, state, torch.zeros(1, STEPS, env.task.action_dim), 1, 0.0,
                                torch.Generator().manual_seed(0))  # (1, 1, STEPS, O, 6)
        steps = unroll(model, graph, STEPS, sleep=None)
    histories = torch.stack([leaves_of(graph, torch.stack([s.graph[NODE].prev_prev_pos, s.graph[NODE].prev_pos,
                                                            s.graph[NODE].pos])) for s in steps])  # (STEPS, 3, L, 3)
    expected = env.roots(env.state_of(histories, torch.zeros(STEPS, dtype=torch.long)))
    assert torch.allclose(roots[0, 0], expected, atol=ATOL)
