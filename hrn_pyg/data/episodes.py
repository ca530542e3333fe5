"""One episode of a scene: pybullet run under the scene's own pushes, as the arrays a dataset stores."""

from __future__ import annotations

import dataclasses
import json
import multiprocessing as mp
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from hrn_pyg.data import mujoco_scene  # noqa: F401  registers the mujoco engine of scene files
from hrn_pyg.data.hierarchy import start_hierarchy
from hrn_pyg.data.scene_file import SceneSpec, scene_spec
from hrn_pyg.data.scenes import Scene

#: a leaf farther than this from the origin (m) marks an episode pybullet lost
MAX_DISTANCE = 50.0
#: a leaf that moves more than this in one model step (m) marks an episode pybullet lost
MAX_STEP_DISPLACEMENT = 0.5


class DivergedEpisode(RuntimeError):
    """pybullet lost an episode: non-finite positions, a leaf far away, through the ground or
    jumping; the message names the seed and what was seen."""


def check_plausible(positions: np.ndarray, pitch: float, where: str) -> None:
    """Raise :class:`DivergedEpisode` unless every leaf stays finite, within :data:`MAX_DISTANCE`
    of the origin, no more than one ``pitch`` under the ground ``z = 0``, and moves at most
    :data:`MAX_STEP_DISPLACEMENT` a step.

    **Shapes:** ``positions [S+1, L, 3]``.
    """
    if not np.all(np.isfinite(positions)):
        raise DivergedEpisode(f"{where}: pybullet produced non-finite positions")
    farthest = float(np.abs(positions).max())
    if farthest > MAX_DISTANCE:
        raise DivergedEpisode(f"{where}: a leaf reached {farthest:.4g} m from the origin "
                              f"(more than {MAX_DISTANCE} m)")
    lowest = float(positions[..., 2].min())
    if lowest < -pitch:
        raise DivergedEpisode(f"{where}: a leaf went {-lowest:.3g} m under the ground "
                              f"(more than one pitch, {pitch} m)")
    jump = float(np.abs(np.diff(positions, axis=0)).max()) if len(positions) > 1 else 0.0
    if jump > MAX_STEP_DISPLACEMENT:
        raise DivergedEpisode(f"{where}: a leaf moved {jump:.3g} m in one step "
                              f"(more than {MAX_STEP_DISPLACEMENT} m)")


def simulate_episode(scene: str | SceneSpec, seed: int, steps: int | None = None, *,
                     after_reset: Callable[[Scene], None] | None = None) -> dict[str, np.ndarray]:
    """Run one episode of ``scene`` (a built-in name or a spec) with its scripted and random pushes;
    ``steps`` overrides its length; ``after_reset(scene)`` runs before step 0 (e.g.
    :meth:`Scene.nudge`). :class:`DivergedEpisode` if pybullet lost it (:func:`check_plausible`).

    **Shapes** (``S`` steps, ``L`` leaves, ``O`` objects, ``N`` nodes): ``positions [S+1, L, 3]``
    f32, ``forces [S, L, 3]`` f32, ``leaf_mass [L]`` f32, ``leaf_object [L]`` i64,
    ``object_material [O]`` i64, ``object_stiffness [O]`` f32, ``hierarchy_parent [N]`` i64,
    ``seed``/``scene``/``params`` (JSON of the draws, settings and file text)/``dt`` scalars.
    """
    spec = scene_spec(scene)
    if steps is not None:
        if not isinstance(steps, (int, np.integer)) or steps < 1:
            raise ValueError(f"steps: must be an integer >= 1, got {steps}")
        spec = dataclasses.replace(spec, config=dataclasses.replace(spec.config, steps=int(steps)))
    sim = spec.make_scene(seed)
    n_steps = sim.config.steps
    try:
        x = sim.reset()
        if after_reset is not None:
            after_reset(sim)
            x = sim.leaf_positions()
        positions = np.empty((n_steps + 1, len(x), 3), dtype=np.float32)
        forces = np.empty((n_steps, len(x), 3), dtype=np.float32)
        positions[0] = x
        for t in range(n_steps):
            action, spins = sim.scripted_action(t)
            positions[t + 1] = sim.step(action, spins)
            forces[t] = sim.last_forces
        leaf_mass, leaf_object = sim.leaf_mass, sim.leaf_object
        record = {"params": sim.params, "config": spec.settings_dict()}
        if not isinstance(scene, str):
            record["scene_file"] = spec.text
        if spec.engine != "pybullet":
            record["engine"] = spec.engine
        episode = {
            "positions": positions,
            "forces": forces,
            "leaf_mass": leaf_mass,
            "leaf_object": leaf_object,
            "object_material": sim.object_material,
            "object_stiffness": sim.object_stiffness,
            "seed": np.array(sim.seed, dtype=np.int64),
            "scene": np.array(sim.name),
            "params": np.array(json.dumps(record, sort_keys=True)),
            "dt": np.array(sim.dt, dtype=np.float64),
        }
    finally:
        sim.close()
    check_plausible(positions, float(spec.config.pitch), f"{sim.name} seed {seed}")
    episode["hierarchy_parent"] = start_hierarchy(positions[0], leaf_mass, leaf_object)
    return episode


def carries_state(spec: SceneSpec) -> bool:
    """Whether simulating ``spec`` leaves state behind in the process: pybullet keeps part of its
    soft-body solver's state per process (a reset does not clear it), so an episode with soft
    bodies or cloth depends on the episodes run before it in the same process."""
    return spec.uses_deformables and spec.engine == "pybullet"


def simulate_episode_alone(scene: str | SceneSpec, seed: int, steps: int | None = None, *,
                           after_reset: Callable[[Scene], None] | None = None) -> dict[str, np.ndarray]:
    """:func:`simulate_episode` as a fresh process would run it: a scene that
    :func:`carries_state` is simulated in an interpreter of its own (a second or two to start), so
    a seed gives the same episode whatever ran before it; others run here. ``after_reset`` is sent
    to that interpreter, so it must pickle (a module-level function or a dataclass instance, not a
    closure). Raises what :func:`simulate_episode` raises."""
    spec = scene_spec(scene)
    if not carries_state(spec):
        return simulate_episode(scene, seed, steps, after_reset=after_reset)
    with ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn")) as pool:
        return pool.submit(simulate_episode, scene, seed, steps, after_reset=after_reset).result()
