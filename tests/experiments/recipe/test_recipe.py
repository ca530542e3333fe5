"""``python -m experiments.recipe`` (``make checkpoints``): the recipe file, the commands, and a
killed run that continues where it stopped without redoing finished work."""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from experiments.recipe import (
    MANIFEST_NAME,
    RUN_RECORD,
    RunConfig,
    Runner,
    add_arguments,
    config_from_args,
    load_recipe,
    option_flags,
    parse_recipe,
)
from experiments.recipe import main as recipe_main
from experiments.recipe.manifest import logged_train_seconds, read_json, update_manifest
from experiments.recipe.schema import CALIBRATE_FLAGS
from hrn_pyg.checkpoints import CHECKPOINT_DIR
from hrn_pyg.cli import main

REPO = Path(__file__).resolve().parents[3]
TINY_MODEL = {"model-hidden": 8, "model-depth": 1, "model-effect-dim": 8, "batch-size": 2,
              "threads": 1, "warmup": 2, "eval-every": 1000}


def _toml_table(name: str, table: dict) -> str:
    lines = [f"[{name}]"]
    for key, value in table.items():
        if isinstance(value, bool):
            lines.append(f"{key} = {'true' if value else 'false'}")
        elif isinstance(value, str):
            lines.append(f'{key} = "{value}"')
        elif isinstance(value, list):
            lines.append(f"{key} = [{', '.join(json.dumps(v) for v in value)}]")
        else:
            lines.append(f"{key} = {value}")
    return "\n".join(lines) + "\n"


def _write_recipe(path: Path, b_steps: int = 4) -> Path:
    """Two tiny models on one tiny dataset; ``a`` is long enough to be killed part-way."""
    text = _toml_table("datasets.tiny", {"scene": "cube_collision", "episodes": 3, "steps": 12, "seed_offset": 0})
    text += _toml_table("models.a", {"dataset": "tiny", "preset": "hrn"})
    text += _toml_table("models.a.train", {"steps": 150, "checkpoint-every": 2, **TINY_MODEL})
    text += _toml_table("models.b", {"dataset": "tiny", "preset": "ours", "aliases": ["b_alias"]})
    text += _toml_table("models.b.train", {"steps": b_steps, "seq-end": 2, "checkpoint-every": 2, **TINY_MODEL})
    path.write_text(text)
    return path


def _args(tmp: Path, *extra: str) -> list[str]:
    return ["--recipe", str(tmp / "recipes.toml"), "--data-dir", str(tmp / "data"),
            "--runs-dir", str(tmp / "runs"), "--checkpoints-dir", str(tmp / "ckpt"), *extra]


def _record(run: Path) -> dict:
    return json.loads((run / RUN_RECORD).read_text())


def _mtimes(folder: Path, pattern: str) -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in sorted(folder.glob(pattern))}


# --------------------------------------------------------------------------------------------
# the recipe file


def test_option_flags():
    assert option_flags({"batch-size": 4, "train_dropout": 0.1, "ema": True, "amp": False,
                         "dropout-modules": "force,collision"}) == [
        "--batch-size", "4", "--train-dropout", "0.1", "--ema", "--dropout-modules", "force,collision"]


def test_shipped_recipe_matches_the_checkpoints_and_the_scenes():
    from hrn_pyg.data.scene_file import builtin_scene, read_scene_file

    recipe = load_recipe(REPO / "data" / "recipes.toml")
    shipped = {p.stem for p in CHECKPOINT_DIR.glob("*.pt")}
    made = {n for m in recipe.models for n in (m.name, *m.aliases)}
    assert made <= shipped
    assert shipped - made == {"cube_push_policy"}  # the RL policy comes from `hrn-pyg rl`
    longer = set()
    for dataset in recipe.datasets:  # the long episodes of the scene defaults, or longer runs of them
        spec = read_scene_file(REPO / dataset.scene) if dataset.from_file else builtin_scene(dataset.scene)
        assert dataset.steps >= spec.config.steps >= 140, dataset.name
        if dataset.steps > spec.config.steps:
            longer.add(dataset.name)
    assert longer == {"shapes_cloth_rest"}, longer  # runs on past the scene's own end, to rest
    wedge = next(m for m in recipe.models if m.name == "wedge")
    args = wedge.train_args(Path("data"), Path("runs/recipe"))
    assert args == [
        "train", "--preset", "ours", "--data", "data/wedge", "--out", "runs/recipe/wedge", "--train-steps", "3000",
        "--batch-size", "8", "--threads", "1", "--seq-end", "8", "--model-rigid-fit", "true",
        "--model-ground-contact", "true", "--model-mirror-average", "true", "--train-dropout", "0.1",
        "--dropout-modules", "force,collision", "--checkpoint-every", "100", "--eval-every", "500", "--seed", "1"]
    ridge = recipe.dataset("wedge_ridge")
    assert ridge.scene == "wedge" and dict(ridge.overrides)["offset_range"] == (-0.003, 0.003)
    # the shipped file is what those commands made (the first training, then each stage from the
    # one before); a run made by hand and adopted records its own run folder
    manifest = json.loads((CHECKPOINT_DIR / "manifest.json").read_text())["checkpoints"]["wedge"]

    def without_out(words: list[str]) -> list[str]:
        at = words.index("--out")
        return words[:at] + words[at + 2:]

    assert without_out(manifest["stage_commands"][0].split()[1:len(args) + 1]) == without_out(args)
    assert len(manifest["stage_commands"]) == wedge.num_stages
    tower = next(m for m in recipe.models if m.name == "tower")
    assert tower.extra_datasets() == ("tower_rest",)
    rest = recipe.dataset("tower_rest")
    assert dict(rest.overrides)["force_range"] == (0.0, 0.0) and rest.seed_offset >= recipe.dataset("tower").episodes


@pytest.mark.parametrize("change, word", [
    (lambda r: r["datasets"]["d"].update(color="red"), "unknown key"),
    (lambda r: r["datasets"]["d"].pop("steps"), "steps"),
    (lambda r: r["datasets"]["d"].update(episodes=0), "episodes"),
    (lambda r: r["models"]["m"].update(dataset="nope"), "nope"),
    (lambda r: r["models"]["m"]["train"].update(out="x"), "set by"),
    (lambda r: r["models"]["m"]["train"].update(steps=[1, 2]), "string, number or boolean"),
    (lambda r: r["models"]["m"].update(aliases=["m"]), "more than once"),
    (lambda r: r["models"].update({"bad name": {}}), "name"),
])
def test_bad_recipes_are_refused(change, word):
    recipe = {"datasets": {"d": {"scene": "wedge", "episodes": 2, "steps": 3}},
              "models": {"m": {"dataset": "d", "preset": "ours", "train": {"steps": 2}}}}
    parse_recipe(recipe)
    change(recipe)
    with pytest.raises(ValueError, match=word):
        parse_recipe(recipe)


def test_cli_errors_are_one_line(tmp_path, capsys):
    _write_recipe(tmp_path / "recipes.toml")
    assert recipe_main(_args(tmp_path, "--only", "zzz")) == 2
    assert recipe_main(_args(tmp_path, "--skip-generate")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "zzz" in err[0] and "missing" in err[1]
    assert not (tmp_path / "runs").exists() and not (tmp_path / "ckpt").exists()


def test_dry_run_prints_the_commands_and_writes_nothing(tmp_path):
    recipe = load_recipe(_write_recipe(tmp_path / "recipes.toml"))
    lines: list[str] = []
    # "meta", a device the default never is: a runner that ignored it (or put the default in its
    # place) would print another --device, or none
    config = RunConfig(data_dir=tmp_path / "data", runs_dir=tmp_path / "runs", checkpoints_dir=tmp_path / "ckpt",
                       device="meta", dry_run=True, threads=3)
    assert Runner(recipe, config, say=lines.append).run() == []
    assert lines[0].startswith("hrn-pyg generate --scene cube_collision --episodes 3 --out ")
    trains = [line for line in lines if line.startswith("hrn-pyg train")]
    assert len(trains) == 2 and all(t.endswith("--device meta --threads 3") for t in trains)
    assert all(t.count("--threads 1") == 1 for t in trains)  # the recipe's, overridden by the last one
    assert all(t.count("--device") == 1 for t in trains)
    assert "--model-hidden 8" in trains[0] and "--resume" not in trains[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["recipes.toml"]


# --------------------------------------------------------------------------------------------
# a killed run continues


def _kill_once_training(tmp: Path, run: Path) -> None:
    """Start the recipe in a child process group; SIGKILL the group once ``run`` has a checkpoint."""
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-m", "experiments.recipe", *_args(tmp, "--jobs", "1")], cwd=tmp,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True, env=env)
    try:
        deadline = time.time() + 300  # generous: a loaded machine starts torch slowly
        while time.time() < deadline and proc.poll() is None and not (run / "last.pt").exists():
            time.sleep(0.02)
    finally:
        with_group = proc.poll() is None
        if with_group:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert with_group, "the recipe ended before it could be killed"


def test_killed_run_continues_and_finished_work_is_not_redone(tmp_path):
    from hrn_pyg.utils.device import default_device

    _write_recipe(tmp_path / "recipes.toml")
    data, runs, ckpt = tmp_path / "data" / "tiny", tmp_path / "runs", tmp_path / "ckpt"
    # a generation killed after its first episode: the recipe must only add the other two
    assert main(["generate", "--scene", "cube_collision", "--episodes", "1", "--out", str(data), "--episode-steps", "12",
                 "--no-progress"]) == 0
    first = _mtimes(data, "episode_*.npz")

    _kill_once_training(tmp_path, runs / "a")
    assert sorted(_mtimes(data, "episode_*.npz")) == [f"episode_{s:06d}.npz" for s in range(3)]
    assert _mtimes(data, "episode_000000.npz") == first
    assert (runs / "a" / "last.pt").exists() and not (runs / "a" / "model.pt").exists()
    assert [i["rc"] for i in _record(runs / "a")["invocations"]] == [None]  # killed mid-run
    episodes = _mtimes(data, "episode_*.npz")

    assert recipe_main(_args(tmp_path, "--jobs", "2")) == 0
    assert _mtimes(data, "episode_*.npz") == episodes
    calls = _record(runs / "a")["invocations"]
    assert len(calls) == 2 and calls[1]["command"].endswith("--resume") and calls[1]["rc"] == 0
    with open(runs / "a" / "metrics.csv") as fh:
        assert [int(r["step"]) for r in csv.DictReader(fh)] == list(range(150))  # one history
    for name, source in (("a", "a"), ("b", "b"), ("b_alias", "b")):
        assert (ckpt / f"{name}.pt").read_bytes() == (runs / source / "model.pt").read_bytes()
    manifest = json.loads((ckpt / MANIFEST_NAME).read_text())["checkpoints"]
    assert sorted(manifest) == ["a", "b"]
    a, b = manifest["a"], manifest["b"]
    assert a["steps"] == 150 and b["steps"] == 4 and b["aliases"] == ["b_alias"]
    assert a["train_command"].startswith(f"hrn-pyg train --preset hrn --data {tmp_path / 'data' / 'tiny'} ")
    assert a["dataset"] == {"name": "tiny", "scene": "cube_collision", "episodes": 3, "steps": 12,
                            "seed_offset": 0, "pitch": None}
    assert a["device"] == b["device"] == str(default_device())
    assert b["wall_seconds"] > 0 and b["train_invocations"] == 1
    assert 0 < b["logged_train_seconds"] <= b["wall_seconds"]  # inside train, without its start-up

    # a third run has nothing to do, with other threads too (like the device, not part of a run's identity)
    before = {"models": _mtimes(runs, "*/model.pt"), "ckpt": _mtimes(ckpt, "*"),
              "calls": {n: len(_record(runs / n)["invocations"]) for n in ("a", "b")}}
    assert recipe_main(_args(tmp_path, "--threads", "2")) == 0
    assert before == {"models": _mtimes(runs, "*/model.pt"), "ckpt": _mtimes(ckpt, "*"),
                      "calls": {n: len(_record(runs / n)["invocations"]) for n in ("a", "b")}}

    # changed options retrain that model only; the old run folder is kept aside
    _write_recipe(tmp_path / "recipes.toml", b_steps=5)
    assert recipe_main(_args(tmp_path, "--only", "b")) == 0
    assert len(list(runs.glob("b.replaced-*"))) == 1
    manifest = json.loads((ckpt / MANIFEST_NAME).read_text())["checkpoints"]
    assert manifest["b"]["steps"] == 5 and manifest["a"] == a
    assert (ckpt / "b_alias.pt").read_bytes() == (runs / "b" / "model.pt").read_bytes()


def test_time_limit_pauses_a_training_and_the_same_command_continues_it(tmp_path, capsys):
    _write_recipe(tmp_path / "recipes.toml")
    runs, ckpt = tmp_path / "runs", tmp_path / "ckpt"
    # a limit far below one step's time: each model stops after its first step, unpublished
    assert recipe_main(_args(tmp_path, "--only", "a", "--time-limit", "0.0001")) == 0
    out = capsys.readouterr().out
    assert "paused at the time limit: a" in out and "up to date" not in out
    assert (runs / "a" / "last.pt").exists() and not (runs / "a" / "model.pt").exists()
    assert not (ckpt / "a.pt").exists()
    first = _record(runs / "a")
    assert first["invocations"][0]["command"].endswith("--time-limit 0.0001") and first["invocations"][0]["rc"] == 0

    # the limit is a property of the sitting, not of the training: no retraining from scratch
    assert recipe_main(_args(tmp_path, "--only", "a")) == 0
    calls = _record(runs / "a")["invocations"]
    assert calls[0] == first["invocations"][0] and calls[1]["command"].endswith("--resume")
    assert not list(runs.glob("a.replaced-*"))
    with open(runs / "a" / "metrics.csv") as fh:
        assert [int(r["step"]) for r in csv.DictReader(fh)] == list(range(150))
    assert (ckpt / "a.pt").read_bytes() == (runs / "a" / "model.pt").read_bytes()


def test_the_ablation_recipe_parses_and_varies_one_factor_at_a_time():
    recipe = load_recipe(REPO / "data" / "ablation.toml")
    options = {m.name: dict(m.options) for m in recipe.select(())}
    # the cube_push pair: the symmetry augmentation is the one change on top of its base
    push_base, push_symmetry = options.pop("abl_push_base"), options.pop("abl_push_symmetry")
    assert {k: v for k, v in push_symmetry.items() if push_base.get(k) != v} == {"augment-symmetry": "true"}
    assert push_base.keys() <= push_symmetry.keys()
    base = options.pop("abl_paper")
    combined = options.pop("abl_all")
    for name, opts in options.items():
        extra = {k: v for k, v in opts.items() if base.get(k) != v}
        assert len(extra) == 1, (name, extra)  # exactly one factor on top of the paper's model
        assert combined.items() >= extra.items()


def test_a_calibrate_table_ships_the_calibrated_copy_and_is_not_redone(tmp_path):
    """``[models.b.calibrate]``: the published file is model.pt calibrated on a validation seed
    (rate and modules in its config and in the manifest); a rerun does not calibrate again."""
    from hrn_pyg.checkpoints import load_model
    from hrn_pyg.sampling.calibrate import calibration_record

    text = _toml_table("datasets.tiny", {"scene": "cube_collision", "episodes": 3, "steps": 12, "seed_offset": 0})
    text += _toml_table("models.b", {"dataset": "tiny", "preset": "ours"})
    text += _toml_table("models.b.train", {"steps": 2, "checkpoint-every": 2, **TINY_MODEL})
    text += _toml_table("models.b.calibrate", {"seeds": "8", "rates": "0.05,0.2", "modules": ["force", "collision"],
                                               "k": 2, "members": 2, "steps": 2})
    (tmp_path / "recipes.toml").write_text(text)
    recipe = load_recipe(tmp_path / "recipes.toml")
    assert option_flags(dict(recipe.models[0].calibrate), CALIBRATE_FLAGS) == [
        "--episode-seeds", "8", "--rates", "0.05,0.2", "--module-sets", "force", "collision", "--k", "2",
        "--members", "2", "--horizon", "2"]
    assert recipe_main(_args(tmp_path, "--device", "cpu")) == 0
    runs, ckpt = tmp_path / "runs", tmp_path / "ckpt"
    shipped = ckpt / "b.pt"
    assert shipped.read_bytes() == (runs / "b" / "model.calibrated.pt").read_bytes()
    record = calibration_record(shipped)
    assert record is not None and record["rate"] in (0.05, 0.2) and record["seeds"] == [8]
    model = load_model(shipped)
    assert model.config.dropout_rate == record["rate"] and list(model.config.dropout_modules) == record["modules"]
    entry = json.loads((ckpt / MANIFEST_NAME).read_text())["checkpoints"]["b"]
    assert entry["calibrated"]["rate"] == record["rate"] and entry["calibrate_command"].startswith(
        f"hrn-pyg calibrate --scene cube_collision --model {runs / 'b' / 'model.pt'} ")
    before = _mtimes(runs / "b", "model*.pt")
    assert recipe_main(_args(tmp_path, "--device", "cpu")) == 0
    assert _mtimes(runs / "b", "model*.pt") == before


def test_bad_calibrate_tables_are_refused():
    base = {"datasets": {"d": {"scene": "wedge", "episodes": 2, "steps": 3}},
            "models": {"m": {"dataset": "d", "preset": "ours"}}}
    for table, word in (({"out": "x"}, "set by"), ({"k": True}, "string, a number or a list"),
                        ({"modules": [1]}, "string, a number or a list"), ("x", "table")):
        recipe = json.loads(json.dumps(base))
        recipe["models"]["m"]["calibrate"] = table
        with pytest.raises(ValueError, match=word):
            parse_recipe(recipe)


def test_a_dataset_can_set_scene_fields_and_old_records_are_unchanged():
    recipe = parse_recipe({"datasets": {"ridge": {"scene": "wedge", "episodes": 2, "steps": 3,
                                                  "set": {"offset_range": [-0.003, 0.003]}},
                                        "plain": {"scene": "wedge", "episodes": 2, "steps": 3}},
                           "models": {"m": {"dataset": "ridge", "preset": "ours"}}})
    ridge, plain = recipe.dataset("ridge"), recipe.dataset("plain")
    assert ridge.generate_args(Path("data"))[-2:] == ["--set", "offset_range=[-0.003, 0.003]"]
    assert ridge.to_dict()["set"] == {"offset_range": [-0.003, 0.003]}
    assert "set" not in plain.to_dict()  # records of datasets without overrides keep their old form
    with pytest.raises(ValueError, match="'set' must be a table"):
        parse_recipe({"datasets": {"d": {"scene": "wedge", "episodes": 2, "steps": 3, "set": {"x": "a"}}},
                      "models": {"m": {"dataset": "d", "preset": "ours"}}})


def test_finetune_stages_start_from_the_stage_before_and_ship_the_last(tmp_path):
    text = _toml_table("datasets.tiny", {"scene": "cube_collision", "episodes": 3, "steps": 12, "seed_offset": 0})
    text += _toml_table("models.b", {"dataset": "tiny", "preset": "ours"})
    text += _toml_table("models.b.train", {"steps": 2, "checkpoint-every": 2, **TINY_MODEL})
    text += "[[models.b.finetune]]\n" + "\n".join(_toml_table("x", {"steps": 3, "seq-start": 3, "seq-end": 3,
                                                                     "lr": 1e-4, "threads": 1}).splitlines()[1:]) + "\n"
    (tmp_path / "recipes.toml").write_text(text)
    recipe = load_recipe(tmp_path / "recipes.toml")
    model = recipe.models[0]
    assert model.num_stages == 2 and model.final_run == "b.ft1"
    runs, ckpt = tmp_path / "runs", tmp_path / "ckpt"
    assert model.train_args(Path("d"), runs, 1)[-12:] == [
        "--init-from", str(runs / "b" / "model.pt"), "--train-steps", "3", "--seq-start", "3", "--seq-end", "3",
        "--lr", "0.0001", "--threads", "1"]
    assert recipe_main(_args(tmp_path, "--device", "cpu")) == 0
    assert (ckpt / "b.pt").read_bytes() == (runs / "b.ft1" / "model.pt").read_bytes()
    tuned = json.loads((runs / "b.ft1" / "config.json").read_text())["train"]
    assert tuned["init_from"] == str(runs / "b" / "model.pt") and tuned["seq_end"] == 3
    entry = json.loads((ckpt / MANIFEST_NAME).read_text())["checkpoints"]["b"]
    assert entry["stage_steps"] == [2, 3] and entry["train_invocations"] == 2
    assert entry["stage_commands"][1] == entry["train_command"] and "--init-from" in entry["train_command"]
    # nothing to redo; a changed first stage redoes both (the fine-tune's start changed)
    before = _mtimes(runs, "*/model.pt")
    assert recipe_main(_args(tmp_path, "--device", "cpu")) == 0
    assert _mtimes(runs, "*/model.pt") == before
    (tmp_path / "recipes.toml").write_text(text.replace("steps = 2\n", "steps = 4\n", 1))
    assert recipe_main(_args(tmp_path, "--device", "cpu")) == 0
    assert len(list(runs.glob("b.replaced-*"))) == 1 and len(list(runs.glob("b.ft1.replaced-*"))) == 1


def test_bad_finetune_tables_are_refused():
    base = {"datasets": {"d": {"scene": "wedge", "episodes": 2, "steps": 3}},
            "models": {"m": {"dataset": "d", "preset": "ours"}}}
    for stages, word in (({"steps": 2}, "list of tables"), ([], "list of tables"),
                         ([{"init-from": "x.pt"}], "set by"), ([{"steps": [1]}], "string, number or boolean")):
        recipe = json.loads(json.dumps(base))
        recipe["models"]["m"]["finetune"] = stages
        with pytest.raises(ValueError, match=word):
            parse_recipe(recipe)


def test_a_stage_can_mix_in_another_dataset_and_its_recipe_is_part_of_the_identity():
    """``extra-datasets`` in a stage: its folders go to ``--extra-data``, the runner generates
    them, the stage's identity records their recipes (so changing one redoes the stage), and
    models without the option keep the identity they had."""
    base = {"datasets": {"d": {"scene": "tower", "episodes": 2, "steps": 3},
                         "rest": {"scene": "tower", "episodes": 2, "steps": 3, "seed_offset": 100,
                                  "set": {"force_range": [0.0, 0.0]}}},
            "models": {"m": {"dataset": "d", "preset": "ours", "train": {"steps": 2},
                             "finetune": [{"steps": 3, "extra_datasets": "rest"}]},
                       "plain": {"dataset": "d", "preset": "ours"}}}
    recipe = parse_recipe(base)
    model, plain = recipe.models
    assert model.extra_datasets() == ("rest",) and model.extra_datasets(0) == ()
    args = model.train_args(Path("data"), Path("runs"), 1)
    assert args[args.index("--extra-data") + 1] == str(Path("data") / "rest") and "--extra-datasets" not in args
    assert "--extra-data" not in model.train_args(Path("data"), Path("runs"), 0)
    assert "extra_datasets" not in recipe.identity(model, 0) and "extra_datasets" not in recipe.identity(plain)
    assert recipe.identity(model, 1)["extra_datasets"] == {"rest": recipe.dataset("rest").to_dict()}
    changed = json.loads(json.dumps(base))
    changed["datasets"]["rest"]["episodes"] = 3
    assert parse_recipe(changed).identity(parse_recipe(changed).models[0], 1) != recipe.identity(model, 1)
    runner = Runner(recipe, RunConfig(dry_run=True))
    assert [d.name for d in runner.datasets()] == ["d", "rest"]
    for value, word in (("nope", r"\['nope'\] not in \[datasets\]"), ("d", "repeats the model's own"),
                        ("a b", "dataset names, comma-separated")):
        bad = json.loads(json.dumps(base))
        bad["models"]["m"]["finetune"][0]["extra_datasets"] = value
        with pytest.raises(ValueError, match=word):
            parse_recipe(bad)


def test_a_dataset_from_a_scene_file_generates_with_it_and_changes_with_its_text(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "drop.toml").write_text('steps = 4\n[[objects]]\nmesh = "box"\nmaterial = "rigid"\nsize = 0.2\n'
                                        'position = [0.0, 0.0, 0.3]\n')
    recipe = parse_recipe({"datasets": {"drop": {"scene": "drop.toml", "episodes": 2, "steps": 4}},
                           "models": {"drop": {"dataset": "drop", "preset": "ours"}}})
    dataset = recipe.dataset("drop")
    assert dataset.generate_args(Path("data"))[:3] == ["generate", "--scene-file", "drop.toml"]
    before = dataset.to_dict()["scene_sha256"]
    (tmp_path / "drop.toml").write_text((tmp_path / "drop.toml").read_text().replace("0.3]", "0.4]"))
    assert dataset.to_dict()["scene_sha256"] != before
    assert main(dataset.generate_args(tmp_path / "data") + ["--no-progress"]) == 0
    assert len(list((tmp_path / "data" / "drop").glob("episode_*.npz"))) == 2


@pytest.mark.parametrize("name, first", [
    ("shapes", ["shapes_drop", "shapes_drop_p025", "shapes_drop_p035", "shapes_drop_p080"]),
    ("shapes_d4", ["shapes_drop", "shapes_push", "soft_bounce_shapes", "cube_collision"]),
])
def test_the_generalist_recipe_reads_and_keeps_its_seeds_apart(name, first):
    from hrn_pyg.data.scene_file import builtin_scene, read_scene_file

    recipe = load_recipe(REPO / "data" / "recipes.toml")
    model = next(m for m in recipe.models if m.name == name)
    datasets = [recipe.dataset(n) for n in (model.dataset, *model.extra_datasets())]
    spans: dict[str, list[tuple[int, int]]] = {}
    for dataset in datasets:
        spec = read_scene_file(REPO / dataset.scene) if dataset.from_file else builtin_scene(dataset.scene)
        assert dataset.steps in (spec.config.steps, 2 * spec.config.steps)  # a rest dataset runs twice as long
        spans.setdefault(dataset.scene, []).append((dataset.seed_offset, dataset.seed_offset + dataset.episodes))
    for scene_spans in spans.values():  # the datasets of one scene train together on seeds of their own
        scene_spans.sort()
        assert all(a[1] <= b[0] for a, b in zip(scene_spans, scene_spans[1:]))
    assert {d.name for d in datasets} >= {"shapes_drop", "shapes_soft", "cube_collision"}
    # calibrated on the validation episodes of all its datasets, the folders naming the scenes
    args = model.calibrate_args(recipe.dataset(model.dataset).scene, Path("runs"),
                                [Path("data") / d.name for d in datasets])
    assert args[:9] == ["calibrate", *(w for n in first for w in ("--data", f"data/{n}"))]
    assert "--scene" not in args and args[args.index("--starts") + 1] == "2"


def test_no_training_scene_of_the_generalist_uses_a_validation_or_test_mesh():
    from hrn_pyg.data.scene_file import read_scene_file

    def meshes(scene: Path) -> set[str]:
        return {m for obj in read_scene_file(scene).objects for m in obj.meshes if m.endswith(".obj")}

    recipe = load_recipe(REPO / "data" / "generalist.toml")  # its datasets and the shipped recipe's
    trained = set().union(*(meshes(REPO / d.scene) for d in recipe.datasets if d.from_file))
    held_out = set().union(*(meshes(f) for f in (REPO / "data" / "shapes" / "unseen").glob("*.toml")))
    assert any("random_urdfs" in m for m in trained) and any("random_urdfs" in m for m in held_out)
    assert not trained & held_out


def test_a_model_can_start_from_a_shipped_checkpoint_and_its_bytes_are_its_identity(monkeypatch, tmp_path):
    import hrn_pyg.checkpoints as checkpoints

    base = {"datasets": {"d": {"scene": "tower", "episodes": 2, "steps": 3}},
            "models": {"m": {"dataset": "d", "preset": "ours", "start": "tower", "train": {"steps": 2},
                             "finetune": [{"steps": 3}]}}}
    recipe = parse_recipe(base)
    model = recipe.models[0]
    args = model.train_args(Path("data"), Path("runs"), 0)
    assert args[args.index("--init-from") + 1] == "tower"
    assert model.train_args(Path("data"), Path("runs"), 1).count("--init-from") == 1  # the stage before
    start = recipe.identity(model, 1)["start"]
    assert start == {"name": "tower", "sha256": hashlib.sha256((CHECKPOINT_DIR / "tower.pt").read_bytes()).hexdigest()}
    # another file under the same name is another start
    (tmp_path / "tower.pt").write_bytes(b"other weights")
    monkeypatch.setattr(checkpoints, "CHECKPOINT_DIR", tmp_path)
    assert recipe.identity(model, 0)["start"]["sha256"] != start["sha256"]
    plain = parse_recipe({**base, "models": {"m": {"dataset": "d", "preset": "ours"}}})
    assert "start" not in plain.identity(plain.models[0])  # the records of other models stay as they were
    for value in ("../x.pt", 3, "a b"):
        bad = json.loads(json.dumps(base))
        bad["models"]["m"]["start"] = value
        with pytest.raises(ValueError, match="start must be a shipped checkpoint's name"):
            parse_recipe(bad)


def test_a_recipe_can_borrow_another_recipes_datasets(tmp_path):
    (tmp_path / "main.toml").write_text(_toml_table("datasets.d", {"scene": "tower", "episodes": 2, "steps": 3})
                                        + _toml_table("models.x", {"dataset": "d", "preset": "ours"}))
    text = 'datasets_from = "main.toml"\n' + _toml_table("datasets.e", {"scene": "wedge", "episodes": 2, "steps": 3})
    (tmp_path / "next.toml").write_text(text + _toml_table("models.y", {"dataset": "d", "preset": "ours"})
                                        + _toml_table("models.y.train", {"extra-datasets": "e"}))
    recipe = load_recipe(tmp_path / "next.toml")
    assert [d.name for d in recipe.datasets] == ["d", "e"] and [m.name for m in recipe.models] == ["y"]
    assert recipe.dataset("d") == load_recipe(tmp_path / "main.toml").dataset("d")
    (tmp_path / "twice.toml").write_text('datasets_from = "main.toml"\n'
                                         + _toml_table("datasets.d", {"scene": "wedge", "episodes": 2, "steps": 3})
                                         + _toml_table("models.y", {"dataset": "d", "preset": "ours"}))
    with pytest.raises(ValueError, match=r"defines dataset\(s\) \['d'\] that main.toml defines too"):
        load_recipe(tmp_path / "twice.toml")
    (tmp_path / "chain.toml").write_text('datasets_from = "next.toml"\n'
                                         + _toml_table("models.z", {"dataset": "d", "preset": "ours"}))
    with pytest.raises(ValueError, match="has datasets_from itself"):
        load_recipe(tmp_path / "chain.toml")
    (tmp_path / "gone.toml").write_text('datasets_from = "nope.toml"\n')
    with pytest.raises(FileNotFoundError, match="nope.toml does not exist"):
        load_recipe(tmp_path / "gone.toml")


def test_skip_generate_checks_each_stage_before_it_trains(tmp_path, capsys):
    """A stage trains while a later stage's dataset is still missing; that stage fails with one
    line naming the dataset, and the same command continues it once the episodes are there."""
    text = _toml_table("datasets.tiny", {"scene": "cube_collision", "episodes": 3, "steps": 12, "seed_offset": 0})
    text += _toml_table("datasets.more", {"scene": "cube_collision", "episodes": 2, "steps": 12, "seed_offset": 10})
    text += _toml_table("models.b", {"dataset": "tiny", "preset": "ours"})
    text += _toml_table("models.b.train", {"steps": 2, "checkpoint-every": 2, **TINY_MODEL})
    text += "[[models.b.finetune]]\n" + "\n".join(_toml_table("x", {"steps": 2, "threads": 1,
                                                                     "extra-datasets": "more"}).splitlines()[1:]) + "\n"
    (tmp_path / "recipes.toml").write_text(text)
    recipe = load_recipe(tmp_path / "recipes.toml")
    assert main(recipe.dataset("tiny").generate_args(tmp_path / "data") + ["--no-progress"]) == 0
    assert recipe_main(_args(tmp_path, "--device", "cpu", "--skip-generate")) == 1
    failed = [line for line in capsys.readouterr().out.splitlines() if line.startswith("FAILED")]
    assert len(failed) == 1 and "dataset 'more' missing" in failed[0] and "b.ft1" in failed[0]
    runs = tmp_path / "runs"
    assert (runs / "b" / "model.pt").is_file() and not (runs / "b.ft1").exists()
    assert main(recipe.dataset("more").generate_args(tmp_path / "data") + ["--no-progress"]) == 0
    lost = recipe.dataset("more").episode_files(tmp_path / "data")[1]  # a seed pybullet lost counts as made
    lost.unlink()
    lost.with_suffix(".rejected").write_text("pybullet lost it\n")
    before = _mtimes(runs, "b/model.pt")
    assert recipe_main(_args(tmp_path, "--device", "cpu", "--skip-generate")) == 0
    assert (tmp_path / "ckpt" / "b.pt").read_bytes() == (runs / "b.ft1" / "model.pt").read_bytes()
    assert _mtimes(runs, "b/model.pt") == before  # the first stage was not trained again


def test_the_next_generalists_recipe_starts_from_shapes_d4_on_the_shipped_datasets():
    shipped = load_recipe(REPO / "data" / "recipes.toml")
    recipe = load_recipe(REPO / "data" / "generalist.toml")
    model = recipe.models[0]
    assert model.start == "shapes_d4" and recipe.identity(model)["start"]["sha256"]
    for name in (model.dataset, *model.extra_datasets()):
        assert recipe.dataset(name) == shipped.dataset(name)  # the same seeds: nothing generated twice


def test_an_average_table_ships_the_mean_of_the_stages_and_is_not_redone(tmp_path):
    """``[models.b.average]``: the published file is the weighted mean of the two stages' weights
    (the last stage's normaliser and config); a rerun rewrites nothing, and changed weights
    rewrite the mean without training again."""
    import torch

    from hrn_pyg.checkpoints import load_model

    text = _toml_table("datasets.tiny", {"scene": "cube_collision", "episodes": 3, "steps": 12, "seed_offset": 0})
    text += _toml_table("models.b", {"dataset": "tiny", "preset": "ours"})
    text += _toml_table("models.b.train", {"steps": 2, "checkpoint-every": 2, **TINY_MODEL})
    text += "[[models.b.finetune]]\n" + "\n".join(_toml_table("x", {"steps": 2, "lr": 0.01, "threads": 1})
                                                  .splitlines()[1:]) + "\n"
    (tmp_path / "recipes.toml").write_text(text + _toml_table("models.b.average", {"stages": [0, 1],
                                                                                   "weights": [0.25, 0.75]}))
    assert recipe_main(_args(tmp_path, "--device", "cpu")) == 0
    runs, ckpt = tmp_path / "runs", tmp_path / "ckpt"
    assert (ckpt / "b.pt").read_bytes() == (runs / "b.ft1" / "model.averaged.pt").read_bytes()
    first, last, shipped = (load_model(p) for p in (runs / "b" / "model.pt", runs / "b.ft1" / "model.pt", ckpt / "b.pt"))
    moved = 0
    for (name, a), (_, b), (_, mean) in zip(first.named_parameters(), last.named_parameters(),
                                            shipped.named_parameters(), strict=True):
        torch.testing.assert_close(mean, 0.25 * a + 0.75 * b, rtol=0, atol=1e-7)
        moved += int(not torch.equal(a, b))
    assert moved > 0  # the fine-tuning changed weights: the mean is neither stage
    entry = json.loads((ckpt / MANIFEST_NAME).read_text())["checkpoints"]["b"]
    assert entry["averaged"] == {"stages": [0, 1], "weights": [0.25, 0.75]}
    before = _mtimes(runs / "b.ft1", "model*.pt")
    assert recipe_main(_args(tmp_path, "--device", "cpu")) == 0
    assert _mtimes(runs / "b.ft1", "model*.pt") == before
    (tmp_path / "recipes.toml").write_text(text + _toml_table("models.b.average", {"stages": [0, 1]}))
    assert recipe_main(_args(tmp_path, "--device", "cpu")) == 0
    after = _mtimes(runs / "b.ft1", "model*.pt")
    assert after["model.pt"] == before["model.pt"] and after["model.averaged.pt"] != before["model.averaged.pt"]
    for (_, a), (_, b), (_, mean) in zip(first.named_parameters(), last.named_parameters(),
                                         load_model(ckpt / "b.pt").named_parameters(), strict=True):
        torch.testing.assert_close(mean, 0.5 * a + 0.5 * b, rtol=0, atol=1e-7)


def test_an_apply_table_sets_applied_options_on_the_shipped_model_and_is_not_redone(tmp_path):
    """``[models.b.apply]``: the published model is the trained one (here the mean of its stages)
    with the options set and nothing else changed; a rerun rewrites nothing, changed options
    rewrite only the applied copy."""
    import torch

    from hrn_pyg.checkpoints import load_model

    text = _toml_table("datasets.tiny", {"scene": "cube_collision", "episodes": 3, "steps": 12, "seed_offset": 0})
    text += _toml_table("models.b", {"dataset": "tiny", "preset": "ours"})
    text += _toml_table("models.b.train", {"steps": 2, "checkpoint-every": 2, **TINY_MODEL})
    text += "[[models.b.finetune]]\n" + "\n".join(_toml_table("x", {"steps": 2, "lr": 0.01, "threads": 1})
                                                  .splitlines()[1:]) + "\n"
    text += _toml_table("models.b.average", {"stages": [0, 1]})
    (tmp_path / "recipes.toml").write_text(text + _toml_table("models.b.apply", {"ground-projection": True,
                                                                                 "cloth_clearance": 0.2}))
    assert recipe_main(_args(tmp_path, "--device", "cpu")) == 0
    run, ckpt = tmp_path / "runs" / "b.ft1", tmp_path / "ckpt"
    assert (ckpt / "b.pt").read_bytes() == (run / "model.applied.pt").read_bytes()
    trained, shipped = load_model(run / "model.averaged.pt"), load_model(ckpt / "b.pt")
    assert not trained.config.ground_projection and trained.config.cloth_clearance == 0.0
    assert shipped.config.ground_projection and shipped.config.cloth_clearance == 0.2
    changed = {k for k, v in trained.config.to_dict().items() if shipped.config.to_dict()[k] != v}
    assert changed == {"ground_projection", "cloth_clearance"}
    for (name, a), (_, b) in zip(trained.state_dict().items(), shipped.state_dict().items(), strict=True):
        assert torch.equal(a, b), name
    entry = json.loads((ckpt / MANIFEST_NAME).read_text())["checkpoints"]["b"]
    assert entry["applied"] == {"ground_projection": True, "cloth_clearance": 0.2}
    before = _mtimes(run, "model*.pt")
    assert recipe_main(_args(tmp_path, "--device", "cpu")) == 0
    assert _mtimes(run, "model*.pt") == before
    (tmp_path / "recipes.toml").write_text(text + _toml_table("models.b.apply", {"ground-projection": True}))
    assert recipe_main(_args(tmp_path, "--device", "cpu")) == 0
    after = _mtimes(run, "model*.pt")
    assert after["model.averaged.pt"] == before["model.averaged.pt"] and after["model.applied.pt"] != before["model.applied.pt"]
    assert load_model(ckpt / "b.pt").config.cloth_clearance == 0.0


def test_bad_apply_tables_are_refused():
    base = {"datasets": {"d": {"scene": "wedge", "episodes": 2, "steps": 3}},
            "models": {"m": {"dataset": "d", "preset": "ours"}}}
    for table, word in (({"hidden": 64}, "not an applied option"), ({"ground-projection": "yes"}, "boolean or a number"),
                        ({}, "one or more applied options"), ("x", "one or more applied options")):
        recipe = json.loads(json.dumps(base))
        recipe["models"]["m"]["apply"] = table
        with pytest.raises(ValueError, match=word):
            parse_recipe(recipe)
    recipe = json.loads(json.dumps(base))
    recipe["models"]["m"]["apply"] = {"ground-projection-rigid": False}
    model = parse_recipe(recipe).models[0]
    assert model.apply == (("ground_projection_rigid", False),) and model.model_file == "model.applied.pt"


def test_bad_average_tables_are_refused():
    base = {"datasets": {"d": {"scene": "wedge", "episodes": 2, "steps": 3}},
            "models": {"m": {"dataset": "d", "preset": "ours", "finetune": [{"steps": 2}, {"steps": 2}]}}}
    for table, word in (({"stages": [0, 1]}, "ending with the last stage"), ({"stages": [2]}, "two or more"),
                        ({"stages": [2, 0]}, "rising"), ({"stages": [0, 2], "weights": [0.5, 0.6]}, "sum to 1"),
                        ({"stages": [0, 2], "weights": [1.0]}, "1 weights for 2"),
                        ({"stages": [0, 2], "weights": "even"}, "list of numbers"),
                        ({"stages": [0, 2], "mix": 1}, "unknown key"), ({"stages": "0,2"}, "wrong type"),
                        ("x", "must be a table"), ({"stages": [True, 2]}, "rising stage numbers")):
        recipe = json.loads(json.dumps(base))
        recipe["models"]["m"]["average"] = table
        with pytest.raises(ValueError, match=word):
            parse_recipe(recipe)
    recipe = json.loads(json.dumps(base))
    recipe["models"]["m"]["average"] = {"stages": [0, 2]}
    assert parse_recipe(recipe).models[0].average == ((0, 0.5), (2, 0.5))


def test_logged_training_time_sums_the_sittings_a_kill_left_unrecorded(tmp_path):
    """Each sitting of ``metrics.csv`` counts its seconds from its own start: a drop starts the
    next one, and each sitting adds its last value (a killed one's last logged row)."""
    metrics = tmp_path / "metrics.csv"
    rows = [(0, 1.0), (1, 2.0), (2, 3.5), (2, 0.4), (3, 1.5), (4, 2.0)]  # killed after step 2, resumed there
    with open(metrics, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["step", "loss", "seconds"])
        writer.writerows([(step, 0.1, seconds) for step, seconds in rows])
    assert logged_train_seconds(metrics) == pytest.approx(3.5 + 2.0)
    assert logged_train_seconds(tmp_path / "missing.csv") is None
    metrics.write_text("step,loss\n0,0.1\n")
    assert logged_train_seconds(metrics) is None


def test_the_manifest_keeps_a_domain_while_the_file_is_the_same(tmp_path):
    path = tmp_path / "manifest.json"
    update_manifest(path, "m", {"sha256": "a", "domain": {"pitches": [0.05]}})
    update_manifest(path, "m", {"sha256": "a", "steps": 2})
    assert read_json(path)["checkpoints"]["m"]["domain"] == {"pitches": [0.05]}
    update_manifest(path, "m", {"sha256": "b", "steps": 2})  # another file: its domain is unknown
    assert "domain" not in read_json(path)["checkpoints"]["m"]


def test_checkpoints_go_under_the_working_directory_by_default():
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    config = config_from_args(parser.parse_args([]))
    assert str(config.checkpoints_dir) == "checkpoints" == str(RunConfig().checkpoints_dir)
    assert not config.checkpoints_dir.is_absolute()
