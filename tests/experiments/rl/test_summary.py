import csv
import json
import math

import pytest

from experiments.rl.summary import main as summary_main
from experiments.rl.summary import (
    run_finished,
    run_record,
    share_by_part,
    task_summary,
    write_task_summary,
)
from hrn_pyg.rl.success_curve import EVAL_FIELDS
from hrn_pyg.utils.checkpoint import save_checkpoint

#: per mode and seed: pybullet success at frames 0, 100, 200, and the partial-hit share per update
RUNS = {
    "deterministic": {0: ([0.0, 0.5, 1.0], [0.0] * 4), 1: ([0.0, 0.25, 0.5], [0.0] * 4),
                      2: ([0.0, 0.0, 0.25], [0.0] * 4)},
    "stochastic": {0: ([0.0, 1.0, 1.0], [0.2, 0.1, 0.0, 0.0]), 1: ([0.5, 1.0, 1.0], [0.3, 0.2, 0.1, 0.0]),
                   2: ([0.0, 0.5, 0.5], [0.1, 0.0, 0.0, 0.0])},
}
LENGTHS = [10.0, 9.0, 8.0, 7.0]


def _write_runs(root, runs=RUNS, offsets=None):
    """``log.csv`` and ``eval.csv`` of every run of ``runs``; a run's lengths are
    :data:`LENGTHS` plus ``offsets[seed]`` (default: plus its seed)."""
    for mode, seeds in runs.items():
        for seed, (success, shares) in seeds.items():
            run = root / mode / f"seed{seed}"
            run.mkdir(parents=True)
            offset = seed if offsets is None else offsets[seed]
            with open(run / "log.csv", "w", newline="") as fh:
                w = csv.writer(fh)
                w.writerow(["step", "update", "frames", "mean_episode_length", "partial_hit_share"])
                for u, (length, share) in enumerate(zip(LENGTHS, shares)):
                    w.writerow([u, u, 50 * (u + 1), length + offset, share])
            with open(run / "eval.csv", "w", newline="") as fh:
                w = csv.DictWriter(fh, fieldnames=EVAL_FIELDS)
                w.writeheader()
                for i, s in enumerate(success):
                    w.writerow({"step": 2 * i, "update": 2 * i, "frames": 100 * i, "model_success_rate": 1.0,
                                "model_mean_length": 5.0, "pybullet_success_rate": s,
                                "pybullet_mean_length": 6.0, "agreement": s,
                                "closed_loop_success_rate": s / 2, "closed_loop_mean_length": 7.0})


def test_run_record_by_hand(tmp_path):
    _write_runs(tmp_path)
    rec = run_record(tmp_path / "stochastic" / "seed1")
    assert rec["partial_hit_share_update0"] == 0.3
    assert rec["partial_hit_share_mean"] == pytest.approx(0.15)
    assert rec["partial_hit_share_by_tenth"] == [0.3, 0.2, 0.1, 0.0]  # 4 updates: 4 parts
    assert rec["pybullet_frames_to_50"] == 0 and rec["pybullet_frames_to_80"] == 100
    assert rec["pybullet_success_auc"] == pytest.approx((100 * 0.75 + 100 * 1.0) / 200)
    assert rec["mean_length"] == pytest.approx(9.5) and rec["updates"] == 4
    assert rec["closed_loop_frames_to_50"] == 100 and rec["closed_loop_frames_to_80"] == math.inf
    assert rec["closed_loop_success_auc"] == pytest.approx((100 * 0.375 + 100 * 0.5) / 200)
    never = run_record(tmp_path / "deterministic" / "seed2")
    assert never["pybullet_frames_to_50"] == math.inf


def test_share_by_part():
    assert share_by_part([1.0, 3.0, 5.0, 7.0], 2) == [2.0, 6.0]
    assert share_by_part([1.0, math.nan, 3.0], 1) == [2.0]
    with pytest.raises(ValueError):
        share_by_part([1.0], 0)


def test_summary_statistics_by_hand(tmp_path):
    _write_runs(tmp_path)
    s = task_summary(tmp_path, "tower", resamples=200)
    det, sto = s["statistics"]["deterministic"], s["statistics"]["stochastic"]
    # three seeds: the IQM trims nothing, it is the mean
    assert det["pybullet_success_auc"]["value"] == pytest.approx((0.5 + 0.25 + 0.0625) / 3)
    assert sto["pybullet_success_auc"]["value"] == pytest.approx((0.75 + 0.875 + 0.375) / 3)
    assert det["pybullet_success_auc"]["low"] <= det["pybullet_success_auc"]["value"] <= det["pybullet_success_auc"]["high"]
    assert det["pybullet_frames_to_50"]["value"] == math.inf   # one run never reached 50 %
    poi = s["versus_deterministic"]["stochastic"]
    # AUC: 0.75 and 0.875 beat all three deterministic runs, 0.375 beats two of them
    assert poi["pybullet_success_auc"]["value"] == pytest.approx(8 / 9)
    # frames to 50 % (fewer is better): {100, 0, 100} against {100, 200, inf}, ties count half
    assert poi["pybullet_frames_to_50"]["value"] == pytest.approx((2.5 + 3 + 2.5) / 9)
    assert 0 <= poi["pybullet_success_auc"]["low"] <= poi["pybullet_success_auc"]["high"] <= 1
    modes = s["modes"]
    assert modes["stochastic"]["seeds"] == [0, 1, 2] and modes["stochastic"]["n"] == 3
    assert modes["stochastic"]["partial_hit_share_update0"]["value"] == pytest.approx(0.2)
    runs = {r["seed"]: r for r in modes["deterministic"]["runs"]}
    assert runs[0]["pybullet_frames_to_50"] == 100 and runs[0]["pybullet_frames_to_80"] == 200
    checks = s["checks"]
    assert checks["seeds_per_mode"] == {"deterministic": 3, "stochastic": 3}
    assert not checks["enough_seeds"] and not checks["all_modes_present"]
    assert checks["partial_hit_share_enough"]  # stochastic: IQM of 0.2, 0.3, 0.1 = 0.2 >= 0.1
    assert not checks["near_miss_share_enough"]  # these logs have no near-miss column: not shown
    curve = s["iqm_curves"]["stochastic"]["success"]
    assert curve["judge"] == "pybullet" and curve["frames"] == [0, 100, 200]
    assert curve["iqm"] == pytest.approx([0.5 / 3, 2.5 / 3, 2.5 / 3])
    profile = s["performance_profiles"]["pybullet_final_success"]["modes"]["deterministic"]
    assert profile["fraction"][profile["tau"].index(0.4)] == pytest.approx(2 / 3)  # 1.0 and 0.5 > 0.4
    assert s["iqm_curves"]["deterministic"]["episode_length"]["iqm"][-1] == pytest.approx(
        sum((10 + 9 + 8 + 7) / 4 + seed for seed in range(3)) / 3)


def test_summary_iqm_trims_a_quarter_of_the_seeds_by_hand(tmp_path):
    # eight seeds: two trimmed at each end, so the IQM and the mean differ in every number below
    finals = [0.0, 1.0, 0.0, 0.25, 0.0, 1.0, 0.5, 0.0]        # sorted: 0 0 [0 0 .25 .5] 1 1
    shares = [0.9, 0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.0]         # sorted: 0 0 [.1 .2 .3 .4] .5 .9
    offsets = [0.0, 0.0, 20.0, 0.0, 1.0, 0.0, 2.0, 0.0]       # sorted: 0 0 [0 0 0 1] 2 20
    runs = {"stochastic": {seed: ([0.0, f / 2, f], [share, 0.0, 0.0, 0.0])
                           for seed, (f, share) in enumerate(zip(finals, shares))}}
    _write_runs(tmp_path, runs, offsets)
    s = task_summary(tmp_path, "tower", resamples=200)
    stats = s["statistics"]["stochastic"]
    assert stats["pybullet_final_success"]["value"] == pytest.approx(0.75 / 4)          # mean: 2.75 / 8
    assert stats["pybullet_success_auc"]["value"] == pytest.approx(0.75 / 8)            # AUC = final / 2
    assert stats["mean_length"]["value"] == pytest.approx(8.5 + 1 / 4)                  # mean: 8.5 + 23 / 8
    assert s["modes"]["stochastic"]["partial_hit_share_update0"]["value"] == pytest.approx(0.25)  # mean: 0.3
    assert s["iqm_curves"]["stochastic"]["success"]["iqm"] == pytest.approx([0.0, 0.75 / 8, 0.75 / 4])
    assert s["iqm_curves"]["stochastic"]["episode_length"]["iqm"][-1] == pytest.approx(8.5 + 1 / 4)
    for stat in (stats["pybullet_final_success"], stats["mean_length"]):
        assert stat["low"] <= stat["value"] <= stat["high"] and stat["n"] == 8


def test_written_summary_is_strict_json_and_deterministic(tmp_path):
    _write_runs(tmp_path / "runs")
    a = write_task_summary(tmp_path / "runs", "tower", tmp_path / "a.json", resamples=100)
    b = write_task_summary(tmp_path / "runs", "tower", resamples=100)
    text = (tmp_path / "a.json").read_text()
    assert text == (tmp_path / "runs" / "rl_tower_summary.json").read_text()
    data = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-strict JSON constant {c}"))
    assert data["statistics"]["deterministic"]["pybullet_frames_to_50"]["value"] is None  # never
    assert a["statistics"] == b["statistics"]


def test_no_runs_is_an_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="no runs"):
        task_summary(tmp_path, "tower")


def test_run_record_reads_the_near_miss_share_where_logged(tmp_path):
    run = tmp_path / "stochastic" / "seed0"
    run.mkdir(parents=True)
    with open(run / "log.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["step", "update", "frames", "mean_episode_length", "partial_hit_share", "near_miss_share"])
        for u, (share, near) in enumerate([(0.05, 0.5), (0.0, ""), (0.1, 0.7)]):  # update 1: no hit
            w.writerow([u, u, 10 * (u + 1), 8.0, share, near])
    rec = run_record(run)
    assert rec["near_miss_share_update0"] == 0.5
    assert rec["near_miss_share_mean"] == pytest.approx(0.6)
    assert "near_miss_share_update0" not in run_record(_old_log(tmp_path))  # logs without the column


def _old_log(root):
    run = root / "deterministic" / "seed0"
    run.mkdir(parents=True)
    with open(run / "log.csv", "w", newline="") as fh:
        csv.writer(fh).writerows([["step", "update", "frames", "mean_episode_length", "partial_hit_share"],
                                  [0, 0, 10, 8.0, 0.0]])
    return run


def _save_policy(run, update, updates):
    save_checkpoint(run / "policy.pt", {"model": {}, "update": update,
                                         "config": json.dumps({"ppo": {"updates": updates}})})


def test_summary_command_leaves_out_runs_under_way(tmp_path, capsys):
    _write_runs(tmp_path)
    for mode, seeds in RUNS.items():
        for seed in seeds:
            _save_policy(tmp_path / mode / f"seed{seed}", 4, 4)
    _save_policy(tmp_path / "stochastic" / "seed2", 2, 4)  # under way
    (tmp_path / "deterministic" / "seed1" / "policy.pt").unlink()  # never saved
    assert run_finished(tmp_path / "stochastic" / "seed0") and not run_finished(tmp_path / "stochastic" / "seed2")
    out = tmp_path / "summary.json"
    assert summary_main(["--task", "tower", "--runs", str(tmp_path), "--out", str(out),
                 "--resamples", "50"]) == 0
    summary = json.loads(out.read_text())
    assert summary["modes"]["stochastic"]["seeds"] == [0, 1]
    assert summary["modes"]["deterministic"]["seeds"] == [0, 2]
    printed = capsys.readouterr().out
    assert "| stochastic | 2 |" in printed and "probability of improvement over deterministic" in printed
    assert summary_main(["--task", "tower", "--runs", str(tmp_path / "none")]) == 2
