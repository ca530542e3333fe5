"""The recipe of ``python -m experiments.recipe``: ``data/recipes.toml`` read into frozen dataclasses.

The recipe (TOML) names every dataset (``[datasets.<name>]``: scene, episodes, steps,
seed_offset, optional pitch and ``set`` table of scene-config fields) and every shipped model
(``[models.<name>]``: dataset, preset, aliases, and a ``train`` table of ``hrn-pyg train``
options: ``key = value`` is ``--key value``, ``true`` a bare ``--key``, ``false`` nothing). A
model may add:

- ``[[models.<name>.finetune]]`` stages, each a table of train options;
- ``[models.<name>.average]``: ``stages`` (rising, ending with the last) and ``weights``
  (summing to one) of a weighted mean of stage weights (:mod:`experiments.recipe.weights`);
- ``[models.<name>.apply]``: options of :data:`hrn_pyg.checkpoints.APPLIED_OPTIONS` set on
  the trained weights;
- ``[models.<name>.calibrate]``: ``hrn-pyg calibrate`` options (a scene-file model calibrates
  on the validation episodes of its datasets);
- ``start = "<name>"``: start from a shipped checkpoint (``--init-from``, its digest part of
  the identity); the train option ``extra-datasets`` joins more datasets.

A top-level ``datasets_from`` borrows another recipe's datasets. :func:`load_recipe` validates
everything up front (one-line ``ValueError``); the dataclasses give ``hrn-pyg`` argument lists
and :func:`shown` the command line. Nothing here runs a process or writes a file.
"""

from __future__ import annotations

import hashlib
import json
import re
import shlex
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

#: default recipe, relative to the working directory (the repository root)
RECIPE_PATH = "data/recipes.toml"
#: dataset, model and alias names: plain file names
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]*")
OPTION_PATTERN = re.compile(r"[A-Za-z][A-Za-z0-9_-]*")
#: train options the runner sets itself; a recipe may not
RESERVED_OPTIONS = frozenset({"preset", "data", "out", "resume", "no-progress", "device", "time-limit",
                              "init-from", "extra-data"})
#: the train option naming more recipe datasets (comma-separated) whose episodes join the
#: model's dataset in a stage; the runner passes their folders as ``--extra-data``
EXTRA_DATASETS = "extra-datasets"
#: a recipe's top-level key naming another recipe file (relative to it) whose datasets it uses
DATASETS_FROM = "datasets_from"
DATASET_KEYS = frozenset({"scene", "episodes", "steps", "seed_offset", "pitch", "set"})
MODEL_KEYS = frozenset({"dataset", "preset", "aliases", "start", "train", "calibrate", "finetune", "average",
                        "apply"})
AVERAGE_KEYS = frozenset({"stages", "weights"})
#: calibrate options the runner sets itself; a recipe may not
RESERVED_CALIBRATE_OPTIONS = frozenset({"scene", "model", "out", "in-place", "device", "no-progress", "data"})
#: the calibrated copy of a run's model.pt
CALIBRATED_NAME = "model.calibrated.pt"
#: the mean of several stages' weights (``[models.<name>.average]``), in the last stage's run folder
AVERAGED_NAME = "model.averaged.pt"
#: the model with the recipe's applied options set (``[models.<name>.apply]``), beside it
APPLIED_NAME = "model.applied.pt"

OptionValue = str | int | float | bool


@dataclass(frozen=True)
class DatasetRecipe:
    """One ``hrn-pyg generate`` dataset: episode ``i`` has seed ``seed_offset + i``; ``scene`` is a
    built-in scene's name or a scene file (``*.toml``, relative to the folder the recipe runs in)."""

    name: str
    scene: str
    episodes: int
    steps: int
    seed_offset: int = 0
    pitch: float | None = None
    #: other scene-config fields (``hrn-pyg generate --set FIELD=VALUE``), e.g. a narrower range
    overrides: tuple[tuple[str, Any], ...] = ()

    def folder(self, data_dir: Path) -> Path:
        return data_dir / self.name

    def to_dict(self) -> dict[str, Any]:
        """The recipe as recorded in run records and the manifest (``overrides`` only when set,
        so datasets without them keep the records they had)."""
        d = asdict(self)
        overrides = d.pop("overrides")
        if overrides:
            d["set"] = {k: list(v) if isinstance(v, tuple) else v for k, v in overrides}
        if self.from_file and Path(self.scene).is_file():  # a changed file is a changed dataset
            d["scene_sha256"] = hashlib.sha256(Path(self.scene).read_bytes()).hexdigest()
        return d

    @property
    def from_file(self) -> bool:
        return self.scene.endswith(".toml")

    def generate_args(self, data_dir: Path) -> list[str]:
        """``hrn-pyg generate`` arguments (no worker count: it does not change the bytes)."""
        args = ["generate", "--scene-file" if self.from_file else "--scene", self.scene, "--episodes", str(self.episodes),
                "--out", str(self.folder(data_dir)), "--episode-steps", str(self.steps),
                "--first-seed", str(self.seed_offset)]
        if self.pitch is not None:
            args += ["--pitch", repr(float(self.pitch))]
        for key, value in self.overrides:
            args += ["--set", f"{key}={json.dumps(list(value) if isinstance(value, tuple) else value)}"]
        return args

    def episode_files(self, data_dir: Path) -> list[Path]:
        return [self.folder(data_dir) / f"episode_{self.seed_offset + i:06d}.npz"
                for i in range(self.episodes)]


@dataclass(frozen=True)
class ModelRecipe:
    """One shipped checkpoint: ``<name>.pt`` (and ``<alias>.pt``), trained on ``dataset``."""

    name: str
    dataset: str
    preset: str
    options: tuple[tuple[str, OptionValue], ...] = ()
    aliases: tuple[str, ...] = ()
    calibrate: tuple[tuple[str, OptionValue | tuple[str, ...]], ...] = ()
    #: fine-tuning stages after the first training, each its train options
    finetune: tuple[tuple[tuple[str, OptionValue], ...], ...] = ()
    #: a shipped checkpoint's name the first training starts from (``--init-from``); "" for a
    #: fresh network
    start: str = ""
    #: ``[models.<name>.average]``: (stage, weight) pairs whose weights' mean is the model; empty
    #: when the model is the last stage's model.pt
    average: tuple[tuple[int, float], ...] = ()
    #: ``[models.<name>.apply]``: (option, value) pairs of applied options set on the trained
    #: model (underscored names of :data:`hrn_pyg.checkpoints.APPLIED_OPTIONS`); empty: none
    apply: tuple[tuple[str, OptionValue], ...] = ()

    @property
    def num_stages(self) -> int:
        return 1 + len(self.finetune)

    def run_name(self, stage: int = 0) -> str:
        """The run folder of a stage: ``<name>``, then ``<name>.ft1``, ``<name>.ft2`` ..."""
        return self.name if stage == 0 else f"{self.name}.ft{stage}"

    @property
    def final_run(self) -> str:
        """The run folder whose ``model.pt`` is the model (the last stage's)."""
        return self.run_name(self.num_stages - 1)

    @property
    def trained_file(self) -> str:
        """The file in :attr:`final_run` the training makes: ``model.pt``, or the mean of the
        stages' weights when the recipe averages them."""
        return AVERAGED_NAME if self.average else "model.pt"

    @property
    def model_file(self) -> str:
        """The file in :attr:`final_run` that is the model, calibrated and shipped:
        :attr:`trained_file`, or its copy with the applied options when the recipe sets some."""
        return APPLIED_NAME if self.apply else self.trained_file

    def stage_options(self, stage: int = 0) -> tuple[tuple[str, OptionValue], ...]:
        """The train options of a stage (0: the first training, then each fine-tuning)."""
        return self.options if stage == 0 else self.finetune[stage - 1]

    def extra_datasets(self, stage: int | None = None) -> tuple[str, ...]:
        """The datasets a stage mixes into ``dataset`` (its ``extra-datasets`` option, dataset
        names, comma-separated); every stage's when ``stage`` is None."""
        stages = range(self.num_stages) if stage is None else (stage,)
        names: list[str] = []
        for s in stages:
            value = dict(self.stage_options(s)).get(EXTRA_DATASETS, "")
            names += [n for n in str(value).split(",") if n and n not in names]
        return tuple(names)

    def identity(self, dataset: DatasetRecipe, stage: int = 0,
                 extra: Mapping[str, DatasetRecipe] | None = None) -> dict[str, Any]:
        """What makes two trainings the same (not paths or device); a stage is the same only when every
        stage before it is. ``extra``: the recipes of ``extra-datasets`` up to this stage (recorded
        only when there are any)."""
        identity: dict[str, Any] = {"preset": self.preset, "options": [list(o) for o in self.options],
                                    "dataset": dataset.to_dict()}
        if self.start:
            identity["start"] = {"name": self.start}
        if stage > 0:
            identity["finetune"] = [[list(o) for o in opts] for opts in self.finetune[:stage]]
        names = [n for s in range(stage + 1) for n in self.extra_datasets(s)]
        if names:
            extra = extra or {}
            identity["extra_datasets"] = {n: extra[n].to_dict() for n in sorted(set(names))}
        return identity

    def train_args(self, data_dir: Path, runs_dir: Path, stage: int = 0) -> list[str]:
        """``hrn-pyg train`` arguments of a stage, without ``--device``, ``--resume``,
        ``--no-progress``."""
        args = ["train", "--preset", self.preset, "--data", str(data_dir / self.dataset),
                "--out", str(runs_dir / self.run_name(stage))]
        options = dict(self.stage_options(stage))
        if EXTRA_DATASETS in options:  # dataset names -> their folders
            del options[EXTRA_DATASETS]
            options["extra-data"] = ",".join(str(data_dir / n) for n in self.extra_datasets(stage))
        if stage == 0:
            return args + (["--init-from", self.start] if self.start else []) + option_flags(options, TRAIN_FLAGS)
        return args + ["--init-from", str(runs_dir / self.run_name(stage - 1) / "model.pt"),
                       *option_flags(options, TRAIN_FLAGS)]

    def calibrate_args(self, scene: str, runs_dir: Path, data: Sequence[Path] = ()) -> list[str]:
        """``hrn-pyg calibrate`` arguments (without ``--device``, ``--no-progress``) for the run's model;
        empty without a calibrate table. With ``data``, the starts are those folders' validation
        episodes instead of ``--scene``'s fresh seeds."""
        if not self.calibrate:
            return []
        run = runs_dir / self.final_run
        where = [flag for folder in data for flag in ("--data", str(folder))] if data else ["--scene", scene]
        return ["calibrate", *where, "--model", str(run / self.model_file), "--out", str(run / CALIBRATED_NAME),
                *option_flags(dict(self.calibrate), CALIBRATE_FLAGS)]


@dataclass(frozen=True)
class Recipe:
    datasets: tuple[DatasetRecipe, ...]
    models: tuple[ModelRecipe, ...]

    def dataset(self, name: str) -> DatasetRecipe:
        return next(d for d in self.datasets if d.name == name)

    def identity(self, model: ModelRecipe, stage: int = 0) -> dict[str, Any]:
        """:meth:`ModelRecipe.identity` with the recipes of the model's datasets."""
        extra = {n: self.dataset(n) for n in model.extra_datasets()}
        identity = model.identity(self.dataset(model.dataset), stage, extra)
        if model.start:  # the start is part of what was trained: a changed file trains again
            from hrn_pyg.checkpoints import checkpoint_path

            path = checkpoint_path(model.start)
            identity["start"]["sha256"] = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None
        return identity

    def select(self, only: Sequence[str] = ()) -> tuple[ModelRecipe, ...]:
        """The models named in ``only`` (all when empty), in recipe order."""
        known = {m.name for m in self.models}
        unknown = sorted(set(only) - known)
        if unknown:
            raise ValueError(f"--only: unknown model(s) {unknown}; the recipe has {sorted(known)}")
        return tuple(m for m in self.models if not only or m.name in only)


#: recipe keys of a train table whose option is not ``--<key>`` (the key keeps its name, so
#: recorded identities stay the same)
TRAIN_FLAGS: dict[str, str] = {"steps": "--train-steps"}
#: recipe keys of a calibrate table whose option is not ``--<key>``
CALIBRATE_FLAGS: dict[str, str] = {"steps": "--horizon", "seeds": "--episode-seeds", "modules": "--module-sets"}


def option_flags(options: Mapping[str, OptionValue], flags_of: Mapping[str, str] | None = None) -> list[str]:
    """``{"batch-size": 4, "ema": True, "amp": False}`` -> ``["--batch-size", "4", "--ema"]``;
    underscores become dashes, and ``flags_of`` renames (``steps`` -> ``--train-steps``)."""
    flags: list[str] = []
    for key, value in options.items():
        flag = (flags_of or {}).get(key, "--" + key.replace("_", "-"))
        if isinstance(value, bool):
            flags += [flag] if value else []
        elif isinstance(value, tuple):  # a list in the recipe: one flag, several values
            flags += [flag, *map(str, value)]
        else:
            flags += [flag, str(value)]
    return flags


def _require(table: Mapping[str, Any], key: str, kind: type | tuple[type, ...], where: str) -> Any:
    if key not in table:
        raise ValueError(f"{where}: missing {key!r}")
    value = table[key]
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise ValueError(f"{where}: {key!r} has the wrong type ({value!r})")
    return value


def _check_keys(table: Mapping[str, Any], allowed: frozenset[str], where: str) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(allowed)}")


def _check_name(name: str, where: str) -> str:
    if not NAME_PATTERN.fullmatch(name):
        raise ValueError(f"{where}: name {name!r} must be letters, digits, '_' or '-'")
    return name


def _parse_dataset(name: str, table: Mapping[str, Any]) -> DatasetRecipe:
    where = f"datasets.{_check_name(name, 'datasets')}"
    _check_keys(table, DATASET_KEYS, where)
    episodes = _require(table, "episodes", int, where)
    steps = _require(table, "steps", int, where)
    seed_offset = table.get("seed_offset", 0)
    pitch = table.get("pitch")
    if episodes < 1 or steps < 1:
        raise ValueError(f"{where}: episodes and steps must be >= 1")
    if not isinstance(seed_offset, int) or isinstance(seed_offset, bool) or seed_offset < 0:
        raise ValueError(f"{where}: seed_offset must be an integer >= 0, got {seed_offset!r}")
    if pitch is not None and (isinstance(pitch, bool) or not isinstance(pitch, (int, float)) or pitch <= 0):
        raise ValueError(f"{where}: pitch must be a number > 0, got {pitch!r}")
    overrides = table.get("set", {})
    if not isinstance(overrides, Mapping) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool)
            or isinstance(v, list) and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
            for v in overrides.values()):
        raise ValueError(f"{where}: 'set' must be a table of scene-config fields, each a number or a list of numbers")
    return DatasetRecipe(name, _require(table, "scene", str, where), episodes, steps, seed_offset,
                         None if pitch is None else float(pitch),
                         tuple((k, tuple(v) if isinstance(v, list) else v) for k, v in overrides.items()))


def _parse_options(table: Any, where: str, kind: str = "train") -> tuple[tuple[str, OptionValue], ...]:
    if not isinstance(table, Mapping):
        raise ValueError(f"{where}: '{kind}' must be a table of train options")
    options = []
    for key, value in table.items():
        if not OPTION_PATTERN.fullmatch(key):
            raise ValueError(f"{where}.{kind}: {key!r} is not an option name")
        if key.replace("_", "-") in RESERVED_OPTIONS:
            raise ValueError(f"{where}.{kind}: {key!r} is set by the recipe runner itself")
        if not isinstance(value, (str, int, float, bool)):
            raise ValueError(f"{where}.{kind}: {key!r} must be a string, number or boolean, got {value!r}")
        if key.replace("_", "-") == EXTRA_DATASETS:
            if not isinstance(value, str) or not all(NAME_PATTERN.fullmatch(n) for n in value.split(",")):
                raise ValueError(f"{where}.{kind}: {key!r} must be dataset names, comma-separated, got {value!r}")
            key = EXTRA_DATASETS
        options.append((key, value))
    return tuple(options)


def _parse_calibrate(table: Any, where: str) -> tuple[tuple[str, OptionValue | tuple[str, ...]], ...]:
    if not isinstance(table, Mapping):
        raise ValueError(f"{where}: 'calibrate' must be a table of calibrate options")
    options: list[tuple[str, OptionValue | tuple[str, ...]]] = []
    for key, value in table.items():
        if not OPTION_PATTERN.fullmatch(key):
            raise ValueError(f"{where}.calibrate: {key!r} is not an option name")
        if key.replace("_", "-") in RESERVED_CALIBRATE_OPTIONS:
            raise ValueError(f"{where}.calibrate: {key!r} is set by the recipe runner itself")
        if isinstance(value, list) and value and all(isinstance(v, str) for v in value):
            options.append((key, tuple(value)))
        elif isinstance(value, (str, int, float)) and not isinstance(value, bool):
            options.append((key, value))
        else:
            raise ValueError(f"{where}.calibrate: {key!r} must be a string, a number or a list of strings, "
                             f"got {value!r}")
    return tuple(options)


def _parse_average(table: Any, where: str, num_stages: int) -> tuple[tuple[int, float], ...]:
    """``[models.<name>.average]``: ``stages`` (at least two stage numbers, rising, the last
    one the model's last stage, whose config and normaliser the mean keeps) and ``weights``
    (one per stage, > 0, summing to one; equal when left out)."""
    from experiments.recipe.weights import check_average_weights  # imports torch; only for a recipe that averages

    if not isinstance(table, Mapping):
        raise ValueError(f"{where}: 'average' must be a table with 'stages' (and 'weights')")
    _check_keys(table, AVERAGE_KEYS, f"{where}.average")
    stages = _require(table, "stages", list, f"{where}.average")
    if (len(stages) < 2 or not all(isinstance(s, int) and not isinstance(s, bool) for s in stages)
            or any(b <= a for a, b in zip(stages, stages[1:])) or stages[0] < 0 or stages[-1] != num_stages - 1):
        raise ValueError(f"{where}.average: stages must be two or more rising stage numbers ending with the last "
                         f"stage ({num_stages - 1}), got {stages!r}")
    weights = table.get("weights", [1.0 / len(stages)] * len(stages))
    if not isinstance(weights, list) or not all(isinstance(w, (int, float)) and not isinstance(w, bool) for w in weights):
        raise ValueError(f"{where}.average: weights must be a list of numbers, got {weights!r}")
    try:
        values = check_average_weights(weights, len(stages))
    except ValueError as exc:
        raise ValueError(f"{where}.{exc}") from None
    return tuple(zip(stages, values, strict=True))


def _parse_apply(table: Any, where: str) -> tuple[tuple[str, OptionValue], ...]:
    """``[models.<name>.apply]``: options of :data:`hrn_pyg.checkpoints.APPLIED_OPTIONS` (dashes
    or underscores) and their values (booleans or numbers), at least one."""
    from hrn_pyg.checkpoints import APPLIED_OPTIONS  # imports torch; only for a recipe that applies options

    if not isinstance(table, Mapping) or not table:
        raise ValueError(f"{where}: 'apply' must be a table of one or more applied options")
    options = []
    for key, value in table.items():
        name = str(key).replace("-", "_")
        if name not in APPLIED_OPTIONS:
            raise ValueError(f"{where}.apply: {key!r} is not an applied option ({', '.join(APPLIED_OPTIONS)})")
        if not isinstance(value, (bool, int, float)):
            raise ValueError(f"{where}.apply: {key!r} must be a boolean or a number, got {value!r}")
        options.append((name, value))
    return tuple(options)


def _parse_model(name: str, table: Mapping[str, Any], datasets: set[str]) -> ModelRecipe:
    where = f"models.{_check_name(name, 'models')}"
    _check_keys(table, MODEL_KEYS, where)
    dataset = _require(table, "dataset", str, where)
    if dataset not in datasets:
        raise ValueError(f"{where}: dataset {dataset!r} is not in [datasets]")
    aliases = table.get("aliases", [])
    if not isinstance(aliases, list) or not all(isinstance(a, str) for a in aliases):
        raise ValueError(f"{where}: aliases must be a list of names")
    start = table.get("start", "")
    if not isinstance(start, str) or (start and not NAME_PATTERN.fullmatch(start)):
        raise ValueError(f"{where}: start must be a shipped checkpoint's name, got {start!r}")
    stages = table.get("finetune", [])
    if not isinstance(stages, list) or ("finetune" in table and not stages):
        raise ValueError(f"{where}: 'finetune' must be a list of tables ([[{where}.finetune]])")
    model = ModelRecipe(name, dataset, _require(table, "preset", str, where),
                        _parse_options(table.get("train", {}), where),
                        tuple(_check_name(a, f"{where}.aliases") for a in aliases),
                        _parse_calibrate(table["calibrate"], where) if "calibrate" in table else (),
                        tuple(_parse_options(t, where, f"finetune[{i}]") for i, t in enumerate(stages)), start,
                        _parse_average(table["average"], where, 1 + len(stages)) if "average" in table else (),
                        _parse_apply(table["apply"], where) if "apply" in table else ())
    unknown = sorted(set(model.extra_datasets()) - datasets)
    if unknown:
        raise ValueError(f"{where}: {EXTRA_DATASETS} {unknown} not in [datasets]")
    if dataset in model.extra_datasets():
        raise ValueError(f"{where}: {EXTRA_DATASETS} repeats the model's own dataset {dataset!r}")
    return model


def parse_recipe(data: Mapping[str, Any]) -> Recipe:
    """A :class:`Recipe` from the parsed TOML; every problem is a one-line ``ValueError``."""
    _check_keys(data, frozenset({"datasets", "models"}), "recipe")
    datasets_table, models_table = data.get("datasets", {}), data.get("models", {})
    if not datasets_table or not models_table:
        raise ValueError("recipe: needs [datasets.<name>] and [models.<name>] tables")
    datasets = tuple(_parse_dataset(n, t) for n, t in datasets_table.items())
    models = tuple(_parse_model(n, t, {d.name for d in datasets}) for n, t in models_table.items())
    files = [n for m in models for n in (m.name, *m.aliases)]
    twice = sorted({n for n in files if files.count(n) > 1})
    if twice:
        raise ValueError(f"recipe: checkpoint name(s) {twice} used more than once")
    return Recipe(datasets, models)


def load_recipe(path: str | Path) -> Recipe:
    """The recipe in the TOML file ``path``. A top-level ``datasets_from = "other.toml"`` (a path
    relative to ``path``) adds that recipe's datasets to this one's, so a recipe of models that
    are not shipped (``data/generalist.toml``) trains on the shipped recipe's datasets by name."""
    path = Path(path)
    data = _read_toml(path)
    source = data.pop(DATASETS_FROM, None)
    if source is not None:  # another recipe's datasets, by name, beside this file's own
        if not isinstance(source, str) or not source:
            raise ValueError(f"recipe: {path}: {DATASETS_FROM} must be a recipe file's path, got {source!r}")
        borrowed = _read_toml(path.parent / source)
        if DATASETS_FROM in borrowed:
            raise ValueError(f"recipe: {path.parent / source} has {DATASETS_FROM} itself; name the file it reads")
        own = data.get("datasets", {})
        both = sorted(set(own) & set(borrowed.get("datasets", {})))
        if both:
            raise ValueError(f"recipe: {path} defines dataset(s) {both} that {source} defines too")
        data["datasets"] = {**borrowed.get("datasets", {}), **own}
    return parse_recipe(data)


def _read_toml(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise FileNotFoundError(f"recipe: {path} does not exist")
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"recipe: {path} is not valid TOML ({exc})") from None


def shown(args: Sequence[str]) -> str:
    """The command line a person would type for ``hrn-pyg`` arguments ``args``."""
    return shlex.join(["hrn-pyg", *args])
