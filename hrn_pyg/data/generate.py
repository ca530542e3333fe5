"""``hrn-pyg generate``: simulate a scene's episodes in worker processes and write them.

Episode ``i`` (``0 <= i < --episodes``) has seed ``--seed-offset + i`` and is written as
``<out>/episode_<seed:06d>.npz`` (:func:`hrn_pyg.data.io.save_episode`, atomic). A rerun skips
files that exist, so a killed run loses at most the episodes in flight. ``--shard i/N`` keeps
the episodes whose index is ``i`` modulo ``N``, so N machines can split one dataset.
``<out>/meta.json`` (atomic) records the scene, its configuration and the counts.
``--scene-file FILE`` simulates a scene read from a TOML file
(:mod:`hrn_pyg.data.scene_file`) instead of a built-in one; its meta.json keeps the file's text.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing as mp
import os
import time
from pathlib import Path

from tqdm import tqdm

from hrn_pyg.data.io import save_episode
from hrn_pyg.data.scene_file import read_scene_file
from hrn_pyg.data.scenes import SCENES, config_to_dict, scene_config, simulate_episode
from hrn_pyg.utils.files import atomic_write_json


def add_arguments(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--scene", help=f"a built-in scene: one of {', '.join(SCENES)}")
    source.add_argument("--scene-file", help="a scene file (TOML: objects from meshes, materials, pushes)")
    parser.add_argument("--episodes", type=int, required=True, help="episodes in the dataset")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    parser.add_argument("--shard", default="0/1", help="i/N: this machine's share (default 0/1)")
    parser.add_argument("--steps", type=int, default=None, help="model steps per episode")
    parser.add_argument("--seed-offset", type=int, default=0, help="seed of episode 0")
    parser.add_argument("--substeps", type=int, default=None, help="physics steps per model step")
    parser.add_argument("--physics-hz", type=float, default=None, help="physics rate (Hz)")
    parser.add_argument("--pitch", type=float, default=None, help="voxel size of the leaves (m)")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", dest="overrides",
                        help="any other field of the scene's config, VALUE as JSON, e.g. "
                             "offset_range=[-0.003,0.003] (repeatable)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def parse_overrides(items: list[str], scene: str) -> dict:
    """``["offset_range=[-0.003,0.003]", ...]`` -> ``{"offset_range": (-0.003, 0.003)}``: each
    VALUE read as JSON, lists becoming tuples (the configs' ranges); the field names are checked
    against the scene's config by :func:`~hrn_pyg.data.scenes.scene_config`."""
    overrides = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name:
            raise ValueError(f"--set: expected FIELD=VALUE, got {item!r}")
        if name in ("steps", "substeps", "physics_hz", "pitch"):
            raise ValueError(f"--set: {name} has its own option (--{name.replace('_', '-')})")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            raise ValueError(f"--set {name}: VALUE must be JSON (a number or a list such as [0.1,0.2]), "
                             f"got {text!r}") from None
        overrides[name] = tuple(value) if isinstance(value, list) else value
    scene_config(scene, **overrides)  # unknown fields and bad values fail here, before any work
    return overrides


def parse_shard(spec: str) -> tuple[int, int]:
    """``"i/N"`` -> ``(i, N)`` with ``0 <= i < N``."""
    try:
        i_text, n_text = spec.split("/")
        index, count = int(i_text), int(n_text)
    except (ValueError, AttributeError):
        raise ValueError(f"shard: expected i/N such as 0/4, got {spec!r}") from None
    if count < 1 or not 0 <= index < count:
        raise ValueError(f"shard: need 0 <= i < N, got {spec!r}")
    return index, count


def episode_path(out: str, seed: int) -> str:
    return os.path.join(out, f"episode_{seed:06d}.npz")


def _generate_one(task: tuple[str, str, int, dict, str]) -> tuple[int, bool]:
    """Worker: simulate one episode and write it; ``(seed, written)``. ``kind`` is ``"scene"``
    (``source`` a built-in scene's name, ``fields`` its config) or ``"file"`` (``source`` a
    scene file, ``fields`` holding at most ``steps``)."""
    kind, source, seed, fields, path = task
    if os.path.exists(path):
        return seed, False
    if kind == "file":
        episode = simulate_episode(read_scene_file(source), seed, steps=fields.get("steps"))
    else:
        episode = simulate_episode(source, seed, config=scene_config(source, **fields))
    save_episode(path, episode)
    return seed, True


def _file_source(args: argparse.Namespace) -> tuple[str, dict, dict]:
    """A scene file's name, its worker fields and what meta.json records of it."""
    for option in ("substeps", "physics_hz", "pitch"):
        if getattr(args, option) is not None:
            raise ValueError(f"--{option.replace('_', '-')}: a scene file sets it itself")
    if getattr(args, "overrides", []):
        raise ValueError("--set: a scene file sets its fields itself (edit the file)")
    spec = read_scene_file(args.scene_file)
    spec.check(args.seed_offset)  # overlaps and leaf counts fail here, before anything is written
    if args.steps is not None and args.steps < 1:
        raise ValueError(f"steps: must be >= 1, got {args.steps}")
    config = config_to_dict(spec.config) | ({"steps": args.steps} if args.steps is not None else {})
    fields = {"steps": args.steps} if args.steps is not None else {}
    return spec.name, fields, {"scene_file": str(args.scene_file), "scene_text": spec.text, "config": config}


def run(args: argparse.Namespace) -> int:
    # --- validate everything before touching the disk --------------------------------------
    if getattr(args, "scene_file", None) is None and args.scene not in SCENES:
        raise ValueError(f"scene: unknown {args.scene!r}; choose one of {sorted(SCENES)}")
    if args.episodes < 1:
        raise ValueError(f"episodes: must be >= 1, got {args.episodes}")
    if args.workers < 1:
        raise ValueError(f"workers: must be >= 1, got {args.workers}")
    if args.seed_offset < 0:
        raise ValueError(f"seed-offset: must be >= 0, got {args.seed_offset}")
    shard_index, shard_count = parse_shard(args.shard)
    if getattr(args, "scene_file", None) is not None:
        name, fields, record = _file_source(args)
        kind, source = "file", str(Path(args.scene_file).resolve())
    else:
        overrides = parse_overrides(getattr(args, "overrides", []), args.scene)
        config = scene_config(args.scene, steps=args.steps, substeps=args.substeps,
                              physics_hz=args.physics_hz, pitch=args.pitch, **overrides)
        fields = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}
        name, kind, source, record = args.scene, "scene", args.scene, {"config": config_to_dict(config)}

    os.makedirs(args.out, exist_ok=True)
    meta_path = os.path.join(args.out, "meta.json")
    if os.path.exists(meta_path):
        with open(meta_path) as f:
            old = json.load(f)
        if old.get("scene") != name or any(old.get(k) != v for k, v in record.items()):
            raise ValueError(f"out: {args.out} holds a dataset with another scene/config "
                             "(see its meta.json); choose a new --out")
    seeds = [args.seed_offset + i for i in range(args.episodes) if i % shard_count == shard_index]
    todo = [s for s in seeds if not os.path.exists(episode_path(args.out, s))]
    meta = {
        "scene": name,
        **record,
        "episodes": args.episodes,
        "seed_offset": args.seed_offset,
        "shard": f"{shard_index}/{shard_count}",
        "shard_seeds": len(seeds),
        "already_done": len(seeds) - len(todo),
        "written": 0,
        "complete": False,
    }
    atomic_write_json(meta_path, meta)

    tasks = [(kind, source, s, fields, episode_path(args.out, s)) for s in todo]
    start = time.perf_counter()
    bar = tqdm(total=len(seeds), initial=len(seeds) - len(todo), unit="ep",
               desc=f"generate {name}", disable=args.no_progress)
    written = 0
    try:
        if args.workers == 1 or len(tasks) <= 1:
            results = map(_generate_one, tasks)
            for _, did in results:
                written += did
                bar.update(1)
        else:
            # spawn: a fresh interpreter per worker, each with its own pybullet client
            ctx = mp.get_context("spawn")
            with ctx.Pool(processes=min(args.workers, len(tasks))) as pool:
                for _, did in pool.imap_unordered(_generate_one, tasks):
                    written += did
                    bar.update(1)
    finally:
        bar.close()
    meta.update(written=written, complete=True,
                seconds=round(time.perf_counter() - start, 3))
    atomic_write_json(meta_path, meta)
    return 0
