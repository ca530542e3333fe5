"""``hrn-pyg generate``: simulate a scene's episodes in worker processes and write them.

Episode ``i`` has seed ``--first-seed + i`` and goes to ``<out>/episode_<seed:06d>.npz``
(atomic); a rerun skips what exists. ``--shard i/N`` keeps the indices ``i`` modulo ``N``.
``<out>/meta.json`` records the scene, settings and counts (per shard under ``shards``).
Writers hold ``<out>/.lock`` (:class:`~hrn_pyg.utils.files.FolderLock`): one with other settings
stops with one line; shards run together; a failed run leaves meta.json as it was.
``--scene-file FILE`` reads a scene file (its text kept in meta.json); ``--set NAME=VALUE``
changes a setting. Soft and cloth episodes run in processes of their own, so their bytes depend
on seed and settings only. A seed pybullet loses (:func:`hrn_pyg.data.episodes.check_plausible`)
is not written: one line says why and ``episode_<seed:06d>.rejected`` keeps the reason.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path

from hrn_pyg.data.episodes import DivergedEpisode, carries_state, simulate_episode
from hrn_pyg.data.io import save_episode
from hrn_pyg.data.scene_file import builtin_scene, check_scene_name, read_scene_file
from hrn_pyg.utils.files import LOCK_NAME, FolderLock, atomic_write_json, atomic_write_text, remove_temporaries
from hrn_pyg.utils.options import progress_bar


#: the most episodes of one dataset (a file each; the package's largest has a few thousand)
MAX_EPISODES = 1_000_000
#: the most worker processes (each holds an interpreter and a pybullet client, about 300 MB)
MAX_WORKERS = 256
#: settings of a scene that have an option of their own, and its name
OWN_OPTIONS = {"steps": "--episode-steps", "substeps": "--substeps", "physics_hz": "--physics-hz", "pitch": "--pitch"}


def parse_overrides(items: list[str]) -> dict:
    """``["offset_range=[-0.003,0.003]", ...]`` -> ``{"offset_range": (-0.003, 0.003)}``: each
    VALUE read as JSON, lists becoming tuples; the names are checked against the scene's settings
    by :meth:`~hrn_pyg.data.scene_file.SceneSpec.with_settings`."""
    overrides = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name:
            raise ValueError(f"--set: expected NAME=VALUE, got {item!r}")
        if name in OWN_OPTIONS:
            raise ValueError(f"--set: {name} has its own option ({OWN_OPTIONS[name]})")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            raise ValueError(f"--set {name}: VALUE must be JSON (a number or a list such as [0.1,0.2]), "
                             f"got {text!r}") from None
        overrides[name] = tuple(value) if isinstance(value, list) else value
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


def rejected_path(out: str, seed: int) -> str:
    """Where a seed that pybullet lost is marked (:class:`~hrn_pyg.data.episodes.DivergedEpisode`):
    a text file with the reason, which a rerun skips and no dataset reads."""
    return os.path.join(out, f"episode_{seed:06d}.rejected")


def _generate_one(task: tuple[str, str, int, dict, str, str | None]) -> tuple[int, bool]:
    """Worker: simulate one episode and write it; ``(seed, written)``. ``kind`` is ``"scene"``
    (``source`` a built-in scene's name) or ``"file"`` (``source`` a scene file); ``settings``
    replace the scene's own, ``engine`` (None: the scene's) simulates it."""
    kind, source, seed, settings, path, engine = task
    if os.path.exists(path):
        return seed, False
    spec = read_scene_file(source) if kind == "file" else builtin_scene(source)
    try:
        episode = simulate_episode(spec.with_settings(**settings).with_engine(engine), seed)
    except DivergedEpisode as lost:
        atomic_write_text(path.removesuffix(".npz") + ".rejected", f"{lost}\n")
        print(f"rejected: {lost}", file=sys.stderr, flush=True)
        return seed, False
    save_episode(path, episode)
    return seed, True


def run(args: argparse.Namespace) -> int:
    # --- validate everything before touching the disk --------------------------------------
    if getattr(args, "scene_file", None) is None:
        check_scene_name(args.scene)
    if not 1 <= args.episodes <= MAX_EPISODES:
        raise ValueError(f"episodes: must be in [1, {MAX_EPISODES}], got {args.episodes}")
    if not 1 <= args.workers <= MAX_WORKERS:
        raise ValueError(f"workers: must be in [1, {MAX_WORKERS}], got {args.workers}")
    if args.seed_offset < 0:
        raise ValueError(f"--first-seed: must be >= 0, got {args.seed_offset}")
    shard_index, shard_count = parse_shard(args.shard)
    engine = getattr(args, "engine", None)  # None: the scene's own
    settings = {k: v for k, v in (dict(steps=args.steps, substeps=args.substeps, physics_hz=args.physics_hz,
                                       pitch=args.pitch) | parse_overrides(getattr(args, "overrides", []))).items()
                if v is not None}
    if getattr(args, "scene_file", None) is not None:
        kind, source = "file", str(Path(args.scene_file).resolve())
        spec = read_scene_file(args.scene_file).with_settings(**settings).with_engine(engine)
        record = {"scene_file": str(args.scene_file), "scene_text": spec.text}
    else:
        kind, source = "scene", args.scene
        spec = builtin_scene(args.scene, **settings).with_engine(engine)
        record = {}
    spec.check(args.seed_offset)  # overlaps and leaf counts fail here, before anything is written
    if kind == "file" and args.episodes > 1 and not spec.draws_anything:
        print(f"hrn-pyg generate: warning: {args.scene_file} draws nothing at random (no [draw], uniform(), "
              f"integer(), range or choice of meshes): its {args.episodes} episodes will all be the same",
              file=sys.stderr)
    name, fields = spec.name, settings
    record["config"] = spec.settings_dict()
    if spec.engine != "pybullet":
        record["engine"] = spec.engine

    made = not os.path.exists(args.out)
    os.makedirs(args.out, exist_ok=True)
    try:
        with FolderLock(args.out) as lock:
            if lock.alone:
                remove_temporaries(args.out)  # a killed writer's half-written episodes
                lock.shared()
            return _write(args, lock, spec, kind, source, name, record, fields, engine, (shard_index, shard_count))
    except BaseException:
        if made and set(os.listdir(args.out)) <= {LOCK_NAME}:  # a failed first run leaves no folder
            Path(args.out, LOCK_NAME).unlink(missing_ok=True)
            os.rmdir(args.out)
        raise


def _write(args: argparse.Namespace, lock: FolderLock, spec, kind: str, source: str, name: str, record: dict,
           fields: dict, engine: str | None, shard: tuple[int, int]) -> int:
    """The episodes of one shard, written into ``args.out`` under ``lock``, with meta.json."""
    shard_index, shard_count = shard
    meta_path = os.path.join(args.out, "meta.json")
    seeds = [args.seed_offset + i for i in range(args.episodes) if i % shard_count == shard_index]
    with lock.exclusive():  # the check and the first record, with no other writer between them
        old = _read_meta(meta_path)
        if old is not None and (old.get("scene") != name or any(old.get(k) != v for k, v in record.items())
                                or old.get("engine", "pybullet") != spec.engine):
            raise ValueError(f"out: {args.out} holds a dataset with another scene/config "
                             "(see its meta.json); choose a new --out")
        todo = [s for s in seeds if not os.path.exists(episode_path(args.out, s))
                and not os.path.exists(rejected_path(args.out, s))]
        shard_record = {"shard_seeds": len(seeds), "already_done": len(seeds) - len(todo), "written": 0,
                        "complete": False}
        meta = {
            "scene": name,
            **record,
            "episodes": args.episodes,
            "seed_offset": args.seed_offset,
            "shard": f"{shard_index}/{shard_count}",
            **shard_record,
        }
        _record_shard(meta_path, meta, meta["shard"], shard_record, old)

    tasks = [(kind, source, s, fields, episode_path(args.out, s), engine) for s in todo]
    start = time.perf_counter()
    bar = progress_bar(len(seeds), f"generate {name}", "ep", enabled=not args.no_progress)
    bar.update(len(seeds) - len(todo))
    written = 0
    # an episode whose engine carries state between episodes (carries_state) gets an interpreter
    # of its own, so a seed gives the same episode whatever the workers, shards or resume point
    isolate = carries_state(spec)
    try:
        if tasks and (isolate or (args.workers > 1 and len(tasks) > 1)):
            # spawn: a fresh interpreter per worker (per episode when isolating), each with its
            # own pybullet client
            ctx = mp.get_context("spawn")
            with ctx.Pool(processes=min(args.workers, len(tasks)),
                          maxtasksperchild=1 if isolate else None) as pool:
                for _, did in pool.imap_unordered(_generate_one, tasks):
                    written += did
                    bar.update(1)
        else:
            for _, did in map(_generate_one, tasks):
                written += did
                bar.update(1)
    except BaseException:
        with lock.exclusive():
            _undo_record(meta_path, old, meta["shard"], args.out)
        raise
    finally:
        bar.close()
    rejected = sum(os.path.exists(rejected_path(args.out, s)) for s in seeds)
    shard_record.update(written=written, rejected=rejected, complete=True,
                        seconds=round(time.perf_counter() - start, 3))
    meta.update(shard_record)
    with lock.exclusive():
        _record_shard(meta_path, meta, meta["shard"], shard_record, _read_meta(meta_path))
    return 0


def _read_meta(path: str) -> dict | None:
    """meta.json as a dict; None when there is none."""
    if not os.path.exists(path):
        return None
    with open(path) as f:
        return json.load(f)


def _record_shard(path: str, meta: dict, shard: str, shard_record: dict, current: dict | None) -> None:
    """Write ``meta`` to ``path`` with ``shard``'s record added to the ``shards`` of ``current``
    (what is on disk now: other writers' records stay)."""
    shards = dict((current or {}).get("shards", {}))
    shards[shard] = shard_record
    atomic_write_json(path, {**meta, "shards": shards})


def _undo_record(path: str, old: dict | None, shard: str, out: str) -> None:
    """After a failed run: meta.json as it was before (``old``), with the other writers' records
    kept; removed when there was none and the folder holds no episode."""
    current = _read_meta(path) or {}
    others = {k: v for k, v in current.get("shards", {}).items() if k != shard}
    if old is not None:
        atomic_write_json(path, {**old, "shards": {**old.get("shards", {}), **others}})
    elif others or any(name.startswith("episode_") for name in os.listdir(out)):
        current.get("shards", {}).pop(shard, None)
        atomic_write_json(path, current)  # says complete: false; a rerun finishes it
    else:
        Path(path).unlink(missing_ok=True)
