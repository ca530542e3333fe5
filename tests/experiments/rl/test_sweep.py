"""The sweep over modes and seeds (experiments/rl/sweep.py) and its episode-length figure and
summary tables (experiments/rl/episode_length.py)."""

import csv
import json

from experiments.rl.episode_length import plot_episode_length, write_summary
from experiments.rl.sweep import main


def test_sweep_runs_every_mode_and_seed_and_compares_them(tmp_path, capsys):
    out = tmp_path / "rl"
    argv = ["--task", "tower", "--modes", "deterministic", "action_noise", "--num-seeds", "1",
            "--updates", "1", "--num-envs", "4", "--frames-per-batch", "20", "--minibatch", "20",
            "--eval-episodes", "2", "--out", str(out), "--no-progress"]
    assert main(argv) == 0
    assert (out / "deterministic" / "seed0" / "log.csv").is_file()
    assert (out / "episode_length.png").stat().st_size > 0
    summary = json.loads((out / "summary.json").read_text())
    assert sorted(r["mode"] for r in summary) == ["action_noise", "deterministic"]
    assert plot_episode_length(out, tmp_path / "again.png") == ["deterministic", "action_noise"]
    comparison = json.loads((out / "comparison.json").read_text())
    assert sorted(comparison["modes"]) == ["action_noise", "deterministic"]
    assert comparison["levels"] == [11.25, 7.5]  # three quarters and half of the tower's 15 steps
    assert list(comparison["versus_deterministic"]) == ["action_noise"]
    assert (out / "rl_tower_summary.json").is_file() and (out / "summary.md").is_file()
    # a second seed of one mode: summary.json grows, the first runs stay
    assert main([*argv[:3], "deterministic", *argv[5:7], "--first-seed", "1", *argv[7:]]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert sorted((r["mode"], r["seed"]) for r in summary) == [
        ("action_noise", 0), ("deterministic", 0), ("deterministic", 1)]


def test_sweep_bad_input_exits_2(tmp_path, capsys):
    assert main(["--num-seeds", "0", "--out", str(tmp_path), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("python -m experiments.rl.sweep: error:") and "--num-seeds" in err and "\n" not in err
    assert not any(tmp_path.iterdir())


def test_write_summary_tables(tmp_path):
    for mode, seed, curve in (("deterministic", 0, [10.0] * 5 + [4.0] * 20),
                              ("stochastic", 0, [10.0, 4.0] + [3.0] * 23)):
        log = tmp_path / mode / f"seed{seed}" / "log.csv"
        log.parent.mkdir(parents=True)
        log.write_text("update,mean_episode_length\n" + "".join(f"{i},{v}\n" for i, v in enumerate(curve)))
    results = [{"task": "cube_push", "mode": "stochastic", "seed": 0, "final_length": 3.0,
                "updates_to_final": 2, "success_rate": 1.0, "mean_episode_length": 3.0,
                "pybullet_success_rate": 0.5, "pybullet_mean_length": 6.5},
               {"task": "cube_push", "mode": "deterministic", "seed": 0, "final_length": 4.0,
                "updates_to_final": 13, "success_rate": 0.5, "mean_episode_length": 7.0}]
    write_summary(tmp_path, results)
    with open(tmp_path / "summary.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["mode"] for r in rows] == ["deterministic", "stochastic"]
    md = (tmp_path / "summary.md").read_text().splitlines()
    det = next(line for line in md if line.startswith("| deterministic"))
    sto = next(line for line in md if line.startswith("| stochastic"))
    assert "4.00 [4.00, 4.00]" in det and "| - | - |" in det          # no pybullet check there
    # the stochastic curve's trailing mean is <= 4 from update 7 on, (10 + 4 + 6 * 3) / 8, but
    # only full ten-update windows count: update 9
    assert "| 9.00 [9.00, 9.00] |" in sto and "0.50 [0.50, 0.50]" in sto
