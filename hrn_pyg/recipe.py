"""``hrn-pyg checkpoints``: remake the shipped checkpoints from the recipe in ``data/recipes.toml``.

The recipe (TOML, read with :mod:`tomllib`) names every dataset (``[datasets.<name>]``: scene,
episodes, steps, seed_offset, optional pitch) and every shipped model (``[models.<name>]``:
dataset, preset, optional aliases, and a free-form ``[models.<name>.train]`` table of extra
``hrn-pyg train`` options: ``key = value`` becomes ``--key value``, ``true`` a bare ``--key``,
``false`` nothing).

One run does, for the selected models (``--only``, default all):

1. ``hrn-pyg generate`` for each of their datasets into ``<data-dir>/<dataset>`` (it skips the
   episodes already written, so a killed generation resumes);
2. ``hrn-pyg train`` for each model into ``<runs-dir>/<model>``, up to ``--jobs`` at once, each
   in its own process: skipped when ``model.pt`` exists and the run's ``recipe.json`` records the
   same preset, options and dataset; ``--resume`` when ``last.pt`` exists; a run folder made
   with other options is renamed aside (``<model>.replaced-<time>``), never deleted;
2b. for a model with ``[[models.<name>.finetune]]`` tables (each a table of train options, in
   order): fine-tunes stage by stage, each ``hrn-pyg train --init-from`` the previous stage's
   ``model.pt`` into ``<runs-dir>/<model>.ft<i>``, with the same rules (skip, resume, replace;
   a stage is redone when anything before it changes); the last stage is the model;
3. for a model with a ``[models.<name>.calibrate]`` table (``hrn-pyg calibrate`` options; a
   list of strings becomes one flag with several values, e.g. ``modules``): calibrates the
   run's ``model.pt`` into ``model.calibrated.pt`` (validation seeds only; redone only when
   ``model.pt`` or the options change, ``calibration.json``);
4. copies ``model.pt`` (the calibrated copy when there is one) to
   ``<checkpoints-dir>/<model>.pt`` (and each alias) atomically and refreshes the model's entry
   in ``<checkpoints-dir>/manifest.json`` (dataset recipe, the exact commands, training steps,
   device, wall seconds of the training invocations, the calibrated rate and modules).

Every step is idempotent, so after a kill at any point the same command continues where it
stopped. ``--dry-run`` prints what would run and writes nothing.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
import tomllib
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from hrn_pyg.utils.files import atomic_write, atomic_write_json

#: default recipe, relative to the working directory (the repository root)
RECIPE_PATH = "data/recipes.toml"
#: where the shipped checkpoints live
CHECKPOINTS_DIR = Path(__file__).resolve().parent / "checkpoints"
MANIFEST_NAME = "manifest.json"
#: per-run record of what the run folder was trained with, and of every train invocation
RUN_RECORD = "recipe.json"
#: seconds a child process gets to save and exit after Ctrl-C before it is interrupted again
STOP_GRACE_S = 30.0
#: dataset, model and alias names: plain file names
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]*")
OPTION_PATTERN = re.compile(r"[A-Za-z][A-Za-z0-9_-]*")
#: train options the runner sets itself; a recipe may not
RESERVED_OPTIONS = frozenset({"preset", "data", "out", "resume", "no-progress", "device", "time-limit",
                              "init-from", "extra-data"})
#: the train option naming more recipe datasets (comma-separated) whose episodes join the
#: model's dataset in a stage; the runner passes their folders as ``--extra-data``
EXTRA_DATASETS = "extra-datasets"
DATASET_KEYS = frozenset({"scene", "episodes", "steps", "seed_offset", "pitch", "set"})
MODEL_KEYS = frozenset({"dataset", "preset", "aliases", "train", "calibrate", "finetune"})
#: calibrate options the runner sets itself; a recipe may not
RESERVED_CALIBRATE_OPTIONS = frozenset({"scene", "model", "out", "in-place", "device", "no-progress", "data"})
#: the calibrated copy of a run's model.pt, and the record of what it was calibrated from
CALIBRATED_NAME = "model.calibrated.pt"
CALIBRATION_RECORD = "calibration.json"

OptionValue = str | int | float | bool


# --------------------------------------------------------------------------------------------
# the recipe


@dataclass(frozen=True)
class DatasetRecipe:
    """One ``hrn-pyg generate`` dataset: episode ``i`` has seed ``seed_offset + i``."""

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
        return d

    def generate_args(self, data_dir: Path) -> list[str]:
        """``hrn-pyg generate`` arguments (no worker count: it does not change the bytes)."""
        args = ["generate", "--scene", self.scene, "--episodes", str(self.episodes),
                "--out", str(self.folder(data_dir)), "--steps", str(self.steps),
                "--seed-offset", str(self.seed_offset)]
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
        """What makes two trainings the same (paths and device do not); a fine-tuning stage is
        the same only when every stage before it is too. ``extra``: the recipes of the datasets
        named in ``extra-datasets`` options up to this stage (recorded only when there are any,
        so the records of models without them stay as they were)."""
        identity: dict[str, Any] = {"preset": self.preset, "options": [list(o) for o in self.options],
                                    "dataset": dataset.to_dict()}
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
            return args + option_flags(options)
        return args + ["--init-from", str(runs_dir / self.run_name(stage - 1) / "model.pt"), *option_flags(options)]

    def calibrate_args(self, scene: str, runs_dir: Path) -> list[str]:
        """``hrn-pyg calibrate`` arguments (without ``--device``, ``--no-progress``): the run's
        model.pt into its calibrated copy; empty when the recipe has no calibrate table."""
        if not self.calibrate:
            return []
        run = runs_dir / self.final_run
        return ["calibrate", "--scene", scene, "--model", str(run / "model.pt"), "--out", str(run / CALIBRATED_NAME),
                *option_flags(dict(self.calibrate))]


@dataclass(frozen=True)
class Recipe:
    datasets: tuple[DatasetRecipe, ...]
    models: tuple[ModelRecipe, ...]

    def dataset(self, name: str) -> DatasetRecipe:
        return next(d for d in self.datasets if d.name == name)

    def identity(self, model: ModelRecipe, stage: int = 0) -> dict[str, Any]:
        """:meth:`ModelRecipe.identity` with the recipes of the model's datasets."""
        extra = {n: self.dataset(n) for n in model.extra_datasets()}
        return model.identity(self.dataset(model.dataset), stage, extra)

    def select(self, only: Sequence[str] = ()) -> tuple[ModelRecipe, ...]:
        """The models named in ``only`` (all when empty), in recipe order."""
        known = {m.name for m in self.models}
        unknown = sorted(set(only) - known)
        if unknown:
            raise ValueError(f"--only: unknown model(s) {unknown}; the recipe has {sorted(known)}")
        return tuple(m for m in self.models if not only or m.name in only)


def option_flags(options: Mapping[str, OptionValue]) -> list[str]:
    """``{"batch-size": 4, "ema": True, "amp": False}`` -> ``["--batch-size", "4", "--ema"]``.

    Underscores in keys become dashes (``batch_size`` is ``--batch-size``).
    """
    flags: list[str] = []
    for key, value in options.items():
        flag = "--" + key.replace("_", "-")
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
            raise ValueError(f"{where}.{kind}: {key!r} is set by `hrn-pyg checkpoints` itself")
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
            raise ValueError(f"{where}.calibrate: {key!r} is set by `hrn-pyg checkpoints` itself")
        if isinstance(value, list) and value and all(isinstance(v, str) for v in value):
            options.append((key, tuple(value)))
        elif isinstance(value, (str, int, float)) and not isinstance(value, bool):
            options.append((key, value))
        else:
            raise ValueError(f"{where}.calibrate: {key!r} must be a string, a number or a list of strings, "
                             f"got {value!r}")
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
    stages = table.get("finetune", [])
    if not isinstance(stages, list) or ("finetune" in table and not stages):
        raise ValueError(f"{where}: 'finetune' must be a list of tables ([[{where}.finetune]])")
    model = ModelRecipe(name, dataset, _require(table, "preset", str, where),
                        _parse_options(table.get("train", {}), where),
                        tuple(_check_name(a, f"{where}.aliases") for a in aliases),
                        _parse_calibrate(table["calibrate"], where) if "calibrate" in table else (),
                        tuple(_parse_options(t, where, f"finetune[{i}]") for i, t in enumerate(stages)))
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
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"recipe: {path} does not exist")
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"recipe: {path} is not valid TOML ({exc})") from None
    return parse_recipe(data)


# --------------------------------------------------------------------------------------------
# running it


@dataclass(frozen=True)
class RunConfig:
    """Where things go and how the runner behaves (the sub-command's options)."""

    recipe: Path = Path(RECIPE_PATH)
    data_dir: Path = Path("data")
    runs_dir: Path = Path("runs/recipe")
    checkpoints_dir: Path = CHECKPOINTS_DIR
    device: str | None = None
    jobs: int = 1
    skip_generate: bool = False
    dry_run: bool = False
    only: tuple[str, ...] = ()
    time_limit: float = 0.0

    def __post_init__(self) -> None:
        if self.jobs < 1:
            raise ValueError(f"jobs: must be >= 1, got {self.jobs}")
        if not 0.0 <= self.time_limit < float("inf"):
            raise ValueError(f"time_limit: must be a finite number of minutes >= 0, got {self.time_limit}")


class Paused(RuntimeError):
    """A training stopped at ``--time-limit``; running the command again continues it."""


def shown(args: Sequence[str]) -> str:
    """The command line a person would type for ``hrn-pyg`` arguments ``args``."""
    return shlex.join(["hrn-pyg", *args])


def _cli(args: Sequence[str]) -> list[str]:
    """The same command run with this interpreter (independent of PATH and of a venv's bin)."""
    return [sys.executable, "-m", "hrn_pyg.cli", *args]


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _copy_atomic(source: Path, target: Path) -> None:
    with open(source, "rb") as src:
        atomic_write(target, lambda fh: shutil.copyfileobj(src, fh))


def _free_name(path: Path) -> Path:
    """``path``, or ``path-1``, ``path-2`` ... whichever does not exist yet."""
    candidate, n = path, 0
    while candidate.exists():
        n += 1
        candidate = path.with_name(f"{path.name}-{n}")
    return candidate


def _stop(proc: subprocess.Popen, grace: float = STOP_GRACE_S) -> None:
    """End a child after Ctrl-C: a child that got the same SIGINT saves and exits by itself;
    otherwise it is sent SIGINT (train then saves its checkpoint), and last SIGKILL."""
    for sig in (None, signal.SIGINT, signal.SIGKILL):
        if proc.poll() is not None:
            return
        if sig is not None:
            proc.send_signal(sig)
        try:
            proc.wait(timeout=grace)
            return
        except subprocess.TimeoutExpired:
            continue


class Runner:
    """Carries out a :class:`Recipe` under a :class:`RunConfig`; ``say`` prints one line."""

    def __init__(self, recipe: Recipe, config: RunConfig, say: Callable[[str], None] = print) -> None:
        self.recipe, self.config = recipe, config
        self.models = recipe.select(config.only)
        self._say = say
        self._lock = threading.Lock()  # manifest, printing and children, from training threads
        self._children: set[subprocess.Popen] = set()
        self._interrupted = False
        self.paused: list[str] = []  # models stopped at --time-limit in this call

    def call(self, args: Sequence[str], **popen_kwargs: Any) -> int:
        """Run ``hrn-pyg args`` in a child process and wait for it; its exit code."""
        with self._lock:
            if self._interrupted:
                return -int(signal.SIGINT)
            proc = subprocess.Popen(_cli(args), **popen_kwargs)
            self._children.add(proc)
        try:
            return proc.wait()
        except KeyboardInterrupt:
            _stop(proc)
            raise
        finally:
            with self._lock:
                self._children.discard(proc)

    def interrupt(self) -> None:
        """Ctrl-C in parallel mode: start nothing new, end the running children."""
        with self._lock:
            self._interrupted = True
            children = list(self._children)
        for proc in children:
            _stop(proc)

    def say(self, line: str) -> None:
        with self._lock:
            self._say(line)

    # -- datasets ------------------------------------------------------------------------------
    def datasets(self) -> list[DatasetRecipe]:
        """The datasets the selected models need, in recipe order."""
        needed = {n for m in self.models for n in (m.dataset, *m.extra_datasets())}
        return [d for d in self.recipe.datasets if d.name in needed]

    def generate(self, dataset: DatasetRecipe) -> None:
        cfg = self.config
        if cfg.skip_generate:
            missing = [f for f in dataset.episode_files(cfg.data_dir) if not f.is_file()]
            if missing and not cfg.dry_run:
                raise FileNotFoundError(f"--skip-generate: {len(missing)} of {dataset.episodes} episodes of "
                                        f"dataset {dataset.name!r} missing in {dataset.folder(cfg.data_dir)}")
            self.say(f"dataset {dataset.name}: not generated (--skip-generate)")
            return
        args = dataset.generate_args(cfg.data_dir)
        self.say(shown(args))
        if cfg.dry_run:
            return
        rc = self.call([*args, "--workers", str(cfg.jobs)])
        if rc != 0:
            raise RuntimeError(f"dataset {dataset.name}: `{shown(args)}` exited with {rc}")

    # -- training ------------------------------------------------------------------------------
    def train_command(self, model: ModelRecipe, stage: int = 0) -> list[str]:
        args = model.train_args(self.config.data_dir, self.config.runs_dir, stage)
        args += ["--device", self.config.device] if self.config.device else []
        # a sitting's time limit is how long this call may run, not part of the training
        return args + (["--time-limit", str(self.config.time_limit)] if self.config.time_limit > 0 else [])

    def plan(self, model: ModelRecipe, stage: int = 0) -> str:
        """``"done"`` (model.pt of these options), ``"resume"``, ``"fresh"`` or ``"replace"``
        (the run folder holds another training: it is renamed aside, then fresh)."""
        run = self.config.runs_dir / model.run_name(stage)
        if not run.exists():
            return "fresh"
        record = _read_json(run / RUN_RECORD)
        identity = self.recipe.identity(model, stage)
        if record is None or record.get("identity") != identity:
            return "replace"
        if (run / "model.pt").is_file():
            return "done"
        return "resume" if (run / "last.pt").is_file() else "fresh"

    def train(self, model: ModelRecipe) -> None:
        """Train (or finish training) one model, stage by stage; raises ``RuntimeError`` when
        train fails."""
        for stage in range(model.num_stages):
            self._train_stage(model, stage)

    def _train_stage(self, model: ModelRecipe, stage: int) -> None:
        cfg, run = self.config, self.config.runs_dir / model.run_name(stage)
        plan = self.plan(model, stage)
        label = model.run_name(stage)
        args = self.train_command(model, stage) + (["--resume"] if plan == "resume" else [])
        if plan == "done":
            self.say(f"model {label}: trained already ({run / 'model.pt'})")
            return
        if plan == "replace":
            aside = _free_name(run.with_name(f"{run.name}.replaced-{time.strftime('%Y%m%d-%H%M%S')}"))
            verb = "would move" if cfg.dry_run else "moved"
            self.say(f"model {label}: {run} holds a training with other options; {verb} it to {aside}")
            if not cfg.dry_run:
                run.rename(aside)
        self.say(shown(args))
        if cfg.dry_run:
            return
        if plan == "fresh":  # rows a run killed before its first checkpoint left behind
            (run / "metrics.csv").unlink(missing_ok=True)
        record = self._start_record(model, run, args, stage)
        quiet = cfg.jobs > 1  # parallel runs log to files instead of sharing the terminal
        start = time.perf_counter()
        rc: int | None = None
        try:
            if quiet:
                with open(run / "train.log", "ab") as log:
                    rc = self.call([*args, "--no-progress"], stdout=log, stderr=subprocess.STDOUT)
            else:
                rc = self.call(args)
        finally:  # also on Ctrl-C: the time spent counts
            record["invocations"][-1].update(seconds=round(time.perf_counter() - start, 3),
                                             rc=-int(signal.SIGINT) if rc is None else rc)
            atomic_write_json(run / RUN_RECORD, record)
        if rc == 0 and cfg.time_limit > 0 and not (run / "model.pt").is_file() and (run / "last.pt").is_file():
            raise Paused(f"model {label}: stopped at the {cfg.time_limit:g}-minute time limit; "
                         "run the command again to continue")
        if rc != 0 or not (run / "model.pt").is_file():
            where = f" (log: {run / 'train.log'})" if quiet else ""
            raise RuntimeError(f"model {label}: `{shown(args)}` exited with {rc}{where}")
        self.say(f"model {label}: trained in {record['invocations'][-1]['seconds']:.0f} s")

    def _start_record(self, model: ModelRecipe, run: Path, args: list[str], stage: int = 0) -> dict[str, Any]:
        """Write the run's record (before training, so a killed run is recognised as ours)."""
        record = _read_json(run / RUN_RECORD) or {}
        record = {"identity": self.recipe.identity(model, stage),
                  "invocations": [*record.get("invocations", []),
                                  {"command": shown(args), "args": list(args), "device": self.device_name(),
                                   "seconds": None, "rc": None}]}
        run.mkdir(parents=True, exist_ok=True)
        atomic_write_json(run / RUN_RECORD, record)
        return record

    def device_name(self) -> str:
        """The device train runs on: ``--device`` or train's default (CUDA when available)."""
        from hrn_pyg.utils.device import resolve_device  # imports torch; only when training

        return str(resolve_device(self.config.device))

    # -- publishing ----------------------------------------------------------------------------
    def calibrate_command(self, model: ModelRecipe) -> list[str]:
        scene = self.recipe.dataset(model.dataset).scene
        args = model.calibrate_args(scene, self.config.runs_dir)
        return args + (["--device", self.config.device] if args and self.config.device else [])

    def calibrate(self, model: ModelRecipe) -> None:
        """``hrn-pyg calibrate`` the run's model.pt into ``model.calibrated.pt`` when the recipe
        asks for it; skipped when the copy exists and was made from this model.pt with these
        options (``calibration.json``). Raises ``RuntimeError`` when calibrate fails."""
        args = self.calibrate_command(model)
        if not args:
            return
        run = self.config.runs_dir / model.final_run
        if self.config.dry_run:
            self.say(shown(args))
            return
        record = {"model_sha256": _sha256(run / "model.pt"), "options": [list(o) if not isinstance(o[1], tuple)
                                                                          else [o[0], list(o[1])] for o in model.calibrate]}
        if (run / CALIBRATED_NAME).is_file() and _read_json(run / CALIBRATION_RECORD) == record:
            return
        self.say(f"model {model.name}: {shown(args)}")
        with open(run / "calibrate.log", "w") as log:
            rc = self.call([*args, "--no-progress"], stdout=log, stderr=subprocess.STDOUT)
        if rc != 0 or not (run / CALIBRATED_NAME).is_file():
            raise RuntimeError(f"model {model.name}: `{shown(args)}` exited with {rc} (log: {run / 'calibrate.log'})")
        atomic_write_json(run / CALIBRATION_RECORD, record)

    def publish(self, model: ModelRecipe) -> None:
        """Copy the run's model.pt (its calibrated copy when the recipe calibrates it) to the
        checkpoints folder and refresh the manifest."""
        cfg, run = self.config, self.config.runs_dir / model.final_run
        source = run / (CALIBRATED_NAME if model.calibrate else "model.pt")
        if cfg.dry_run:
            self.say(f"copy {source} -> {cfg.checkpoints_dir / (model.name + '.pt')}"
                     + "".join(f", {a}.pt" for a in model.aliases) + f"; refresh {MANIFEST_NAME}")
            return
        digest = _sha256(source)
        for name in (model.name, *model.aliases):
            target = cfg.checkpoints_dir / f"{name}.pt"
            if not target.is_file() or _sha256(target) != digest:
                _copy_atomic(source, target)
                self.say(f"model {model.name}: wrote {target}")
        self._update_manifest(model, run, digest)

    def manifest_entry(self, model: ModelRecipe, run: Path, digest: str) -> dict[str, Any]:
        dataset = self.recipe.dataset(model.dataset)
        folders = [self.config.runs_dir / model.run_name(i) for i in range(model.num_stages)]
        # per stage: the invocations that ended, and the command that made its model.pt (its
        # last invocation), as one would type it afresh
        done = [[i for i in (_read_json(f / RUN_RECORD) or {}).get("invocations", []) if i.get("seconds") is not None]
                for f in folders]
        commands = [shown([a for a in (d[-1]["args"] if d else self.train_command(model, i)) if a != "--resume"])
                    for i, d in enumerate(done)]
        steps = [(_read_json(f / "config.json") or {}).get("train", {}).get("steps") for f in folders]
        invocations = [i for d in done for i in d]
        stages = {"stage_commands": commands, "stage_steps": steps} if model.num_stages > 1 else {}
        return {
            "name": model.name,
            "aliases": list(model.aliases),
            "dataset": dataset.to_dict(),
            "generate_command": shown(dataset.generate_args(self.config.data_dir)),
            "train_command": commands[-1],
            "steps": steps[-1],
            "device": ",".join(sorted({i["device"] for i in invocations})),
            "wall_seconds": round(sum(i["seconds"] for i in invocations), 3),
            "train_invocations": len(invocations),
            "sha256": digest,
            **stages,
            **self._calibration_entry(model, run),
        }

    def _calibration_entry(self, model: ModelRecipe, run: Path) -> dict[str, Any]:
        """The manifest's calibration fields: the command and the chosen rate and modules."""
        if not model.calibrate:
            return {}
        from hrn_pyg.sampling.calibrate import calibration_record  # imports torch

        record = calibration_record(run / CALIBRATED_NAME) or {}
        chosen = {k: record.get(k) for k in ("rate", "modules", "spread_ratio_median", "seeds")}
        return {"calibrate_command": shown(self.calibrate_command(model)), "calibrated": chosen}

    def _update_manifest(self, model: ModelRecipe, run: Path, digest: str) -> None:
        entry = self.manifest_entry(model, run, digest)
        path = self.config.checkpoints_dir / MANIFEST_NAME
        with self._lock:
            manifest = _read_json(path) or {}
            entries = manifest.get("checkpoints", {})
            old = dict(entries.get(model.name, {}))
            old.pop("updated", None)
            if old == entry:
                return
            entries[model.name] = {**entry, "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
            atomic_write_json(path, {"about": "how each checkpoint here was made: `hrn-pyg checkpoints` "
                                              "from data/recipes.toml", "checkpoints": dict(sorted(entries.items()))})

    # -- everything ----------------------------------------------------------------------------
    def build(self, model: ModelRecipe) -> None:
        self.train(model)
        self.calibrate(model)
        self.publish(model)

    def run(self) -> list[str]:
        """Generate, train and publish; returns what failed (``"dataset X"``, model names).

        A dataset that fails to generate stops the run (its models cannot train); a model that
        fails to train is reported and the others go on.
        """
        if not self.config.dry_run and not self.config.skip_generate:
            self.config.data_dir.mkdir(parents=True, exist_ok=True)
        for dataset in self.datasets():
            try:
                self.generate(dataset)
            except RuntimeError as exc:
                self.say(f"FAILED: {exc}")
                return [f"dataset {dataset.name}"]
        if not self.config.dry_run:
            self.device_name()  # a bad --device fails here, before any training starts
        failed: list[str] = []

        def attempt(model: ModelRecipe) -> None:
            if self._interrupted:
                return
            try:
                self.build(model)
            except Paused as exc:
                self.say(f"PAUSED: {exc}")
                self.paused.append(model.name)
            except RuntimeError as exc:
                self.say(f"FAILED: {exc}")
                failed.append(model.name)

        if self.config.jobs == 1:
            for model in self.models:
                attempt(model)
            return failed
        pool = ThreadPoolExecutor(max_workers=self.config.jobs)
        try:
            wait([pool.submit(attempt, model) for model in self.models])
        except KeyboardInterrupt:
            self.interrupt()
            raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
        return failed


# --------------------------------------------------------------------------------------------
# command line


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--recipe", default=RECIPE_PATH, help=f"recipe file (default {RECIPE_PATH})")
    parser.add_argument("--only", default="", help="NAME[,NAME]: only these models (default all)")
    parser.add_argument("--data-dir", default="data", help="datasets go to DATA_DIR/<dataset> (default data)")
    parser.add_argument("--runs-dir", default="runs/recipe", help="run folders (default runs/recipe)")
    parser.add_argument("--checkpoints-dir", default=str(CHECKPOINTS_DIR),
                        help="where <model>.pt and manifest.json go (default: the package's checkpoints)")
    parser.add_argument("--device", default=None, help="passed to train (default: CUDA when available)")
    parser.add_argument("--jobs", type=int, default=1,
                        help="trainings at once, each its own process; also generate's --workers (default 1)")
    parser.add_argument("--skip-generate", action="store_true",
                        help="the datasets are already there (checked, not generated)")
    parser.add_argument("--dry-run", action="store_true", help="print the commands, run and write nothing")
    parser.add_argument("--time-limit", type=float, default=0.0,
                        help="minutes each training may run in this call; a rerun continues it (default: none)")


def config_from_args(args: argparse.Namespace) -> RunConfig:
    return RunConfig(recipe=Path(args.recipe), data_dir=Path(args.data_dir), runs_dir=Path(args.runs_dir),
                     checkpoints_dir=Path(args.checkpoints_dir), device=args.device or None, jobs=args.jobs,
                     skip_generate=args.skip_generate, dry_run=args.dry_run,
                     only=tuple(n for n in args.only.split(",") if n), time_limit=args.time_limit)


def run(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    runner = Runner(load_recipe(config.recipe), config, say=lambda line: print(line, flush=True))
    failed = runner.run()
    if failed:
        print(f"hrn-pyg checkpoints: failed: {', '.join(failed)}; rerun to continue", file=sys.stderr)
        return 1
    if runner.paused:
        print(f"paused at the time limit: {', '.join(runner.paused)}; rerun the same command to continue")
        return 0
    if not config.dry_run:
        print(f"checkpoints up to date: {', '.join(m.name for m in runner.models)}")
    return 0
