"""``hrn-pyg calibrate``: choose a model's sampling rate so its spread matches the physics'.

On a few **validation** starts (``seed % 10 == 8``; test seeds are refused) the truth is a
perturbed-start pybullet ensemble (:func:`hrn_pyg.sampling.ensemble.ground_truth_ensemble`,
2 mm by default). For every candidate (dropout rate, masked modules) the model draws ``k``
futures (:func:`hrn_pyg.sampling.sample.sample`, seeded ``--sample-seed``); at the last step:

* the **spread ratio**: the samples' RMS distance from their mean over the ensemble's, over
  moving leaves (:func:`~hrn_pyg.sampling.metrics.root_spread`);
* the **energy score** (:func:`~hrn_pyg.sampling.metrics.energy_score`) per moving leaf.

The chosen candidate has the median ``log(spread ratio)`` closest to 0, ties to the lower
energy score (:func:`choose`). It is written into a copy of the checkpoint (default
``<name>.calibrated.pt``; ``--in-place``; atomically): ``model.dropout_rate`` /
``model.dropout_modules`` and a ``calibration`` record of how. ``hrn-pyg sample``, the demo and
the RL environment use that rate when given none.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import tomllib
import warnings
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.checkpoints import load_model, resolve_model
from hrn_pyg.commands.calibrate import DEFAULT_RATES, DEFAULT_SEEDS, add_arguments  # noqa: F401  the command's arguments, here too
from hrn_pyg.data.dataset import (
    EPISODE_PATTERN,
    SPLIT_MODULUS,
    TEST_RESIDUE,
    VAL_RESIDUE,
    read_episode,
)
from hrn_pyg.data.graph import HISTORY, NODE
from hrn_pyg.data.scene_file import check_scene_name
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.sampling.ensemble import (
    PerturbationConfig,
    episode_state,
    ground_truth_ensemble,
)
from hrn_pyg.sampling.metrics import energy_score, root_spread
from hrn_pyg.sampling.sample import sample
from hrn_pyg.sim.plausibility import is_implausible, state_plausibility
from hrn_pyg.utils.checkpoint import load_checkpoint, save_checkpoint
from hrn_pyg.utils.device import resolve_device
from hrn_pyg.utils.files import atomic_write
from hrn_pyg.utils.options import progress_bar

#: default output: ``<stem>.calibrated.pt`` beside the input
CALIBRATED_SUFFIX = ".calibrated.pt"
#: key of the calibration record in a checkpoint's JSON config
RECORD_KEY = "calibration"
#: what the choice minimises, as written into the record
CRITERION = "median over starts of |log(spread ratio samples / ensemble)| at the last step; ties: lower energy score"


# ----------------------------------------------------------------------------- argument checks
def check_seeds(seeds: list[int] | tuple[int, ...]) -> list[int]:
    """The seeds, each a validation seed (``seed % 10 == 8``); ValueError naming the first that is not
    (test seeds would fit the rate to the test)."""
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError("--episode-seeds must name at least one validation seed (seed % 10 == 8), e.g. 8,18,28")
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"--episode-seeds has duplicates: {seeds}")
    for seed in seeds:
        if seed < 0:
            raise ValueError(f"--episode-seeds: seed {seed} is negative")
        residue = seed % SPLIT_MODULUS
        if residue == TEST_RESIDUE:
            raise ValueError(f"--episode-seeds: {seed} is a test seed (seed % 10 == 9); calibrate on validation "
                             f"seeds only (seed % 10 == 8, e.g. 8,18,28), never on the test split")
        if residue != VAL_RESIDUE:
            raise ValueError(f"--episode-seeds: {seed} is a training seed; calibrate on validation seeds only "
                             f"(seed % 10 == 8, e.g. 8,18,28)")
    return seeds


def parse_seeds(text: str) -> list[int]:
    try:
        seeds = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise ValueError(f"--episode-seeds must be comma-separated integers, got {text!r}") from None
    return check_seeds(seeds)


def parse_rates(text: str) -> tuple[float, ...]:
    """Comma-separated rates, each in ``[0, 1)``, at least one, no duplicates."""
    rates = []
    for item in (s.strip() for s in text.split(",")):
        if not item:
            continue
        try:
            rate = float(item)
        except ValueError:
            raise ValueError(f"--rates: {item!r} is not a number") from None
        if not 0.0 <= rate < 1.0:  # also refuses nan
            raise ValueError(f"--rates: every rate must be in [0, 1), got {item}")
        rates.append(rate)
    if not rates:
        raise ValueError("--rates must name at least one rate in [0, 1)")
    if len(set(rates)) != len(rates):
        raise ValueError(f"--rates has duplicates: {text}")
    return tuple(rates)


def default_module_sets(allowed: tuple[str, ...]) -> list[tuple[str, ...]]:
    """The full set of modules the model masks, then each of them alone."""
    sets = [tuple(allowed)] + [(m,) for m in allowed]
    return list(dict.fromkeys(sets))


def parse_module_sets(values: list[str] | None, allowed: tuple[str, ...]) -> list[tuple[str, ...]]:
    """``["force", "force,collision"]`` -> module sets, each module ``allowed``; None:
    :func:`default_module_sets`."""
    if not allowed:
        raise ValueError("the model takes dropout on no module (its dropout_modules is empty): nothing to calibrate")
    if values is None:
        return default_module_sets(allowed)
    sets: list[tuple[str, ...]] = []
    for value in values:
        names = tuple(dict.fromkeys(m.strip() for m in value.split(",") if m.strip()))
        if not names:
            raise ValueError(f"--module-sets: empty module set {value!r}")
        unknown = [m for m in names if m not in allowed]
        if unknown:
            raise ValueError(f"--module-sets: unknown module(s) {', '.join(unknown)}; this model takes "
                             f"dropout on {', '.join(allowed)}")
        ordered = tuple(m for m in allowed if m in names)  # one spelling per set
        if ordered not in sets:
            sets.append(ordered)
    return sets


def default_output(model_path: Path) -> Path:
    """``dir/name.pt`` -> ``dir/name.calibrated.pt`` (a ``.calibrated.pt`` input maps to itself)."""
    name = model_path.name
    if name.endswith(CALIBRATED_SUFFIX):
        return model_path
    stem = name[:-3] if name.endswith(".pt") else name
    return model_path.with_name(stem + CALIBRATED_SUFFIX)


# ----------------------------------------------------------------------------- starts
@dataclass
class Start:
    """One validation start: the model's initial state and the ensemble at the last step."""

    seed: int
    graph: HeteroData  # state at step HISTORY, carrying pos_seq / force_seq
    forces: Tensor  # [steps, N, 3]
    truth: Tensor  # [M, L, 3] ensemble leaf positions at the last predicted step
    moving: Tensor  # [L] bool, leaves of non-static objects


def ensemble_key(scene: str, config: Any, seed: int, members: int, steps: int,
                 perturbation: PerturbationConfig) -> str:
    """A name for one start's ensemble in an ``--ensemble-cache`` folder: a digest of everything
    the ensemble depends on (the scene's name, file text and settings, the seed, members, steps
    and perturbation)."""
    spec = None if config is None else {"text": getattr(config, "text", None), "settings": config.settings_dict()}
    record = {"scene": scene, "spec": spec, "seed": int(seed), "members": int(members), "steps": int(steps),
              "perturbation": perturbation.to_dict()}
    digest = hashlib.sha256(json.dumps(record, sort_keys=True, default=str).encode()).hexdigest()[:16]
    return f"{scene}_{int(seed)}_{digest}.npy"


def cached_ensemble(cache: Path | None, scene: str, seed: int, members: int, steps: int,
                    perturbation: PerturbationConfig, config: Any, leaves: int) -> np.ndarray:
    """:func:`~hrn_pyg.sampling.ensemble.ground_truth_ensemble` of the start, read from ``cache``
    when it holds it with the expected shape ``(members, steps + 1, leaves, 3)``, else simulated
    (and written there atomically)."""
    path = None if cache is None else Path(cache) / ensemble_key(scene, config, seed, members, steps, perturbation)
    shape = (members, steps + 1, leaves, 3)
    if path is not None and path.is_file():
        try:
            kept = np.load(path, allow_pickle=False)
        except (OSError, ValueError):
            kept = None
        if kept is not None and kept.shape == shape and kept.dtype == np.float32 and np.isfinite(kept).all():
            return kept
    ensemble = ground_truth_ensemble(scene, seed, members, steps, perturbation, config)
    if path is not None:
        atomic_write(path, lambda fh: np.save(fh, ensemble, allow_pickle=False))
    return ensemble


def build_start(scene: str, seed: int, steps: int, members: int,
                perturbation: PerturbationConfig = PerturbationConfig(),
                config: Any = None, episode: dict | None = None, cache: Path | None = None) -> Start:
    """Simulate (or take) episode ``(scene, seed)`` and its perturbed-start ensemble: the start at step
    :data:`~hrn_pyg.sampling.ensemble.HISTORY`, the truth the members' leaves ``steps`` later.
    ``cache``: a folder of ensembles (:func:`cached_ensemble`)."""
    from hrn_pyg.data.episodes import simulate_episode_alone
    from hrn_pyg.data.graph import STATIC

    if episode is None:
        episode = simulate_episode_alone(scene if config is None else config, seed, steps=HISTORY + steps)
    leaves = np.asarray(episode["positions"]).shape[1]
    ensemble = cached_ensemble(cache, scene, seed, members, HISTORY + steps, perturbation, config, leaves)
    graph = episode_state(episode, start=HISTORY, steps=steps)
    forces = graph[NODE].force_seq.transpose(0, 1)
    truth = torch.as_tensor(ensemble[:, HISTORY + steps]).float()
    obj = torch.as_tensor(np.asarray(episode["leaf_object"]), dtype=torch.long)
    moving = torch.as_tensor(np.asarray(episode["object_material"]))[obj] != STATIC
    if not bool(moving.any()):
        raise ValueError(f"{scene} seed {seed}: no moving object to calibrate on")
    return Start(int(seed), graph, forces, truth, moving)


def data_scene(folder: Path, scene: str | None) -> tuple[str, Any]:
    """The scene a folder written by ``hrn-pyg generate`` holds: its name and the spec to simulate
    (a scene file's text as it was recorded, or a built-in scene, each with the settings its
    episodes were made with, e.g. another pitch; None: the built-in ``scene`` as it is). ``scene`` (optional) must agree with the folder's."""
    from hrn_pyg.data.scene_file import builtin_scene, parse_scene

    meta_path = folder / "meta.json"
    if not meta_path.is_file():
        if scene is None:
            raise ValueError(f"--data: {folder} has no meta.json naming its scene; pass --scene")
        return scene, None
    meta = json.loads(meta_path.read_text())
    if scene is not None and meta.get("scene") not in (None, scene):
        raise ValueError(f"--data: {folder} holds {meta['scene']!r} episodes, not {scene!r}")
    name = meta.get("scene") or scene
    # the settings the episodes were made with (generate's --pitch, --set ...), as recorded
    fields = {k: tuple(v) if isinstance(v, list) else v for k, v in (meta.get("config") or {}).items()}
    if meta.get("scene_text"):  # a scene file: the text the episodes were made from
        source = Path(meta.get("scene_file") or folder / "scene.toml")
        spec = parse_scene(tomllib.loads(meta["scene_text"]), name=name, base=source.parent,
                           source=str(source), text=meta["scene_text"])
        return name, spec.with_settings(**fields)
    if name is None:
        raise ValueError(f"--data: {folder}'s meta.json names no scene; pass --scene")
    return name, builtin_scene(name, **fields) if fields else None


def data_starts(folder: str | Path, scene: str | None, limit: int) -> tuple[list[int], str, Any, dict[int, Path]]:
    """Validation seeds (at most ``limit``, lowest first), the scene's name and spec
    (:func:`data_scene`) and the episode files of a folder written by ``hrn-pyg generate``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"--data: no folder {folder}")
    name, config = data_scene(folder, scene)
    files = {}
    for path in folder.iterdir():
        match = EPISODE_PATTERN.match(path.name)
        if match and int(match.group(1)) % SPLIT_MODULUS == VAL_RESIDUE:
            files[int(match.group(1))] = path
    if not files:
        raise ValueError(f"--data: no validation episodes (seed % 10 == 8) in {folder}")
    seeds = sorted(files)[:limit]
    return seeds, name, config, {s: files[s] for s in seeds}


# ----------------------------------------------------------------------------- scoring
def score(model: HRN, start: Start, k: int, steps: int, rate: float, modules: tuple[str, ...],
          sample_seed: int = 0) -> tuple[float, float, int]:
    """Spread ratio, energy score (m) and count of implausible futures (:func:`implausible_futures`) of
    one candidate on one start, the first two over the finite futures (NaN if none); the ``k``
    futures are drawn with a CPU generator seeded ``sample_seed``."""
    gen = torch.Generator().manual_seed(int(sample_seed))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a failed future is counted below
        every_step = sample(model, start.graph, k, steps, rate, forces=start.forces, generator=gen,
                            modules=modules).cpu()  # [k, steps, L, 3]
    failures = implausible_futures(start, every_step)
    futures = every_step[:, -1]  # [k, L, 3]
    futures = futures[torch.isfinite(futures).all(dim=(1, 2))]  # a blown-up future has no place to score
    if len(futures) == 0:
        return math.nan, math.nan, failures
    moving = start.moving
    spread = float(root_spread(futures[:, moving]).mean())
    ensemble_spread = float(root_spread(start.truth[:, moving]).mean())
    if not ensemble_spread > 0:
        raise ValueError(f"the ensemble of seed {start.seed} does not spread (all members end equal); "
                         "choose other seeds or a larger perturbation")
    es = float(energy_score(futures[:, moving], start.truth[:, moving]).mean())
    return spread / ensemble_spread, es, failures


def implausible_futures(start: Start, futures: Tensor) -> int:
    """How many of the ``futures`` ``[k, steps, L, 3]`` fail the physics report
    (:mod:`hrn_pyg.sim.plausibility`): a blow-up, energy gained beyond
    :data:`~hrn_pyg.sim.plausibility.ENERGY_TOLERANCE`, or a penetration deeper than pybullet's own
    plus a pitch."""
    reports, reference, scene = state_plausibility(start.graph, futures, start.forces)
    return sum(is_implausible(r, reference, scene.pitch) for r in reports)


def _log(ratio: float) -> float:
    return math.log(ratio) if ratio > 0 else -math.inf


def summarise(rate: float, modules: tuple[str, ...], ratios: list[float], energies: list[float],
              implausible: list[int] | None = None) -> dict:
    """One candidate's row: per-start numbers and their summaries (JSON-safe: no infinities);
    ``implausible``: its futures that failed the physics report, per start (None: none did)."""
    per_start = [0] * len(ratios) if implausible is None else [int(n) for n in implausible]
    ratios = [r for r in ratios if not math.isnan(r)] or [0.0]
    energies = [e for e in energies if not math.isnan(e)] or [0.0]
    log_median = float(np.median([_log(r) for r in ratios]))
    return {
        "implausible_futures": sum(per_start),
        "implausible_per_start": per_start,
        "rate": float(rate), "modules": list(modules),
        "spread_ratios": [float(r) for r in ratios],
        "spread_ratio_median": float(math.exp(log_median)) if math.isfinite(log_median) else 0.0,
        "spread_ratio_min": float(min(ratios)), "spread_ratio_max": float(max(ratios)),
        "log_ratio_median": log_median if math.isfinite(log_median) else None,
        "energy_scores_m": [float(e) for e in energies],
        "energy_score_m": float(np.mean(energies)),
    }


def choose(candidates: list[dict], physics: bool = True) -> int:
    """Index of the candidate whose median log spread ratio is closest to 0 among those whose futures
    all pass the physics report (``physics=False``: among all); ties: lower energy score, then the
    first. ValueError when none qualifies."""
    def key(i: int) -> tuple[float, float]:
        lr = candidates[i]["log_ratio_median"]
        return (math.inf if lr is None else abs(lr), candidates[i]["energy_score_m"])

    possible = [i for i, c in enumerate(candidates) if not (physics and c.get("implausible_futures", 0))]
    if not possible:
        raise ValueError("every candidate rate gives futures that fail the physics report (a blow-up, energy "
                         "gained, or bodies deeper in each other than pybullet's plus a pitch) on these starts: "
                         "try lower --rates")
    best = min(possible, key=key)
    if candidates[best]["log_ratio_median"] is None:
        raise ValueError("no candidate spreads the samples at all (ratio 0 on every one): try higher "
                         "--rates or other --module-sets")
    return best


def grid_edge(chosen: dict, rates: tuple[float, ...]) -> str | None:
    """A warning when the chosen rate is the lowest candidate and still spreads too much, or the
    highest and still spreads too little (the match may lie outside the grid); else None."""
    ratio = chosen["spread_ratio_median"]
    if chosen["rate"] == min(rates) and ratio > 1:
        return (f"the chosen rate is the lowest candidate and the samples still spread {ratio:.3g}x "
                "the ensemble; lower --rates may match better")
    if chosen["rate"] == max(rates) and ratio < 1:
        return (f"the chosen rate is the highest candidate and the samples spread only {ratio:.3g}x "
                "the ensemble; higher --rates may match better")
    return None


def calibrate(model: HRN, starts: list[Start], rates: tuple[float, ...], module_sets: list[tuple[str, ...]],
              k: int, steps: int, sample_seed: int = 0, progress: bool = False) -> list[dict]:
    """Score every (rate, module set) on every start; one :func:`summarise` row per candidate,
    in the order module set, then rate."""
    pairs = [(rate, modules) for modules in module_sets for rate in rates]
    bar = progress_bar(len(pairs) * len(starts), "calibrate", "rollout", enabled=progress)
    candidates = []
    try:
        for rate, modules in pairs:
            ratios, energies, implausible = [], [], []
            for start in starts:
                ratio, es, failures = score(model, start, k, steps, rate, modules, sample_seed)
                ratios.append(ratio)
                energies.append(es)
                implausible.append(failures)
                bar.update(1)
            candidates.append(summarise(rate, modules, ratios, energies, implausible))
            bar.set_postfix(rate=rate, modules="+".join(modules), ratio=f"{candidates[-1]['spread_ratio_median']:.2f}")
    finally:
        bar.close()
    return candidates


def markdown(candidates: list[dict], chosen: int | None = None) -> str:
    """The candidates as a markdown table (with their futures that failed the physics report); the
    chosen one is marked."""
    lines = ["| rate | modules | spread ratio median | range | energy score (mm) | implausible futures | chosen |",
             "|---:|---|---:|---|---:|---:|:---:|"]
    for i, c in enumerate(candidates):
        lines.append(f"| {c['rate']:g} | {','.join(c['modules'])} | {c['spread_ratio_median']:.3g} | "
                     f"{c['spread_ratio_min']:.3g} - {c['spread_ratio_max']:.3g} | "
                     f"{1e3 * c['energy_score_m']:.2f} | {c['implausible_futures']} | "
                     f"{'<-' if i == chosen else ''} |")
    return "\n".join(lines)


def failing_everywhere(candidates: list[dict], names: list[str]) -> list[str]:
    """The ``names`` of the starts (in the candidates' per-start order) where every candidate has a
    future that fails the physics report."""
    rows = [c["implausible_per_start"] for c in candidates]
    return [name for i, name in enumerate(names) if rows and all(row[i] > 0 for row in rows)]


# ----------------------------------------------------------------------------- checkpoint
def calibration_record(path: str | Path) -> dict | None:
    """The ``calibration`` record of a checkpoint's JSON config, or None (never calibrated)."""
    config = json.loads(load_checkpoint(path)["config"])
    record = config.get(RECORD_KEY)
    return record if isinstance(record, dict) else None


def write_calibrated(src: str | Path, dst: str | Path, rate: float, modules: tuple[str, ...],
                     record: dict) -> None:
    """Copy checkpoint ``src`` to ``dst`` (atomically; ``dst`` may be ``src``) with the model
    config's ``dropout_rate`` / ``dropout_modules`` set and ``record`` stored under
    :data:`RECORD_KEY` in the JSON config. Read with a weights-only load."""
    ckpt = load_checkpoint(src)
    config = json.loads(ckpt["config"])
    if not isinstance(config.get("model"), dict):
        raise ValueError(f"{src} has no model config to calibrate")
    model_config = dict(config["model"], dropout_rate=float(rate), dropout_modules=list(modules))
    HRNConfig.from_dict(model_config)  # validates before anything is written
    config["model"] = model_config
    config[RECORD_KEY] = record
    payload = {key: value for key, value in ckpt.items() if key != "format"}
    payload["config"] = json.dumps(config, allow_nan=False)
    save_checkpoint(dst, payload)


def allowed_modules(model: HRN, record: dict | None) -> tuple[str, ...]:
    """Modules the model may be masked on: those it allowed before any earlier calibration."""
    if record and isinstance(record.get("model_dropout_modules"), list):
        return tuple(record["model_dropout_modules"])
    return tuple(model.config.dropout_modules)


# ----------------------------------------------------------------------------- CLI


def run(args: argparse.Namespace) -> int:
    check_scene_name(args.scene)
    # --- everything cheap is checked before anything is simulated ----------------------------
    rates = parse_rates(args.rates)
    for name in ("k", "members"):
        if getattr(args, name) < 2:
            raise ValueError(f"--{name} must be >= 2 (one trajectory has no spread), got {getattr(args, name)}")
    if args.steps < 1:
        raise ValueError(f"--horizon must be >= 1, got {args.steps}")
    if args.starts < 1:
        raise ValueError(f"--starts must be >= 1, got {args.starts}")
    perturbation = PerturbationConfig() if args.position_std is None else PerturbationConfig(position_std=args.position_std)
    seeds = parse_seeds(args.seeds) if args.seeds is not None else list(DEFAULT_SEEDS) if args.data is None else None
    if args.scene is None and (args.data is None or args.model is None):
        raise ValueError("--scene is required unless --data folders name their scenes and --model is given")
    model_path = resolve_model(args.scene, args.model)
    out = model_path if args.in_place else Path(args.out) if args.out else default_output(model_path)
    if out.resolve() == model_path.resolve() and not args.in_place:
        raise ValueError(f"the output {out} is the input checkpoint; pass --in-place to overwrite it, "
                         "or another --out")
    # (name, spec or None, seed, episode file or None) of every start
    plan: list[tuple[str, Any, int, Path | None]] = []
    if args.data is not None:
        for folder in args.data:
            folder_seeds, name, config, files = data_starts(folder, args.scene, args.starts)
            plan += [(name, config, seed, files[seed]) for seed in folder_seeds]
    else:
        plan = [(args.scene, None, seed, None) for seed in seeds]
    device = resolve_device(args.device)
    model = load_model(model_path, device)
    record_before = calibration_record(model_path)
    allowed = allowed_modules(model, record_before)
    module_sets = parse_module_sets(args.modules, allowed)
    model.config = replace(model.config, dropout_modules=allowed)  # masks on any allowed module

    # --- starts: episode and perturbed ensemble --------------------------------------------------
    starts = []
    for name, config, seed, path in plan:
        episode = read_episode(path) if path is not None else None
        print(f"simulating {name} seed {seed}: {args.members} perturbed replays of "
              f"{HISTORY + args.steps} steps", file=sys.stderr, flush=True)
        starts.append(build_start(name, seed, args.steps, args.members, perturbation, config, episode,
                                  getattr(args, "ensemble_cache", None)))

    # --- candidates ---------------------------------------------------------------------------
    candidates = calibrate(model, starts, rates, module_sets, args.k, args.steps, args.sample_seed,
                           progress=not args.no_progress)
    try:
        best = choose(candidates, physics=not args.no_physics_check)
    except ValueError as exc:  # the table says what each candidate did; the starts to blame are named
        print(markdown(candidates))
        names = [f"{name} seed {seed}" for name, _, seed, _ in plan]
        blamed = failing_everywhere(candidates, names)
        raise ValueError(f"{exc}" + (f" (failing at every rate: {', '.join(blamed)})" if blamed else "")) from None
    chosen = candidates[best]
    print(markdown(candidates, best))
    edge = grid_edge(chosen, rates)
    if edge:
        print(f"note: {edge}")
    record = {
        "rate": chosen["rate"], "modules": chosen["modules"],
        "spread_ratio_median": chosen["spread_ratio_median"], "energy_score_m": chosen["energy_score_m"],
        "criterion": CRITERION, "scene": args.scene or sorted({name for name, *_ in plan}),
        "seeds": [seed for *_, seed, _ in plan],
        "data": None if args.data is None else [str(folder) for folder in args.data],
        "start_step": HISTORY, "steps": args.steps, "k": args.k, "members": args.members,
        "perturbation": perturbation.to_dict(), "sample_seed": args.sample_seed,
        "model_dropout_modules": list(allowed), "source": str(model_path), "note": edge,
        "candidates": candidates,
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    write_calibrated(model_path, out, chosen["rate"], tuple(chosen["modules"]), record)
    print(f"chose rate {chosen['rate']:g} on {','.join(chosen['modules'])} (spread ratio "
          f"{chosen['spread_ratio_median']:.3g}, median over {len(starts)} start(s)); wrote {out}")
    return 0
