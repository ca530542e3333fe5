"""``hrn-pyg calibrate``: the rate whose spread matches a validation ensemble, stored in the
checkpoint and used by default (tiny untrained model, 1-2 short starts: a pipeline check)."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from hrn_pyg.checkpoints import load_model
from hrn_pyg.cli import build_parser, main
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import HISTORY, NODE, STATIC
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.sampling import calibrate as cal
from hrn_pyg.sampling.ensemble import (
    PerturbationConfig,
    episode_state,
    ground_truth_ensemble,
)
from hrn_pyg.sampling.metrics import energy_score, root_spread
from hrn_pyg.sampling.sample import sample
from hrn_pyg.train import TrainConfig, model_payload
from hrn_pyg.utils.checkpoint import load_checkpoint, save_checkpoint

SCENE = "cube_collision"
SEEDS = (8, 18)
STEPS, K, MEMBERS = 3, 4, 4
RATES = (0.05, 0.3, 0.9)
#: the ensemble's start perturbation (m): a fifth of the default 2 mm, so that the tiny model's
#: spread matches it near the middle rate: 0.05 spreads too little, 0.9 too much (ratio > 1)
POSITION_STD = 0.0004
#: the rate that matches, not the highest offered
MIDDLE_RATE = 0.3


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    """An untrained model (force and collision masks allowed), normaliser fitted on seed 8."""
    torch.manual_seed(0)
    model = HRN(HRNConfig(hidden=16, effect_dim=16))
    episode = simulate_episode(SCENE, 8, steps=HISTORY + 8)
    fit_normalizer([episode_state(episode, HISTORY, 8)], model.normalizer)
    path = tmp_path_factory.mktemp("ckpt") / "tiny.pt"
    save_checkpoint(path, model_payload(model, TrainConfig(), 0))
    return path


def calibrate_argv(model: Path, *extra: str) -> list[str]:
    """A calibrate command line for the tiny untrained model, whose futures do not obey physics:
    ranked by spread alone (the physics check has tests of its own)."""
    return ["calibrate", "--scene", SCENE, "--model", str(model), "--k", str(K), "--members", str(MEMBERS),
            "--horizon", str(STEPS), "--no-progress", "--no-physics-check", *extra]


@pytest.fixture(scope="module")
def calibrated(checkpoint, tmp_path_factory) -> tuple[Path, str]:
    """One calibrate run with the default output; returns the written file and the input's hash
    before the run."""
    before = digest(checkpoint)
    code = main(calibrate_argv(checkpoint, "--episode-seeds", ",".join(map(str, SEEDS)),
                               "--rates", ",".join(map(str, RATES)), "--module-sets", "force,collision", "force",
                               "--position-std", str(POSITION_STD)))
    assert code == 0
    return checkpoint.with_name("tiny.calibrated.pt"), before


def parse(argv: list[str]):
    return build_parser(argv[0]).parse_args(argv)


def recomputed(checkpoint: Path, modules: tuple[str, ...]) -> dict[float, tuple[list[float], float]]:
    """Per rate: spread ratios per start and mean energy score, computed here from scratch."""
    model = load_model(checkpoint)
    out = {}
    starts = []
    for seed in SEEDS:
        episode = simulate_episode(SCENE, seed, steps=HISTORY + STEPS)
        members = ground_truth_ensemble(SCENE, seed, MEMBERS, HISTORY + STEPS,
                                        PerturbationConfig(position_std=POSITION_STD))
        graph = episode_state(episode, HISTORY, STEPS)
        moving = torch.as_tensor(episode["object_material"])[torch.as_tensor(episode["leaf_object"])] != STATIC
        starts.append((graph, torch.as_tensor(members[:, -1]).float(), moving))
    for rate in RATES:
        ratios, energies = [], []
        for graph, truth, moving in starts:
            futures = sample(model, graph, K, STEPS, rate, forces=graph[NODE].force_seq.transpose(0, 1),
                             generator=torch.Generator().manual_seed(0), modules=modules)[:, -1]
            ratios.append(float(root_spread(futures[:, moving]).mean() / root_spread(truth[:, moving]).mean()))
            energies.append(float(energy_score(futures[:, moving], truth[:, moving]).mean()))
        out[rate] = (ratios, float(np.mean(energies)))
    return out


def test_chosen_rate_has_the_ratio_closest_to_one(checkpoint, calibrated):
    """The ensemble's spread lies between what the lowest and the highest rate give: the chosen
    rate is the middle one, whose median spread ratio is closest to 1, not the highest offered."""
    path, _ = calibrated
    record = cal.calibration_record(path)
    numbers = recomputed(checkpoint, ("force", "collision"))
    medians = {rate: math.exp(float(np.median(np.log(r)))) for rate, (r, _) in numbers.items()}
    # the case is not one-sided: the lowest rate spreads too little, the highest too much
    assert medians[min(RATES)] < 1 < medians[max(RATES)], medians
    distance = {rate: abs(math.log(m)) for rate, m in medians.items()}
    best = min(distance, key=lambda rate: (distance[rate], numbers[rate][1]))
    assert best == MIDDLE_RATE and min(RATES) < MIDDLE_RATE < max(RATES)
    # clearly best: the neighbours are at least twice as far from a ratio of 1 (on the log scale)
    assert all(distance[rate] > 2 * distance[MIDDLE_RATE] for rate in RATES if rate != MIDDLE_RATE), distance
    # force and collision give the same numbers here (no collision in 3 steps): ties go to the first
    assert record["rate"] == MIDDLE_RATE and record["modules"] == ["force", "collision"]
    assert record["spread_ratio_median"] == pytest.approx(medians[MIDDLE_RATE], rel=1e-5)
    assert record["perturbation"]["position_std"] == POSITION_STD
    rows = [c for c in record["candidates"] if c["modules"] == ["force", "collision"]]
    assert [c["rate"] for c in rows] == list(RATES)
    for c in rows:
        ratios, energy = numbers[c["rate"]]
        assert c["spread_ratios"] == pytest.approx(ratios, rel=1e-5)
        assert c["spread_ratio_median"] == pytest.approx(math.exp(np.median(np.log(ratios))), rel=1e-5)
        assert c["energy_score_m"] == pytest.approx(energy, rel=1e-5)
    assert load_model(path).config.dropout_rate == MIDDLE_RATE


def test_written_checkpoint_loads_with_rate_and_record(checkpoint, calibrated):
    path, before = calibrated
    assert path == cal.default_output(checkpoint)
    model = load_model(path)
    record = cal.calibration_record(path)
    assert model.config.dropout_rate == record["rate"] > 0
    assert list(model.config.dropout_modules) == record["modules"]
    assert record["scene"] == SCENE and record["seeds"] == list(SEEDS)
    assert (record["k"], record["members"], record["steps"]) == (K, MEMBERS, STEPS)
    assert record["model_dropout_modules"] == ["force", "collision"]
    assert len(record["candidates"]) == 2 * len(RATES) and record["date"].startswith("20")
    config = json.loads(load_checkpoint(path)["config"])
    assert set(config) == {"model", "train", "calibration"}
    # the input is untouched and, like every old checkpoint, has no record and still loads
    assert digest(checkpoint) == before
    assert cal.calibration_record(checkpoint) is None
    assert load_model(checkpoint).config.dropout_rate == 0.0


def test_in_place_rewrites_only_the_input(checkpoint, tmp_path):
    target = tmp_path / "model.pt"
    target.write_bytes(checkpoint.read_bytes())
    assert main(calibrate_argv(target, "--episode-seeds", "8", "--rates", "0.3", "--module-sets", "force", "--in-place")) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.pt"]  # no temporary file, no copy
    model = load_model(target)
    assert (model.config.dropout_rate, model.config.dropout_modules) == (0.3, ("force",))
    assert cal.calibration_record(target)["seeds"] == [8]


def test_data_folder_gives_its_validation_episodes(checkpoint, tiny_episodes, tmp_path):
    out = tmp_path / "from_data.pt"
    assert main(calibrate_argv(checkpoint, "--data", str(tiny_episodes), "--rates", "0.3", "--module-sets", "force",
                               "--out", str(out))) == 0
    record = cal.calibration_record(out)
    assert record["seeds"] == [8] and record["data"] == [str(tiny_episodes)]  # seeds 0..9: only 8 validates


def test_scene_file_folders_name_their_scene(checkpoint, tiny_episodes, tmp_path, capsys):
    """A folder made from a scene file is calibrated on without ``--scene`` (its meta.json keeps
    the file's text); several folders give the starts of all of them."""
    from hrn_pyg.data.scene_file import BUILTIN_DIR

    scene_file = tmp_path / "two_cubes.toml"
    scene_file.write_text((BUILTIN_DIR / f"{SCENE}.toml").read_text())
    data = tmp_path / "two_cubes"
    assert main(["generate", "--scene-file", str(scene_file), "--episodes", "2", "--first-seed", "17",
                 "--episode-steps", str(HISTORY + STEPS), "--out", str(data), "--no-progress"]) == 0
    scene_file.unlink()  # the recorded text is what is simulated, not the file as it is now
    out = tmp_path / "files.pt"
    argv = ["calibrate", "--model", str(checkpoint), "--data", str(data), "--k", str(K), "--members",
            str(MEMBERS), "--horizon", str(STEPS), "--rates", "0.3", "--module-sets", "force", "--no-progress",
            "--no-physics-check", "--out", str(out)]
    assert main(argv) == 0
    record = cal.calibration_record(out)
    assert record["scene"] == ["two_cubes"] and record["seeds"] == [18] and record["data"] == [str(data)]
    assert main([*argv, "--data", str(tiny_episodes)]) == 2  # a folder without meta.json needs --scene
    assert "pass --scene" in capsys.readouterr().err
    assert main(["calibrate", "--data", str(data), "--no-progress"]) == 2
    assert "--scene is required" in capsys.readouterr().err


def test_a_scene_file_folder_keeps_the_settings_it_was_made_with(tmp_path):
    """A folder generated from a scene file at another pitch is simulated at that pitch again:
    the ensemble has the leaves of the folder's own episodes (it had the file's pitch before)."""
    from hrn_pyg.data.episodes import simulate_episode
    from hrn_pyg.data.io import load_episode
    from hrn_pyg.data.scene_file import BUILTIN_DIR

    scene_file = tmp_path / "two_cubes.toml"
    scene_file.write_text((BUILTIN_DIR / f"{SCENE}.toml").read_text())
    data = tmp_path / "two_cubes_fine"
    assert main(["generate", "--scene-file", str(scene_file), "--episodes", "1", "--first-seed", "8",
                 "--episode-steps", "4", "--pitch", "0.04", "--out", str(data), "--no-progress"]) == 0
    name, spec = cal.data_scene(data, None)
    assert (name, spec.config.pitch, spec.config.steps) == ("two_cubes", 0.04, 4)
    made = load_episode(data / "episode_000008.npz")
    again = simulate_episode(spec, 8)
    assert np.array_equal(made["positions"], again["positions"])


def _spy_on_scoring(monkeypatch) -> list[torch.device]:
    """The device of the model every calibration scores its candidates with."""
    devices, calibrate = [], cal.calibrate

    def spy(model, *args, **kwargs):
        devices.append(next(model.parameters()).device)
        return calibrate(model, *args, **kwargs)

    monkeypatch.setattr(cal, "calibrate", spy)
    return devices


def test_device_cpu_is_used_when_the_default_is_elsewhere(checkpoint, tmp_path, monkeypatch):
    """The default device is made ``meta``: a command that ignored ``--device cpu`` would score
    there (and fail)."""
    import hrn_pyg.utils.device

    monkeypatch.setattr(hrn_pyg.utils.device, "default_device", lambda: torch.device("meta"))
    devices = _spy_on_scoring(monkeypatch)
    out = tmp_path / "cpu.pt"
    assert main(calibrate_argv(checkpoint, "--episode-seeds", "8", "--rates", "0.3", "--module-sets", "force",
                               "--out", str(out), "--device", "cpu")) == 0
    assert devices == [torch.device("cpu")] and cal.calibration_record(out)["rate"] == 0.3


def test_device_meta_is_refused_before_anything_is_scored(checkpoint, tmp_path, monkeypatch, capsys):
    """``--device meta`` is no device the package runs on: one line, exit 2, nothing scored or
    written."""
    devices = _spy_on_scoring(monkeypatch)
    out = tmp_path / "meta.pt"
    assert main(calibrate_argv(checkpoint, "--episode-seeds", "8", "--rates", "0.3", "--module-sets", "force",
                               "--out", str(out), "--device", "meta")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "meta" in err[0]
    assert devices == [] and not out.exists()


def test_a_rate_whose_futures_break_physics_is_rejected(checkpoint, tmp_path, capsys):
    """The tiny untrained model's futures gain energy and sink into each other: with the physics
    check (the default) no candidate is chosen and nothing is written; the rows say why."""
    out = tmp_path / "rejected.pt"
    argv = [a for a in calibrate_argv(checkpoint, "--episode-seeds", "8", "--rates", "0.1,0.3", "--module-sets",
                                      "force", "--out", str(out)) if a != "--no-physics-check"]
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert "fail the physics report" in captured.err and not out.exists()
    assert "failing at every rate" in captured.err and "| implausible futures |" in captured.out


def test_the_starts_failing_at_every_rate_are_named():
    rows = [cal.summarise(0.1, ("force",), [0.5, 0.5], [0.1, 0.1], implausible=[0, 3]),
            cal.summarise(0.3, ("force",), [1.0, 1.0], [0.1, 0.1], implausible=[1, 2])]
    assert rows[1]["implausible_futures"] == 3 and rows[1]["implausible_per_start"] == [1, 2]
    assert cal.failing_everywhere(rows, ["a seed 8", "b seed 18"]) == ["b seed 18"]
    assert "| 3 |" in cal.markdown(rows)  # the table shows each candidate's failures


def test_choose_skips_candidates_with_implausible_futures():
    rows = [cal.summarise(0.1, ("force",), [0.5], [0.1], implausible=[0]),
            cal.summarise(0.3, ("force",), [1.0], [0.1], implausible=[2])]
    assert cal.choose(rows) == 0  # the better spread fails the report
    assert cal.choose(rows, physics=False) == 1
    with pytest.raises(ValueError, match="fail the physics report"):
        cal.choose(rows[1:])


def test_output_equal_to_input_needs_in_place(checkpoint):
    with pytest.raises(ValueError, match="is the input checkpoint; pass --in-place"):
        cal.run(parse(calibrate_argv(checkpoint, "--out", str(checkpoint))))


@pytest.mark.parametrize(("seeds", "message"), [
    ("9", r"--episode-seeds: 9 is a test seed \(seed % 10 == 9\); calibrate on validation seeds only"),
    ("8,19", r"--episode-seeds: 19 is a test seed"),
    ("3", r"--episode-seeds: 3 is a training seed"),
    ("8,x", r"--episode-seeds must be comma-separated integers, got '8,x'"),
])
def test_non_validation_seeds_are_refused(checkpoint, seeds, message):
    with pytest.raises(ValueError, match=message):
        cal.run(parse(calibrate_argv(checkpoint, "--episode-seeds", seeds)))


def test_test_seed_is_a_one_line_cli_error(checkpoint, capsys):
    assert main(calibrate_argv(checkpoint, "--episode-seeds", "29")) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("hrn-pyg calibrate: error: --episode-seeds: 29 is a test seed"), err


@pytest.mark.parametrize(("rates", "message"), [
    ("0.1,1.0", r"--rates: every rate must be in \[0, 1\), got 1.0"),
    ("-0.1", r"--rates: every rate must be in \[0, 1\), got -0.1"),
    ("nan", r"--rates: every rate must be in \[0, 1\), got nan"),
    ("0.1,abc", r"--rates: 'abc' is not a number"),
    (",", r"--rates must name at least one rate"),
])
def test_bad_rates_are_refused(checkpoint, rates, message, capsys):
    with pytest.raises(ValueError, match=message):
        cal.run(parse(calibrate_argv(checkpoint, "--rates", rates)))
    assert main(calibrate_argv(checkpoint, "--rates", rates)) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("hrn-pyg calibrate: error: --rates"), err


@pytest.mark.parametrize(("modules", "message"), [
    (["wings"], r"--module-sets: unknown module\(s\) wings; this model takes dropout on force, collision"),
    (["force", "force,state"], r"--module-sets: unknown module\(s\) state; this model takes dropout on"),
])
def test_unknown_modules_are_refused(checkpoint, modules, message, capsys):
    with pytest.raises(ValueError, match=message):
        cal.run(parse(calibrate_argv(checkpoint, "--episode-seeds", "8", "--module-sets", *modules)))
    assert main(calibrate_argv(checkpoint, "--episode-seeds", "8", "--module-sets", *modules)) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("hrn-pyg calibrate: error: --module-sets"), err


def test_choose_breaks_ties_by_energy_and_needs_a_spread():
    rows = [cal.summarise(0.1, ("force",), [0.5, 0.5], [2.0, 2.0]),  # |log 0.5| = log 2
            cal.summarise(0.2, ("force",), [2.0, 2.0], [1.0, 1.0]),  # |log 2|, lower energy score
            cal.summarise(0.3, ("force",), [4.0, 8.0], [0.5, 0.5])]
    assert cal.choose(rows) == 1
    # two starts: the median of the logs is their mean, a ratio of sqrt(0.9 * 3) = 1.64, nearer 1 than 0.5
    assert cal.choose([rows[0], cal.summarise(0.1, ("force",), [0.9, 3.0], [9.0, 9.0])]) == 1
    flat = cal.summarise(0.1, ("collision",), [0.0, 0.0], [1.0, 1.0])
    assert flat["log_ratio_median"] is None and flat["spread_ratio_median"] == 0.0
    with pytest.raises(ValueError, match="no candidate spreads the samples at all"):
        cal.choose([flat])


def test_default_output_names():
    assert cal.default_output(Path("a/wedge.pt")) == Path("a/wedge.calibrated.pt")
    assert cal.default_output(Path("a/wedge.calibrated.pt")) == Path("a/wedge.calibrated.pt")


def test_sample_uses_the_calibrated_rate_by_default(checkpoint, calibrated, tmp_path):
    path, _ = calibrated
    rate = cal.calibration_record(path)["rate"]
    runs = {"calibrated": (path, []), "explicit": (path, ["--rate", "0.07"]), "uncalibrated": (checkpoint, [])}
    meta = {}
    for name, (model, extra) in runs.items():
        out = tmp_path / name
        assert main(["sample", "--scene", SCENE, "--model", str(model), "--k", "2", "--horizon", "2",
                     "--episode-seed", "8", "--out", str(out), *extra]) == 0
        meta[name] = json.loads((out / "samples.json").read_text())
    assert (meta["calibrated"]["rate"], meta["calibrated"]["rate_source"]) == (rate, "calibrated")
    assert meta["calibrated"]["modules"] == ["force", "collision"]
    assert (meta["explicit"]["rate"], meta["explicit"]["rate_source"]) == (0.07, "--rate")
    assert (meta["uncalibrated"]["rate"], meta["uncalibrated"]["rate_source"]) == (0.3, "uncalibrated default")


def test_rl_uses_the_calibrated_rate_unless_given_one(monkeypatch, tmp_path):
    from hrn_pyg.rl import ppo
    from hrn_pyg.rl.hrn_dynamics import HRNDynamics
    from hrn_pyg.rl.tasks import get_task

    task, config = get_task("cube_push"), ppo.PPOConfig()
    assert ppo.mode_settings("stochastic", task, config)[0].start == task.dropout_rate
    assert ppo.mode_settings("stochastic", task, config, rate=0.04)[0].start == 0.04
    assert ppo.mode_settings("stochastic_annealed", task, config, rate=0.04)[0].start == 0.04
    assert ppo.mode_settings("deterministic", task, config, rate=0.04)[0].start == 0.0
    with pytest.raises(ValueError, match=r"dropout rate must be in \[0, 1\), got 1.5"):
        ppo.mode_settings("stochastic", task, config, rate=1.5)

    # a model calibrated on collision: cube_push's own modules (force) would be refused
    torch.manual_seed(0)
    model = HRN(HRNConfig(hidden=8, effect_dim=8, dropout_rate=0.07, dropout_modules=("collision",)))
    dynamics = HRNDynamics(model, task, pool_seeds=(10_000,))
    assert (dynamics.calibrated_rate, dynamics.dropout_modules) == (0.07, ("collision",))
    seen = []
    monkeypatch.setattr(ppo, "_train", lambda *args: seen.append(args[6].start) or {})
    ppo.train(task, "stochastic", 0, config, tmp_path, dynamics)
    ppo.train(task, "stochastic", 0, config, tmp_path, dynamics, dropout_rate=0.02)
    ppo.train(task, "stochastic", 0, config, tmp_path)  # point-mass dynamics: the task's rate
    assert seen == [0.07, 0.02, task.dropout_rate]


def test_an_ensemble_cache_is_read_back_and_a_bad_file_in_it_is_simulated_again(tmp_path, monkeypatch):
    pert = PerturbationConfig(position_std=POSITION_STD)
    first = cal.build_start(SCENE, 8, STEPS, 2, pert, cache=tmp_path)
    files = list(tmp_path.glob("*.npy"))
    assert len(files) == 1 and files[0].name.startswith(f"{SCENE}_8_")

    def no_simulation(*args, **kwargs):
        raise AssertionError("simulated although the cache holds the ensemble")

    monkeypatch.setattr(cal, "ground_truth_ensemble", no_simulation)
    again = cal.build_start(SCENE, 8, STEPS, 2, pert, cache=tmp_path)
    torch.testing.assert_close(again.truth, first.truth, rtol=0, atol=0)
    # another perturbation is another key: it is simulated (here: refused by the stand-in)
    with pytest.raises(AssertionError, match="simulated although"):
        cal.build_start(SCENE, 8, STEPS, 2, PerturbationConfig(position_std=0.001), cache=tmp_path)
    monkeypatch.undo()
    np.save(files[0], np.zeros((1, 2, 3), dtype=np.float32))  # a file of the wrong shape
    third = cal.build_start(SCENE, 8, STEPS, 2, pert, cache=tmp_path)
    torch.testing.assert_close(third.truth, first.truth, rtol=0, atol=0)
    assert np.load(files[0]).shape == (2, HISTORY + STEPS + 1, first.truth.shape[1], 3)
