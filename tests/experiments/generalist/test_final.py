"""The generalist's final table: the test folders it makes and scores, a rerun that scores nothing
twice, each bar judged from the benchmarks' JSON and the checkpoint, and one-line errors for bad
input."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from experiments.command import script_main
from experiments.generalist import final, validate
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.sampling.calibrate import write_calibrated
from hrn_pyg.train import TrainConfig, model_payload
from hrn_pyg.utils.checkpoint import save_checkpoint

REPO = Path(__file__).resolve().parents[3]


def _data(tmp_path, with_test_folders=True):
    data = tmp_path / "data"
    for name in ("shapes_drop", *(f for f, _ in validate.SPECIALISTS)):
        (data / name).mkdir(parents=True)
    if with_test_folders:
        for name in final.TEST_SETS[final.DEFAULT_TEST_SET][0]:
            (data / name).mkdir(parents=True)
            (data / name / "meta.json").write_text(json.dumps({"complete": True}))
    return data


def test_the_test_folders_are_those_their_scene_files_name():
    for folders, _ in final.TEST_SETS.values():
        for name, (scene, seed) in folders.items():
            header = (REPO / scene).read_text()
            assert (f"--scene-file {scene} --episodes {final.TEST_EPISODES} --out data/{name} "
                    f"--first-seed {seed}") in header


def test_the_test_split_is_scored_on_test_folders_and_test_splits():
    cmds = final.commands("m.pt", Path("d"), Path("o"), 6)
    test, baseline = cmds["test.json"], cmds["test_shapes.json"]
    assert [test[i + 1] for i, w in enumerate(test) if w == "--unseen"] == [
        str(Path("d") / n) for n in final.TEST_SETS[final.DEFAULT_TEST_SET][0]]
    assert test[test.index("--own-split") + 1] == "test" and baseline[baseline.index("--own-split") + 1] == "test"
    assert baseline[baseline.index("--model") + 1] == "shapes_d4" and "--no-rest" in baseline
    assert not any("cloth" in w for w in baseline)   # shapes_d4.pt never moved cloth
    assert not any("val" in w for name in ("test.json", "cloth.json") for w in cmds[name])
    for name, cmd in cmds.items():
        assert cmd[cmd.index("--out") + 1] == str(Path("o") / name)
        if name != "test_shapes.json":
            assert cmd[cmd.index("--model") + 1] == "m.pt"


def test_the_roof_check_is_scored_on_test_drops_of_the_roof_scene():
    roof = final.commands("m.pt", Path("d"), Path("o"), 6)["roof.json"]
    assert roof[1:3] == ["-m", "benchmarks.wedge_sides"]
    assert roof[roof.index("--scene-file") + 1] == str(REPO / "data/shapes/unseen/roof_drop.toml")
    assert roof[roof.index("--split") + 1] == "test" and roof[roof.index("--model") + 1] == "m.pt"
    assert roof[roof.index("--cache") + 1] == str(Path("d") / "final_roof_cache")
    assert "--rates" not in roof and "--data" not in roof   # the checkpoint's calibrated rate; the scene file


def _roof(*samples, coin=(0.136, 0.122)):
    """``wedge_sides.py``'s JSON, cut to what the bars read: ``samples`` are (rate, Brier vs the
    fine ensemble, split difference vs the coarse one), the first rate the calibrated one."""
    results = [{"model": "constant 1/2", "rate": None, "brier_fine": coin[0], "split_difference_coarse": coin[1],
                "energy_score_m": None},
               {"model": "deterministic", "rate": 0.0, "brier_fine": 0.061, "split_difference_coarse": 0.397,
                "energy_score_m": 1.318}]
    results += [{"model": "samples", "rate": rate, "brier_fine": brier, "split_difference_coarse": split,
                 "energy_score_m": 1.3, "share_below": 0.4} for rate, brier, split in samples]
    return {"rates": [rate for rate, _, _ in samples], "results": results}


def _met(lines):
    return [line.rsplit(" | ", 1)[1].strip(" |") for line in lines]


def test_roof_bar_is_met_when_the_samples_beat_a_coin_at_the_calibrated_rate():
    better = final.roof_bars(_roof((0.02, 0.050, 0.377), (0.5, 0.2, 0.175)))
    assert _met(better) == ["yes", "-"]
    assert "rate 0.02" in better[0] and "| 0.050 against 0.136 |" in better[0]
    assert "| 0.377 (constant 1/2: 0.122) |" in better[1]
    worse = final.roof_bars(_roof((0.02, 0.150, 0.377), (0.1, 0.024, 0.305)))   # only the first rate counts
    assert _met(worse) == ["no", "-"] and "| 0.150 against 0.136 |" in worse[0]
    assert final.roof_bars({}) == []


def _checkpoint(path, rate=None):
    """A tiny untrained model's checkpoint; with ``rate``, its copy as ``hrn-pyg calibrate`` writes it."""
    torch.manual_seed(0)
    save_checkpoint(path, model_payload(HRN(HRNConfig(hidden=8, effect_dim=8)), TrainConfig(), 0))
    if rate is not None:
        write_calibrated(path, path, rate, ("force", "collision"), {"rate": rate, "modules": ["force", "collision"]})
    return path


def test_calibration_bar_reads_the_rate_stored_in_the_checkpoint(tmp_path):
    calibrated = final.calibration_bars(str(_checkpoint(tmp_path / "calibrated.pt", 0.02)))
    assert calibrated == ["| calibrated sampling rate stored in the checkpoint | 0.02 on force, collision | yes |"]
    plain = final.calibration_bars(str(_checkpoint(tmp_path / "plain.pt")))
    assert plain == ["| calibrated sampling rate stored in the checkpoint | none (dropout_rate 0) | no |"]
    assert _met(final.calibration_bars(str(tmp_path / "missing.pt"))) == ["no"]
    assert "calibrated sampling rate" not in final.summary(tmp_path)   # no model, no row
    assert "0.02 on force, collision | yes |" in final.summary(tmp_path, str(tmp_path / "calibrated.pt"))


def test_missing_test_folders_are_made_with_their_seeds(tmp_path, monkeypatch):
    data, out = _data(tmp_path, with_test_folders=False), tmp_path / "out"
    for name, complete in (("unseen_test6_cloth", True), ("unseen_test6_soft", False)):
        (data / name).mkdir()   # made already; stopped half-way (the same command finishes it)
        (data / name / "meta.json").write_text(json.dumps({"complete": complete}))
    ran = []
    monkeypatch.setattr(subprocess, "run", lambda command, **kw: ran.append(command))
    argv = ["--model", "m.pt", "--data", str(data), "--out", str(out), "--only", "pitch", "--test-set", "test6"]
    assert script_main("f", "f", final.add_arguments, final.run, argv) == 0
    made = [c for c in ran if "generate" in c]
    assert [c[c.index("--out") + 1] for c in made] == [str(data / "unseen_test6_rigid"), str(data / "unseen_test6_soft")]
    assert [c[c.index("--first-seed") + 1] for c in made] == ["6800000", "7500000"]
    assert made[0][:3] == [sys.executable, "-m", "hrn_pyg.cli"]
    scored = [c for c in ran if "generate" not in c]
    assert len(scored) == 1 and scored[0][scored[0].index("--out") + 1] == str(out / "pitch.json")


def _write(out, name, content):
    (out / name).write_text(json.dumps(content))


def test_a_rerun_scores_nothing_twice_and_judges_every_bar(tmp_path, monkeypatch, capsys):
    data, out = _data(tmp_path), tmp_path / "out"
    out.mkdir()
    ratios = lambda *r: {k: {"ratio": v} for k, v in zip(validate.PARITY_KEYS, r)}   # noqa: E731
    by_material = lambda rigid15, rigid50: {"rigid": {"position@15": rigid15, "position@50": rigid50,   # noqa: E731
                                                      "ratio_position@15": 1.3}}
    _write(out, "test.json", {
        "specialists": {"cube_collision": ratios(1.2, 1.1, 1.4, 1.5), "multi_material": ratios(1.4, 1.2, 1.3, 1.6)},
        "unseen": {"unseen_by_material": by_material(1.1e-3, 2.0e-3)},
        "rest": [{"folder": "unseen_test3_rigid", "holds": True, "pybullet": {"holds": True, "same_run": True}},
                 {"folder": "unseen_test3_soft", "holds": False, "pybullet": {"holds": False, "same_run": True}}]})
    _write(out, "test_shapes.json", {"unseen": {"unseen_by_material": by_material(1.0e-3, 1.0e-3)}})
    _write(out, "pitch.json", {"rows": [{"pitch": 0.025, "ratio_position@15": 1.1, "ratio_position@50": 1.9},
                                        {"pitch": 0.05, "ratio_position@15": 1.0, "ratio_position@50": 1.0},
                                        {"pitch": 0.08, "ratio_position@15": 2.5, "ratio_position@50": 1.0}]})
    _write(out, "many_objects.json", {"rows": [
        {"objects": 2, "leaves": 100, "model_ms": 2.0, "rest": [{"at_rest": True, "holds": True}]},
        {"objects": 10, "leaves": 500, "model_ms": 8.0, "ratio_to": 2, "ratio_position@15": 1.2,
         "ratio_position@50": 1.5, "rest": [{"at_rest": True, "holds": True}, {"at_rest": False}]}]})
    pile = lambda n, x: {"objects": n, "pybullet_ms": 2.0, "models": {"m.pt": {"compiled": {"x_pybullet": x, "ms": 2 * x}}}}  # noqa: E731
    _write(out, "pile_rigid.json", {"rows": [pile(10, 0.97)]})
    _write(out, "pile_soft.json", {"rows": [pile(2, 0.12), pile(10, 0.25)]})
    _write(out, "roof.json", _roof((0.02, 0.05, 0.377)))
    for name in ("cloth.json", "equivariance.json"):
        _write(out, name, {})

    def no_run(*args, **kwargs):
        raise AssertionError("a finished benchmark ran again")

    monkeypatch.setattr(subprocess, "run", no_run)
    argv = ["--model", "m.pt", "--data", str(data), "--out", str(out)]
    assert script_main("f", "f", final.add_arguments, final.run, argv) == 0
    table = capsys.readouterr().out
    met = {line.split(" | ")[0].strip("| "): line.rsplit(" | ", 1)[1].strip(" |")
           for line in table.splitlines() if line.startswith("| ") and line.endswith(("yes |", "no |", "- |"))}
    expected = {
        "cube_collision test split / specialist <= 1.5 (position, shape at t+15; at t+50)": "yes",
        "multi_material test split / specialist <= 1.5 (position, shape at t+15; at t+50)": "no",
        "unseen rigid meshes / own test split, position t+15 <= 2.0": "yes",
        "unseen rigid meshes / shapes_d4.pt, position t+15, t+50 <= 1.2": "no",   # 1.10, 2.00
        "1000 steps from rest: every test episode holds": "no",
        "1000 steps from rest: every test episode that pybullet's own continuation holds": "yes",
        "1000 steps from rest: every pile of 2 holds": "-",   # reported, not judged
        "1000 steps from rest: every pile of 10 holds": "no",   # a pile that never settled is not held
        "pitch 0.025 m / 0.05 m, position t+15, t+50 <= 2.0": "yes",
        "pitch 0.08 m / 0.05 m, position t+15, t+50 <= 2.0": "no",
        "10 objects / 2, position t+15, t+50 <= 2.0": "yes",
        "time per step by object count": "-",
        "calibrated sampling rate stored in the checkpoint": "no",   # m.pt is no file
        "roof ridge, samples at rate 0.02: Brier vs 2 mm ensemble < constant 1/2's": "yes",
        "roof ridge, samples at rate 0.02: split difference vs 1 cm ensemble": "-",
        "rigid pile of 10, compiled step / pybullet's <= 1.0": "yes",
        "soft pile of 2, compiled step / pybullet's <= 0.2": "yes",
        "soft pile of 10, compiled step / pybullet's <= 0.2": "no",
    }
    assert met == expected
    assert "| 1000 steps from rest: every pile of 10 holds | 1 of 1 settled piles (1 not settled) | no |" in table
    assert "| 1000 steps from rest: every pile of 2 holds | 1 of 1 settled piles (0 not settled) | - |" in table
    assert "| rest, unseen_test3_soft | 0 of 1 hold; pybullet holds 0 of 1, the model 0 of those 0 |" in table
    assert "| 1000 steps from rest: every test episode that pybullet's own continuation holds | 1 of 1 (pybullet holds 1 of 2) | yes |" in table


@pytest.mark.parametrize("extra, words", [
    ([], "no folder shapes_drop"),
    (["--only", "test,nope"], "--only: unknown nope"),
    (["--rest-episodes", "0"], "--rest-episodes must be >= 1"),
])
def test_bad_input_is_one_line(tmp_path, capsys, extra, words):
    argv = ["--model", "m.pt", "--data", str(tmp_path / "nothing"), "--out", str(tmp_path / "o"), *extra]
    assert script_main("f", "f", final.add_arguments, final.run, argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0]


def test_each_test_set_scores_its_own_folders_and_meshes():
    for name, (folders, meshes) in final.TEST_SETS.items():
        cmds = final.commands("m.pt", Path("d"), Path("o"), 6, test_set=name)
        test = cmds["test.json"]
        assert [test[i + 1] for i, w in enumerate(test) if w == "--unseen"] == [str(Path("d") / n) for n in folders]
        cloth = cmds["cloth.json"]
        assert cloth[cloth.index("--episodes") + 1] == str(Path("d") / next(n for n in folders if "cloth" in n))
        pitch = cmds["pitch.json"]
        rigid_scene, rigid_seed = next(iter(folders.values()))
        assert pitch[pitch.index("--scene-file") + 1] == str(REPO / rigid_scene) and "rigid" in rigid_scene
        assert pitch[pitch.index("--first-seed") + 1] == str(rigid_seed)
        many = cmds["many_objects.json"]
        assert [m.split("/")[-2] for m in many[many.index("--meshes") + 1].split(",")] == list(meshes)
    made = final.generate_commands(Path("/nonexistent"), "test3")
    assert sorted(made) == sorted(final.TEST_SETS["test3"][0])
    # no two sets share a mesh
    seen = [m for _, meshes in final.TEST_SETS.values() for m in meshes]
    assert len(seen) == len(set(seen))


def test_a_model_without_a_compiled_path_is_held_to_the_pile_bar_on_its_eager_step():
    row = {"objects": 10, "pybullet_ms": 2.0, "compiled_skipped": "fixed_shape_rollout: this model moves leaves",
           "models": {"m.pt": {"as loaded": {"x_pybullet": 1.4, "ms": 2.8}}}}
    assert final.pile_bars({"rows": [row]}, soft=False) == [
        "| rigid pile of 10, eager step (no compiled path) / pybullet's <= 1.0 | "
        "1.40 (2.80 ms against 2.00) | no |"]
    del row["compiled_skipped"]  # no compiled run and no reason: no row
    assert final.pile_bars({"rows": [row]}, soft=False) == []
