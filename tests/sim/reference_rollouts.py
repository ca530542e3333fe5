"""Short rollouts of every shipped checkpoint, kept on disk so that a change of the code can be
checked to leave every model's predictions as they were (to rounding).

``python tests/sim/reference_rollouts.py --write`` remakes ``reference_rollouts.npz`` (only
when the predictions are *meant* to change); ``--add NAME[,NAME]`` adds (or replaces) the
rollouts of newly shipped checkpoints from the stored start states and keeps every other array as
it is; ``--rl`` remakes only the RL environment's steps (``rl/...``, when the environment is meant
to change);
``tests/sim/test_reference_rollouts.py`` compares.
The start states are stored with the file (pybullet is not rerun), so the comparison is of the
model code alone.
"""

from __future__ import annotations

import argparse
import hashlib
from pathlib import Path

import numpy as np
import torch

import hrn_pyg
from hrn_pyg.sim.rollout import rollout as rollout_nodes
from hrn_pyg.checkpoints import CHECKPOINT_DIR, load_model
from hrn_pyg.data.graph import set_pitch
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sim.fixed_shape import fixed_shape_rollout

FILE = Path(__file__).with_name("reference_rollouts.npz")
#: the scene each shipped model was trained on (its reference start states come from there)
SCENE_OF = {
    "cube_collision": "cube_collision", "cube_collision_dropout": "cube_collision",
    "cube_collision_hrn": "cube_collision", "cube_push": "cube_push", "multi_material": "multi_material",
    "soft_bounce": "soft_bounce", "soft_bounce_fine": "soft_bounce", "soft_bounce_hrn": "soft_bounce",
    "tower": "tower", "wedge": "wedge", "shapes": "data/shapes/shapes_drop.toml",
    "shapes_d4": "data/shapes/shapes_drop.toml",
    "gns_cube_collision": "cube_collision", "gns_soft_bounce": "soft_bounce",
}
#: shipped files that are not dynamics models (they have no rollout to keep)
NOT_MODELS = ("cube_push_policy",)
#: how far a rollout may move from its reference where kernels round differently (another torch,
#: CPU vector unit or math-library path): 30 um. Rounding alone moved these 12-step rollouts by at
#: most 5e-6 m (shapes' sampled rollout, AVX512 against AVX2 kernels), while 0.1 % more on every
#: weight moves a start near rest by 2.4e-4 to 8.7e-4 m (the shipped models) and a resting start
#: moves 2.2e-4 m in one step
CROSS_MACHINE_ATOL = 3e-5
#: episode arrays the start states are rebuilt from
EPISODE_KEYS = ("positions", "forces", "leaf_mass", "leaf_object", "object_material", "object_stiffness",
                "hierarchy_parent")
SEED, EPISODE_STEPS, LATE_START, STEPS = 9, 60, 45, 12
#: the voxel pitch (m) every reference scene is made at (each scene file's default); the stored
#: episodes do not carry it, and a pitch-aware model reads it from the graph
PITCH = 0.05
RL_TASKS = {"cube_push": "cube_push", "tower": "tower"}
RL_POOL = (10_000, 10_001, 10_002)


def episodes() -> dict[str, dict[str, np.ndarray]]:
    """One short pybullet episode per scene (only when writing)."""
    from hrn_pyg.data.episodes import simulate_episode
    from hrn_pyg.data.scene_file import read_scene_file

    root = Path(__file__).resolve().parents[2]
    out = {}
    for scene in sorted(set(SCENE_OF.values())):
        spec = read_scene_file(root / scene) if scene.endswith(".toml") else scene
        ep = simulate_episode(spec, SEED, steps=EPISODE_STEPS)
        out[scene_key(scene)] = {k: ep[k] for k in EPISODE_KEYS}
    return out


def scene_key(scene: str) -> str:
    """The key of a scene's start states in the file: its name, or a scene file's stem."""
    return Path(scene).stem if scene.endswith(".toml") else scene


def start_state(model, episode: dict[str, np.ndarray], start: int):
    """The graph of ``episode`` at step ``start``; with its pitch when ``model`` reads it."""
    state = episode_state(episode, start=start, steps=STEPS)
    if getattr(model.config, "pitch_aware", False):
        set_pitch(state, PITCH)
    return state


def push(graph, steps: int) -> torch.Tensor:
    """``[steps, N, 3]``: a 2 N horizontal push on object 0's leaves for steps 2-4, else zero."""
    store = graph["particle"]
    target = store.is_leaf & (store.object == 0) & ~store.is_static
    force = torch.zeros(steps, store.num_nodes, 3)
    force[2:5, target, 0] = 2.0 / max(int(target.sum()), 1)
    return force


def compute(episode_arrays: dict[str, dict[str, np.ndarray]], names: tuple[str, ...] | None = None,
            rl: bool = True) -> dict[str, np.ndarray]:
    """Every reference rollout (of ``names`` only, when given; the RL ones with ``rl``), keyed
    ``<checkpoint>/<kind>``."""
    torch.set_num_threads(1)
    out: dict[str, np.ndarray] = {}
    for name, scene in SCENE_OF.items():
        if names is not None and name not in names:
            continue
        model = load_model(CHECKPOINT_DIR / f"{name}.pt")
        ep = episode_arrays[scene_key(scene)]
        with torch.no_grad():
            for start in (2, LATE_START):
                state = start_state(model, ep, start)
                forces = push(state, STEPS)
                key = f"{name}/start{start}"
                out[f"{key}/plain"] = rollout_nodes(model, state, STEPS, forces, sleep=None).numpy()
                out[f"{key}/sleep"] = rollout_nodes(model, state, STEPS, forces).numpy()
                # the GNS has no fixed-shape step
                if getattr(model.config, "network", "hrn") != "gns":
                    out[f"{key}/fixed"] = fixed_shape_rollout(model, state, STEPS, forces).pos.numpy()
                rate = float(model.config.dropout_rate) or 0.1
                if model.config.dropout_modules:
                    g = torch.Generator().manual_seed(3)
                    out[f"{key}/sample"] = hrn_pyg.sample(model, state, k=3, steps=STEPS, rate=rate,
                                                          forces=forces, generator=g).numpy()
    for name, task in RL_TASKS.items() if rl else ():
        from hrn_pyg.rl.hrn_dynamics import HRNDynamics

        dyn = HRNDynamics(load_model(CHECKPOINT_DIR / f"{name}.pt"), task, pool_seeds=RL_POOL)
        g = torch.Generator().manual_seed(5)
        states = dyn.reset_states(4, g)
        forces = torch.randn(4, dyn.num_objects, 3, generator=g) * 5.0
        forces[1] = 0.0  # an environment at rest with no push: its objects sleep
        out[f"rl/{name}/start"] = states.numpy()
        for rate in (0.0, 0.2):
            nxt = dyn.sample_next(states, forces, 2, rate, g)
            out[f"rl/{name}/rate{rate}"] = nxt.numpy()
            out[f"rl/{name}/rate{rate}/again"] = dyn.sample_next(nxt[:, 0], forces, 2, rate, g).numpy()
    return out


def checkpoint_digests() -> dict[str, str]:
    return {name: hashlib.sha256((CHECKPOINT_DIR / f"{name}.pt").read_bytes()).hexdigest()[:16] for name in SCENE_OF}


def machine() -> dict[str, str]:
    """What decides the floating-point kernels torch runs: its version and the CPU's vector unit."""
    return {"torch": torch.__version__, "cpu_capability": torch.backends.cpu.get_cpu_capability()}


def write() -> None:
    eps = episodes()
    arrays = {f"episode/{scene}/{k}": v for scene, ep in eps.items() for k, v in ep.items()}
    arrays.update(compute(eps))
    arrays.update({f"digest/{k}": np.array(v) for k, v in checkpoint_digests().items()})
    arrays.update({f"machine/{k}": np.array(v) for k, v in machine().items()})
    tmp = FILE.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(FILE)
    print(f"wrote {FILE} ({FILE.stat().st_size / 1e6:.2f} MB, {len(arrays)} arrays)")


def add(names: tuple[str, ...]) -> None:
    """Add the reference rollouts of ``names`` (in :data:`SCENE_OF`) from the stored start states,
    keeping every other array of the file."""
    unknown = sorted(set(names) - set(SCENE_OF))
    if unknown:
        raise SystemExit(f"--add: {unknown} are not in SCENE_OF")
    arrays = read()
    episodes = stored_episodes(arrays)
    arrays = {k: v for k, v in arrays.items() if not k.startswith(tuple(f"{n}/" for n in names))}  # replaced
    arrays.update(compute(episodes, names, rl=False))
    digests = checkpoint_digests()
    arrays.update({f"digest/{k}": np.array(digests[k]) for k in names})
    tmp = FILE.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(FILE)
    print(f"added {', '.join(names)} to {FILE} ({FILE.stat().st_size / 1e6:.2f} MB, {len(arrays)} arrays)")


def remake_rl() -> None:
    """Remake the RL environment's arrays (``rl/...``), keeping every other array of the file."""
    arrays = read()
    fresh = compute(stored_episodes(arrays), names=(), rl=True)
    for key in sorted(fresh):
        if fresh[key].shape == arrays[key].shape:
            print(f"{key}: moved up to {float(np.abs(fresh[key] - arrays[key]).max()):.3g}")
        else:
            print(f"{key}: shape {arrays[key].shape} -> {fresh[key].shape}")
    arrays.update(fresh)
    tmp = FILE.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(FILE)
    print(f"remade the RL arrays of {FILE} ({FILE.stat().st_size / 1e6:.2f} MB, {len(arrays)} arrays)")


def read() -> dict[str, np.ndarray]:
    with np.load(FILE, allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


def stored_episodes(arrays: dict[str, np.ndarray]) -> dict[str, dict[str, np.ndarray]]:
    out: dict[str, dict[str, np.ndarray]] = {}
    for key, value in arrays.items():
        if key.startswith("episode/"):
            _, scene, field = key.split("/")
            out.setdefault(scene, {})[field] = value
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", action="store_true", help="remake the reference file")
    parser.add_argument("--add", default="", help="NAME[,NAME]: add these models' rollouts, keep the rest")
    parser.add_argument("--rl", action="store_true", help="remake the RL environment's steps, keep the rest")
    args = parser.parse_args()
    if args.write:
        write()
    elif args.rl:
        remake_rl()
    elif args.add:
        add(tuple(n for n in args.add.split(",") if n))
