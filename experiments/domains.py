"""The domain of each shipped model, derived from its recipe's datasets without their files.

``python -m experiments.domains [--episodes N] [--only NAME,...]`` (from the repository root)
re-simulates the first training episodes (seed ``% 10`` not 8 or 9) of every dataset a manifest
entry names, one in ten of its episodes but at least :data:`MIN_EPISODES` and at most ``N``
(:func:`episodes_to_measure`) (its own and those its stages join in), each at the dataset's length,
pitch and settings, measures their :class:`~hrn_pyg.checkpoints.domain.Domain` and writes it
as the entry's ``domain`` in ``hrn_pyg/checkpoints/manifest.json`` (atomically). The
checkpoints themselves are not touched. A dataset's episodes are the same bytes ``hrn-pyg
generate`` wrote, so the domain is that of a sample of the training data; sizes and speeds
span that sample (:mod:`hrn_pyg.checkpoints.domain` allows for it).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from hrn_pyg.checkpoints import MANIFEST_PATH, entry_datasets, read_manifest
from hrn_pyg.checkpoints.domain import Domain, episode_domain, merge_all, with_pitch_range
from hrn_pyg.data.dataset import split_of_seed
from experiments.recipe.schema import RECIPE_PATH, DatasetRecipe, load_recipe
from hrn_pyg.utils.files import atomic_write_json

#: training episodes simulated per dataset at most, by default
EPISODES = 12
#: training episodes simulated per dataset at least
MIN_EPISODES = 4


def entry_pitch_aware(entry: dict[str, Any]) -> bool:
    """Whether a manifest entry's model reads the pitch: its training (or a stage's) was run
    with ``--model-pitch-aware`` true."""
    for command in [entry.get("train_command", ""), *entry.get("stage_commands", [])]:
        words = shlex.split(command or "")
        for i, word in enumerate(words[:-1]):
            if word == "--model-pitch-aware" and words[i + 1].strip().lower() in ("1", "true", "yes", "on"):
                return True
    return False


def episodes_to_measure(dataset: DatasetRecipe, most: int) -> int:
    """How many of ``dataset``'s episodes are simulated: one in ten, within
    [:data:`MIN_EPISODES`, ``most``]."""
    return max(min(MIN_EPISODES, most), min(most, dataset.episodes // 10))


def dataset_spec(dataset: DatasetRecipe):
    """The :class:`~hrn_pyg.data.scene_file.SceneSpec` ``hrn-pyg generate`` simulates for
    ``dataset`` (its scene, length, pitch and ``set`` overrides)."""
    from hrn_pyg.data.scene_file import builtin_scene, read_scene_file

    settings = {"steps": dataset.steps, "pitch": dataset.pitch, **dict(dataset.overrides)}
    settings = {k: v for k, v in settings.items() if v is not None}
    if dataset.from_file:
        return read_scene_file(dataset.scene).with_settings(**settings)
    return builtin_scene(dataset.scene, **settings)


def training_seeds(dataset: DatasetRecipe, count: int) -> list[int]:
    """The first ``count`` seeds of ``dataset``'s training split."""
    seeds = [dataset.seed_offset + i for i in range(dataset.episodes)]
    return [s for s in seeds if split_of_seed(s) == "train"][:count]


def simulated_domain(dataset: DatasetRecipe, count: int) -> Domain:
    """The domain of ``count`` of ``dataset``'s training episodes, simulated afresh."""
    from hrn_pyg.data.episodes import simulate_episode

    spec = dataset_spec(dataset)
    return merge_all(episode_domain(simulate_episode(spec, seed), dataset.name)
                     for seed in training_seeds(dataset, count))


def derive_domains(recipe_path: str | Path, manifest_path: str | Path, count: int = EPISODES,
                   only: Sequence[str] = (), say=print) -> dict[str, Domain]:
    """Each manifest entry's domain (those of ``only`` when given) from up to ``count`` episodes
    of each of its datasets (:func:`episodes_to_measure`); writes them into the manifest and
    returns them."""
    recipe = load_recipe(recipe_path)
    manifest = read_manifest(manifest_path)
    unknown = sorted(set(only) - set(manifest))
    if unknown:
        raise ValueError(f"--only: not in the manifest: {unknown}; there are {sorted(manifest)}")
    measured: dict[str, Domain] = {}
    domains: dict[str, Domain] = {}
    for name, entry in sorted(manifest.items()):
        if only and name not in only:
            continue
        for dataset in entry_datasets(entry):
            if dataset not in measured:
                started = time.perf_counter()
                d = recipe.dataset(dataset)
                measured[dataset] = simulated_domain(d, episodes_to_measure(d, count))
                say(f"{dataset}: {json.dumps(measured[dataset].to_dict())} "
                    f"({time.perf_counter() - started:.0f} s)")
        domains[name] = merge_all(measured[d] for d in entry_datasets(entry))
        if entry_pitch_aware(entry):  # a pitch-aware model covers the span of its pitches
            domains[name] = with_pitch_range(domains[name])
    raw = json.loads(Path(manifest_path).read_text())
    for name, domain in domains.items():
        raw["checkpoints"][name]["domain"] = domain.to_dict()
    atomic_write_json(manifest_path, raw)
    return domains


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m experiments.domains", description=__doc__.splitlines()[0])
    parser.add_argument("--recipe", default=RECIPE_PATH, help=f"recipe file (default {RECIPE_PATH})")
    parser.add_argument("--manifest", default=str(MANIFEST_PATH), help="manifest to update (default: the package's)")
    parser.add_argument("--episodes", type=int, default=EPISODES,
                        help=f"training episodes simulated per dataset at most (default {EPISODES})")
    parser.add_argument("--only", default="", help="NAME[,NAME]: only these models (default all)")
    args = parser.parse_args(argv)
    if args.episodes < 1:
        print(f"{parser.prog}: error: --episodes must be >= 1, got {args.episodes}", file=sys.stderr)
        return 2
    try:
        derive_domains(args.recipe, args.manifest, args.episodes, tuple(n for n in args.only.split(",") if n))
    except (ValueError, FileNotFoundError) as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
