"""The runner of ``python -m experiments.recipe``: carries out a recipe, one child process per step.

For the selected models (``--only``, default all):

1. ``hrn-pyg generate`` each dataset into ``<data-dir>/<dataset>`` (resumes);
2. ``hrn-pyg train`` each model into ``<runs-dir>/<model>``, up to ``--jobs`` at once: skipped
   when ``model.pt`` exists with the same ``recipe.json``, ``--resume`` from ``last.pt``, a
   folder made with other options renamed aside (never deleted); then the fine-tuning stages
   (``<model>.ft<i>``, each ``--init-from`` the previous), the weighted average of stages
   (``model.averaged.pt``) and the applied options (``model.applied.pt``), each redone only
   when what it is made from changes;
3. ``hrn-pyg calibrate`` into ``model.calibrated.pt`` where the recipe asks (validation seeds);
4. copy the model to ``<checkpoints-dir>/<model>.pt`` (and aliases) atomically and refresh its
   entry in ``manifest.json`` (:mod:`experiments.recipe.manifest`) with the checkpoint's domain.
   ``<checkpoints-dir>`` is ``./checkpoints`` unless named.

Every step is idempotent, so a killed run continues where it stopped. With
:attr:`RunConfig.dry_run` it prints what would run and writes nothing.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from experiments.recipe.manifest import (
    MANIFEST_NAME,
    RUN_RECORD,
    copy_atomic,
    model_entry,
    read_json,
    sha256,
    update_manifest,
)
from experiments.recipe.schema import (
    APPLIED_NAME,
    AVERAGED_NAME,
    CALIBRATED_NAME,
    RECIPE_PATH,
    DatasetRecipe,
    ModelRecipe,
    Recipe,
    shown,
)
from hrn_pyg.utils.files import atomic_write_json

#: seconds a child process gets to save and exit after Ctrl-C before it is interrupted again
STOP_GRACE_S = 30.0
#: the record of what a run's calibrated copy was calibrated from
CALIBRATION_RECORD = "calibration.json"
#: the record of which stages' weights, with which weights, a run's averaged model was made from
AVERAGE_RECORD = "averaged.json"
#: the record of which file, with which options, a run's model.applied.pt was made from
APPLY_RECORD = "applied.json"
#: where the checkpoints and their manifest go unless named, relative to the working directory
#: (never the installed package's folder)
DEFAULT_CHECKPOINTS_DIR = Path("checkpoints")


@dataclass(frozen=True)
class RunConfig:
    """Where things go and how the runner behaves (the sub-command's options)."""

    recipe: Path = Path(RECIPE_PATH)
    data_dir: Path = Path("data")
    runs_dir: Path = Path("runs/recipe")
    checkpoints_dir: Path = DEFAULT_CHECKPOINTS_DIR
    device: str | None = None
    jobs: int = 1
    skip_generate: bool = False
    dry_run: bool = False
    only: tuple[str, ...] = ()
    time_limit: float = 0.0
    #: torch threads of every training in place of the recipe's (0: the recipe's); like the
    #: device, not part of what makes two trainings the same
    threads: int = 0

    def __post_init__(self) -> None:
        if self.jobs < 1:
            raise ValueError(f"jobs: must be >= 1, got {self.jobs}")
        if self.threads < 0:
            raise ValueError(f"threads: must be >= 0, got {self.threads}")
        if not 0.0 <= self.time_limit < float("inf"):
            raise ValueError(f"time_limit: must be a finite number of minutes >= 0, got {self.time_limit}")


class Paused(RuntimeError):
    """A training stopped at ``--time-limit``; running the command again continues it."""


def _cli(args: Sequence[str]) -> list[str]:
    """The same command run with this interpreter (independent of PATH and of a venv's bin)."""
    return [sys.executable, "-m", "hrn_pyg.cli", *args]


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
        if cfg.skip_generate:  # checked stage by stage, before each trains (check_datasets)
            self.say(f"dataset {dataset.name}: not generated (--skip-generate)")
            return
        args = dataset.generate_args(cfg.data_dir)
        self.say(shown(args))
        if cfg.dry_run:
            return
        rc = self.call([*args, "--workers", str(cfg.jobs)])
        if rc != 0:
            raise RuntimeError(f"dataset {dataset.name}: `{shown(args)}` exited with {rc}")

    def check_datasets(self, model: ModelRecipe, stage: int) -> None:
        """Under ``--skip-generate``: ``FileNotFoundError`` unless every episode a stage trains on is here
        (checked per stage, so later datasets may still be generating)."""
        for name in (model.dataset, *model.extra_datasets(stage)):
            dataset = self.recipe.dataset(name)
            # a seed pybullet lost is done too: `generate` marks it .rejected and never makes it again
            missing = [f for f in dataset.episode_files(self.config.data_dir)
                       if not f.is_file() and not f.with_suffix(".rejected").is_file()]
            if missing:
                raise FileNotFoundError(f"--skip-generate: {len(missing)} of {dataset.episodes} episodes of "
                                        f"dataset {name!r} missing in {dataset.folder(self.config.data_dir)} "
                                        f"(model {model.run_name(stage)})")

    # -- training ------------------------------------------------------------------------------
    def train_command(self, model: ModelRecipe, stage: int = 0) -> list[str]:
        args = model.train_args(self.config.data_dir, self.config.runs_dir, stage)
        args += ["--device", self.config.device] if self.config.device else []
        args += ["--threads", str(self.config.threads)] if self.config.threads else []  # the last one counts
        # a sitting's time limit is how long this call may run, not part of the training
        return args + (["--time-limit", str(self.config.time_limit)] if self.config.time_limit > 0 else [])

    def plan(self, model: ModelRecipe, stage: int = 0) -> str:
        """``"done"`` (model.pt of these options), ``"resume"``, ``"fresh"`` or ``"replace"``
        (the run folder holds another training: it is renamed aside, then fresh)."""
        run = self.config.runs_dir / model.run_name(stage)
        if not run.exists():
            return "fresh"
        record = read_json(run / RUN_RECORD)
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
        if cfg.skip_generate and not cfg.dry_run:
            try:
                self.check_datasets(model, stage)
            except FileNotFoundError as exc:
                raise RuntimeError(str(exc)) from None
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
        record = read_json(run / RUN_RECORD) or {}
        record = {"identity": self.recipe.identity(model, stage),
                  "invocations": [*record.get("invocations", []),
                                  {"command": shown(args), "args": list(args), "device": self.device_name(),
                                   "seconds": None, "rc": None}]}
        run.mkdir(parents=True, exist_ok=True)
        atomic_write_json(run / RUN_RECORD, record)
        return record

    def device_name(self) -> str:
        """The device train runs on: ``--device`` or train's default (CUDA when available)."""
        from hrn_pyg.utils.device import (
            resolve_device,  # imports torch; only when training
        )

        return str(resolve_device(self.config.device))

    # -- publishing ----------------------------------------------------------------------------
    def average(self, model: ModelRecipe) -> None:
        """Write the recipe's weighted mean of stages' weights into ``model.averaged.pt``;
        skipped when the copy exists and was made from these stages' model.pt files with these
        weights (``averaged.json``). Raises ``RuntimeError`` when the stages cannot be averaged."""
        if not model.average:
            return
        runs, run = self.config.runs_dir, self.config.runs_dir / model.final_run
        sources = [runs / model.run_name(stage) / "model.pt" for stage, _ in model.average]
        weights = [weight for _, weight in model.average]
        if self.config.dry_run:
            self.say(f"model {model.name}: average {', '.join(f'{w:g} x {s}' for s, w in zip(sources, weights))}"
                     f" -> {run / AVERAGED_NAME}")
            return
        record = {"sources": [{"stage": stage, "weight": weight, "model_sha256": sha256(source)}
                              for (stage, weight), source in zip(model.average, sources, strict=True)]}
        if (run / AVERAGED_NAME).is_file() and read_json(run / AVERAGE_RECORD) == record:
            return
        from experiments.recipe.weights import write_average  # imports torch

        try:
            write_average(sources, weights, run / AVERAGED_NAME)
        except ValueError as exc:
            raise RuntimeError(f"model {model.name}: {exc}") from None
        atomic_write_json(run / AVERAGE_RECORD, record)
        self.say(f"model {model.name}: wrote {run / AVERAGED_NAME}")

    def apply(self, model: ModelRecipe) -> None:
        """Write the trained model (:attr:`ModelRecipe.trained_file`) with the recipe's applied
        options into ``model.applied.pt``; skipped when the copy exists and was made from this
        file with these options (``applied.json``). Raises ``RuntimeError`` when they cannot be set."""
        if not model.apply:
            return
        run = self.config.runs_dir / model.final_run
        options = dict(model.apply)
        if self.config.dry_run:
            self.say(f"model {model.name}: set {options} on {run / model.trained_file} -> {run / APPLIED_NAME}")
            return
        record = {"model_sha256": sha256(run / model.trained_file), "options": [list(o) for o in model.apply]}
        if (run / APPLIED_NAME).is_file() and read_json(run / APPLY_RECORD) == record:
            return
        from experiments.recipe.weights import write_applied  # imports torch

        try:
            write_applied(run / model.trained_file, options, run / APPLIED_NAME)
        except ValueError as exc:
            raise RuntimeError(f"model {model.name}: {exc}") from None
        atomic_write_json(run / APPLY_RECORD, record)
        self.say(f"model {model.name}: wrote {run / APPLIED_NAME}")

    def calibrate_command(self, model: ModelRecipe) -> list[str]:
        dataset = self.recipe.dataset(model.dataset)
        folders: tuple[Path, ...] = ()
        if dataset.from_file:  # no --scene for a file: the datasets' folders name their scenes
            names = (model.dataset, *model.extra_datasets())
            folders = tuple(self.recipe.dataset(n).folder(self.config.data_dir) for n in names)
        args = model.calibrate_args(dataset.scene, self.config.runs_dir, folders)
        return args + (["--device", self.config.device] if args and self.config.device else [])

    def calibrate(self, model: ModelRecipe) -> None:
        """``hrn-pyg calibrate`` the run's model into ``model.calibrated.pt`` when the recipe asks, unless
        made from this model with these options (``calibration.json``); ``RuntimeError`` on failure."""
        args = self.calibrate_command(model)
        if not args:
            return
        run = self.config.runs_dir / model.final_run
        if self.config.dry_run:
            self.say(shown(args))
            return
        record = {"model_sha256": sha256(run / model.model_file), "options": [list(o) if not isinstance(o[1], tuple)
                                                                         else [o[0], list(o[1])] for o in model.calibrate]}
        if (run / CALIBRATED_NAME).is_file() and read_json(run / CALIBRATION_RECORD) == record:
            return
        self.say(f"model {model.name}: {shown(args)}")
        with open(run / "calibrate.log", "w") as log:
            rc = self.call([*args, "--no-progress"], stdout=log, stderr=subprocess.STDOUT)
        if rc != 0 or not (run / CALIBRATED_NAME).is_file():
            raise RuntimeError(f"model {model.name}: `{shown(args)}` exited with {rc} (log: {run / 'calibrate.log'})")
        atomic_write_json(run / CALIBRATION_RECORD, record)

    def publish(self, model: ModelRecipe) -> None:
        """Copy the run's model (:attr:`ModelRecipe.model_file`, or its calibrated copy when the
        recipe calibrates it) to the checkpoints folder and refresh the manifest."""
        cfg, run = self.config, self.config.runs_dir / model.final_run
        source = run / (CALIBRATED_NAME if model.calibrate else model.model_file)
        if cfg.dry_run:
            self.say(f"copy {source} -> {cfg.checkpoints_dir / (model.name + '.pt')}"
                     + "".join(f", {a}.pt" for a in model.aliases) + f"; refresh {MANIFEST_NAME}")
            return
        digest = sha256(source)
        for name in (model.name, *model.aliases):
            target = cfg.checkpoints_dir / f"{name}.pt"
            if not target.is_file() or sha256(target) != digest:
                copy_atomic(source, target)
                self.say(f"model {model.name}: wrote {target}")
        self._update_manifest(model, run, digest)

    def manifest_entry(self, model: ModelRecipe, run: Path, digest: str) -> dict[str, Any]:
        """The model's manifest entry (:func:`~experiments.recipe.manifest.model_entry`) with this
        runner's commands."""
        return model_entry(model, self.recipe.dataset(model.dataset), self.config.data_dir, self.config.runs_dir,
                           run, digest, lambda stage: self.train_command(model, stage),
                           lambda: self.calibrate_command(model))

    def _update_manifest(self, model: ModelRecipe, run: Path, digest: str) -> None:
        from hrn_pyg.checkpoints import checkpoint_domain  # imports torch

        entry = self.manifest_entry(model, run, digest)
        domain = checkpoint_domain(self.config.checkpoints_dir / f"{model.name}.pt")
        if domain is not None:
            entry["domain"] = domain.to_dict()
        path = self.config.checkpoints_dir / MANIFEST_NAME
        with self._lock:
            update_manifest(path, model.name, entry)

    # -- everything ----------------------------------------------------------------------------
    def build(self, model: ModelRecipe) -> None:
        self.train(model)
        self.average(model)
        self.apply(model)
        self.calibrate(model)
        self.publish(model)

    def run(self) -> list[str]:
        """Generate, train and publish; returns what failed (``"dataset X"``, model names). A dataset
        that fails stops the run; a model that fails is reported and the others go on."""
        if not self.config.dry_run and not self.config.skip_generate:
            self.config.data_dir.mkdir(parents=True, exist_ok=True)
        for dataset in self.datasets():
            try:
                self.generate(dataset)
            except RuntimeError as exc:
                self.say(f"FAILED: {exc}")
                return [f"dataset {dataset.name}"]
        if self.config.skip_generate and not self.config.dry_run:
            for model in self.models:  # each model's next stage to train; later ones before they train
                stage = next((s for s in range(model.num_stages) if self.plan(model, s) != "done"), None)
                if stage is not None:
                    self.check_datasets(model, stage)
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
