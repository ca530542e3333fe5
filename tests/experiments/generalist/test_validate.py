"""The generalist's validation suite: its commands, a rerun that skips finished benchmarks, the
summary of their JSON, and one-line errors for bad input."""

import argparse
import json
import subprocess
from pathlib import Path

import pytest

from experiments.command import script_main
from experiments.generalist import validate


def _data(tmp_path):
    data = tmp_path / "data"
    for name in (*validate.UNSEEN, "shapes_drop", *(f for f, _ in validate.SPECIALISTS)):
        (data / name).mkdir(parents=True)
    return data


def test_the_commands_score_the_model_on_validation_episodes_only():
    cmds = validate.commands("m.pt", Path("d"), Path("o"), 6)
    assert sorted(cmds) == ["cloth.json", "parity.json", "piles.json", "rest.json", "unseen2.json",
                            "unseen2_shapes.json", "unseen3.json", "unseen3_shapes.json"]
    for name, cmd in cmds.items():
        model = "shapes_d4" if name.endswith("_shapes.json") else "m.pt"   # the one-pass bar's baseline
        assert cmd[cmd.index("--model") + 1] == model and cmd[cmd.index("--out") + 1] == str(Path("o") / name)
        assert not any("test" in word for word in cmd)
    rest, parity = cmds["rest.json"], cmds["parity.json"]
    assert [rest[i + 1] for i, w in enumerate(rest) if w == "--unseen"] == [
        str(Path("d") / n) for n in validate.UNSEEN]
    assert rest[rest.index("--own-split") + 1] == "val" and parity[parity.index("--own-split") + 1] == "val"
    assert rest[rest.index("--pybullet-rest") + 1] == str(Path("d") / "pybullet_rest")   # shared by every model
    shared = validate.commands("m.pt", Path("d"), Path("o"), 6, Path("w"))["rest.json"]
    assert shared[shared.index("--pybullet-rest") + 1] == "w"
    assert [parity[i + 1] for i, w in enumerate(parity) if w == "--specialist"] == [
        f"{Path('d') / 'cube_collision'}=cube_collision", f"{Path('d') / 'soft_bounce'}=soft_bounce",
        f"{Path('d') / 'multi_material'}=multi_material"]
    piles = cmds["piles.json"]   # piles of the second set's meshes, 1000 steps from rest
    assert piles[piles.index("--meshes") + 1].split(",") == list(validate.PILE_MESHES)
    assert piles[piles.index("--counts") + 1] == "10" and piles[piles.index("--rest-steps") + 1] == "1000"
    assert piles[piles.index("--work") + 1] == str(Path("d") / "validation_piles")


def test_a_rerun_skips_what_is_done_and_sums_it_up(tmp_path, monkeypatch, capsys):
    data, out = _data(tmp_path), tmp_path / "out"
    out.mkdir()
    (out / "rest.json").write_text(json.dumps({"rest": [
        {"folder": "unseen_val_rigid", "holds": True}, {"folder": "unseen_val_rigid", "holds": False},
        {"folder": "unseen_val_soft", "holds": True}]}))
    (out / "parity.json").write_text(json.dumps({"specialists": {"multi_material": {
        "position@15": {"ratio": 1.634}, "shape@15": {"ratio": 1.2}, "position@50": {"ratio": 1.4},
        "shape@50": {"ratio": 1.1}}}}))
    (out / "cloth.json").write_text(json.dumps({"runs": [{"folders": {"unseen_val_cloth": {"summary": {
        "model": {"mean": 10.5}, "pybullet": {"mean": 0.12}}}}}]}))
    (out / "piles.json").write_text(json.dumps({"rows": [{"objects": 10, "rest": [
        {"at_rest": True, "holds": True, "rest_drift": 0.021}, {"at_rest": True, "holds": False, "rest_drift": 0.0526},
        {"at_rest": False}]}]}))

    def no_run(*args, **kwargs):
        raise AssertionError("a finished benchmark ran again")

    monkeypatch.setattr(subprocess, "run", no_run)

    argv = ["--model", "m.pt", "--data", str(data), "--out", str(out)]
    assert script_main("v", "v", validate.add_arguments, validate.run, argv) == 0
    table = capsys.readouterr().out
    assert "| rest, unseen_val_rigid | 1 of 2 hold |" in table and "| rest, unseen_val_soft | 1 of 1 hold |" in table
    assert "| 1.63, 1.20, 1.40, 1.10 |" in table and "| 10.50 (0.12) |" in table
    assert "| 1000 steps from rest, piles of 10 | 1 of 3 hold (1 not settled), largest drift 5.3 cm |" in table


def test_the_summary_counts_the_model_where_pybullet_holds(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    truth = {"holds": True, "same_run": True}
    (out / "rest.json").write_text(json.dumps({"rest": [
        {"folder": "unseen_val_soft", "holds": True, "pybullet": truth},
        {"folder": "unseen_val_soft", "holds": False, "pybullet": truth},
        {"folder": "unseen_val_soft", "holds": False, "pybullet": dict(truth, holds=False)},
        {"folder": "unseen_val_soft", "holds": True, "pybullet": dict(truth, same_run=False)}]}))
    assert ("| rest, unseen_val_soft | 2 of 4 hold; pybullet holds 2 of 4, the model 1 of those 2 |"
            in validate.summary(out))


@pytest.mark.parametrize("extra, words", [
    ([], "no folder unseen_val_rigid"),
    (["--only", "rest,nope"], "--only: unknown nope"),
    (["--rest-episodes", "0"], "--rest-episodes must be >= 1"),
])
def test_bad_input_is_one_line(tmp_path, capsys, extra, words):
    argv = ["--model", "m.pt", "--data", str(tmp_path / "nothing"), "--out", str(tmp_path / "o"), *extra]
    assert script_main("v", "v", validate.add_arguments, validate.run, argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0]


def test_the_second_mesh_set_runs_when_its_folders_are_there_and_is_summed_up(tmp_path, monkeypatch, capsys):
    data, out = _data(tmp_path), tmp_path / "out"
    out.mkdir()
    for name in ("rest.json", "parity.json", "cloth.json", "piles.json"):
        (out / name).write_text("{}")
    ran = []
    monkeypatch.setattr(subprocess, "run", lambda command, **kw: ran.append(command))
    argv = ["--model", "m.pt", "--data", str(data), "--out", str(out)]
    assert script_main("v", "v", validate.add_arguments, validate.run, argv) == 0
    said = capsys.readouterr().out
    assert ran == [] and "the second mesh set is not run: no folder unseen_val2_rigid" in said
    assert "the third mesh set is not run: no folder unseen_val3_rigid" in said
    with pytest.raises(FileNotFoundError, match="no folder unseen_val2_rigid"):
        validate.run(argparse.Namespace(model="m.pt", data=data, out=out, rest_episodes=6, only="unseen2",
                                        pybullet_rest=None))
    for name in validate.UNSEEN2:
        (data / name).mkdir()
    assert script_main("v", "v", validate.add_arguments, validate.run, argv) == 0
    outs = [c[c.index("--out") + 1] for c in ran]
    assert outs == [str(out / "unseen2.json"), str(out / "unseen2_shapes.json")]
    model, baseline = ran
    assert [model[i + 1] for i, w in enumerate(model) if w == "--unseen"] == [str(data / n) for n in validate.UNSEEN2]
    assert baseline[baseline.index("--model") + 1] == "shapes_d4" and not any("cloth" in w for w in baseline)
    by_material = {"rigid": {"position@15": 2e-3, "position@50": 6e-3, "ratio_position@15": 0.9},
                   "soft": {"position@15": 1e-3, "position@50": 3e-3}}
    (out / "unseen2.json").write_text(json.dumps({"unseen": {"unseen_by_material": by_material}, "rest": [
        {"folder": "unseen_val2_cloth", "holds": False}]}))
    (out / "unseen2_shapes.json").write_text(json.dumps({"unseen": {"unseen_by_material": {
        "rigid": {"position@15": 1e-3, "position@50": 6e-3}, "soft": {"position@15": 1e-3, "position@50": 2e-3}}}}))
    table = validate.summary(out)
    assert "| unseen rigid meshes / own validation split, position t+15 | 0.90 |" in table
    assert "| unseen rigid meshes / shapes_d4.pt, position t+15, t+50 | 2.00, 1.00 |" in table
    assert "| unseen soft meshes / shapes_d4.pt, position t+15, t+50 | 1.00, 1.50 |" in table
    assert "| rest, unseen_val2_cloth | 0 of 1 hold |" in table


def test_the_ratios_to_shapes_pt_compare_the_same_windows():
    """The model's JSON also holds the cloth scenes' rigid and soft objects, which shapes_d4.pt never
    ran: its errors are pooled over shapes_d4.pt's folders only, each folder weighted by its finite
    values."""
    def stats(p15, p50, objects, diverged50=0):
        return {"position@15": p15, "position@50": p50, "objects": objects, "diverged@15": 0,
                "diverged@50": diverged50}

    model = {"unseen_folders": ["/d/unseen_val2_rigid", "/d/unseen_val2_soft", "/d/unseen_val2_cloth"],
             "unseen": {"unseen_by_material": {"rigid": {**stats(1.0, 1.0, 9), "ratio_position@15": 0.5},
                                               "soft": stats(1.0, 1.0, 5)},
                        "unseen_by_folder": {"unseen_val2_rigid (rigid)": stats(2e-3, 4e-3, 4, diverged50=1),
                                             "unseen_val2_soft (rigid)": stats(1e-3, 1e-3, 2),
                                             "unseen_val2_cloth (rigid)": stats(1e-6, 1e-6, 3),
                                             "unseen_val2_soft (soft)": stats(3e-4, 6e-4, 4),
                                             "unseen_val2_cloth (soft)": stats(1e-7, 1e-7, 1)}}}
    baseline = {"unseen_folders": ["/d/unseen_val2_rigid", "/d/unseen_val2_soft"],
                "unseen": {"unseen_by_material": {"rigid": stats(1e-3, 2e-3, 6), "soft": stats(3e-4, 3e-4, 4)}}}
    own, ratios = validate.unseen_ratios(model, baseline)
    assert own == 0.5
    rigid15 = (4 * 2e-3 + 2 * 1e-3) / 6 / 1e-3
    rigid50 = (3 * 4e-3 + 2 * 1e-3) / 5 / 2e-3   # the diverged window has no value
    assert ratios["rigid"] == pytest.approx([rigid15, rigid50]) and ratios["soft"] == pytest.approx([1.0, 2.0])
    del model["unseen"]["unseen_by_folder"]
    with pytest.raises(ValueError, match="no per-folder errors"):
        validate.unseen_ratios(model, baseline)
    model["unseen_folders"] = baseline["unseen_folders"]   # the same folders: the per-material means
    assert validate.unseen_ratios(model, baseline)[1]["rigid"] == [1.0 / 1e-3, 1.0 / 2e-3]


def test_the_mesh_sets_are_pooled_window_by_window():
    """Two mesh sets' errors pooled: each set's folders weighted by their finite windows, the
    model's and shapes_d4.pt's over the same (the baseline's) folders."""
    def result(folder_errors):
        by_folder = {f"{f} (rigid)": {"position@15": e, "position@50": 2 * e, "objects": n, "diverged@15": 0,
                                      "diverged@50": 0} for f, (e, n) in folder_errors.items()}
        return {"unseen_folders": [f"/d/{f}" for f in folder_errors], "unseen": {"unseen_by_folder": by_folder}}

    set2 = (result({"unseen_val2_rigid": (2e-3, 3)}), result({"unseen_val2_rigid": (1e-3, 3)}))
    set3 = (result({"unseen_val3_rigid": (1e-3, 1), "unseen_val3_cloth": (9.0, 5)}),
            result({"unseen_val3_rigid": (1e-3, 1)}))
    ratios = validate.pooled_ratios([set2, set3])
    expected = ((3 * 2e-3 + 1e-3) / 4) / ((3 * 1e-3 + 1e-3) / 4)   # the cloth folder: not the baseline's
    assert ratios["rigid"] == pytest.approx([expected, expected]) and "soft" not in ratios
