"""Statistics of RL sweeps (hrn_pyg.rl.stats): medians with censoring, bootstrap intervals,
and the per-mode comparison read from run logs."""

import json
import math

import pytest
import torch

from hrn_pyg.rl.stats import (
    bootstrap_median,
    bootstrap_median_difference,
    compare_modes,
    comparison_markdown,
    median,
    reference_levels,
    run_table,
    write_comparison,
)


def test_median_by_hand_with_censored_values():
    assert median(torch.tensor([3.0, 1.0, 2.0])) == 2.0
    assert median(torch.tensor([4.0, 1.0, 2.0, 3.0])) == 2.5
    # censored runs sort last: two of five never reached -> the median is still finite
    assert median(torch.tensor([5.0, math.inf, 1.0, math.inf, 3.0])) == 5.0
    assert median(torch.tensor([1.0, math.inf, math.inf, 2.0])) == math.inf
    rows = torch.tensor([[1.0, 2.0, 9.0], [math.inf, 0.0, math.inf]])
    assert median(rows, dim=1).tolist() == [2.0, math.inf]


def test_bootstrap_median_is_seeded_and_brackets_the_median():
    values = [12.0, 40.0, 7.0, 30.0, 22.0, 15.0]
    a = bootstrap_median(values, seed=3)
    assert a == bootstrap_median(values, seed=3)
    assert a["median"] == 18.5 and a["n"] == 6
    assert min(values) <= a["low"] <= a["median"] <= a["high"] <= max(values)
    assert a["low"] < a["high"]
    one = bootstrap_median([4.0])
    assert one["low"] == one["high"] == one["median"] == 4.0
    flat = bootstrap_median([2.0] * 5)
    assert flat["low"] == flat["high"] == 2.0


def test_bootstrap_interval_covers_the_true_median_about_as_often_as_it_says():
    # percentile bootstrap of the median from 15 normal draws: nominal 95 %, and for small
    # samples a little under; 200 repetitions with 2000 resamples each
    g = torch.Generator().manual_seed(0)
    covered = 0
    for rep in range(200):
        x = torch.randn(15, generator=g).tolist()
        s = bootstrap_median(x, resamples=2000, seed=rep)
        covered += s["low"] <= 0.0 <= s["high"]
    assert 0.85 <= covered / 200 <= 0.995


def test_censored_runs_give_an_open_interval():
    s = bootstrap_median([100.0, 200.0, math.inf, math.inf, math.inf])
    assert s["median"] == math.inf and s["high"] == math.inf and s["low"] == 100.0


def test_difference_interval_separates_distinct_groups_only():
    fast, slow = [100.0, 120.0, 90.0, 130.0, 110.0], [300.0, 280.0, 350.0, 320.0, math.inf]
    d = bootstrap_median_difference(fast, slow)
    assert d["difference"] == 110.0 - 320.0
    assert d["high"] < 0  # excludes 0: fast is faster
    same = bootstrap_median_difference(fast, list(reversed(fast)))
    assert same["difference"] == 0.0 and same["low"] < 0 < same["high"]
    both_never = bootstrap_median_difference([math.inf] * 3, [math.inf] * 3)
    assert math.isnan(both_never["low"]) and math.isnan(both_never["high"])


@pytest.mark.parametrize("values, message", [
    ([], "at least one value"),
    ([1.0, math.nan], "pass math.inf"),
])
def test_bootstrap_bad_input_says_why(values, message):
    with pytest.raises(ValueError, match=message):
        bootstrap_median(values)


def test_bootstrap_bad_level_says_why():
    with pytest.raises(ValueError, match="0 < level < 1"):
        bootstrap_median([1.0, 2.0], level=1.5)
    with pytest.raises(ValueError, match="both groups"):
        bootstrap_median_difference([], [1.0])


def _write_log(folder, lengths):
    folder.mkdir(parents=True)
    rows = ["update,mean_episode_length"] + [f"{i},{'' if math.isnan(v) else v}"
                                             for i, v in enumerate(lengths)]
    (folder / "log.csv").write_text("\n".join(rows) + "\n")


def test_comparison_from_logs_by_hand(tmp_path):
    # max_steps 10 -> levels 7.5 and 5; a 10-update trailing mean reaches a level the first
    # update its full window is at or below it
    fast = [10.0] * 10 + [4.0] * 40            # window mean <= 7.5 at update 14, <= 5 at 18
    slow = [10.0] * 30 + [6.0] * 20            # <= 7.5 at update 36 (7 sixes), never <= 5
    for seed in range(3):
        _write_log(tmp_path / "stochastic" / f"seed{seed}", fast)
        _write_log(tmp_path / "deterministic" / f"seed{seed}", slow)
    results = [{"mode": m, "seed": s, "pybullet_success_rate": 0.5, "model_success_rate": 0.75}
               for m in ("deterministic", "stochastic") for s in range(3)]
    assert reference_levels(10) == [7.5, 5.0]
    rows = run_table(tmp_path, results, max_steps=10)
    by = {(r["mode"], r["seed"]): r for r in rows}
    # window of updates 5..14 holds five 10s and five 4s: mean 7.0 <= 7.5; 5..13 gives 7.6
    assert by[("stochastic", 0)]["updates_to_7.5"] == 14
    assert by[("stochastic", 0)]["updates_to_5"] == 18  # (1 * 10 + 9 * 4) / 10 = 4.6; 17 gives 5.2
    assert by[("deterministic", 1)]["updates_to_7.5"] == 36  # 10 - 0.4 * 7 = 7.2; 6 sixes: 7.6
    assert by[("deterministic", 1)]["updates_to_5"] == math.inf
    assert by[("stochastic", 2)]["final_length"] == 4.0
    assert by[("deterministic", 2)]["final_length"] == 6.0
    cmp = compare_modes(rows, max_steps=10)
    assert cmp["modes"]["stochastic"]["updates_to_7.5"]["median"] == 14
    assert cmp["modes"]["deterministic"]["updates_to_5"]["median"] == math.inf
    assert cmp["versus_deterministic"]["stochastic"]["updates_to_7.5"]["difference"] == 14 - 36
    assert cmp["modes"]["deterministic"]["n"] == 3 and cmp["modes"]["stochastic"]["updates"] == 50
    text = comparison_markdown(cmp, "toy")
    assert "never" in text and "| stochastic | 3 | 50 |" in text
    assert "both never" not in text  # stochastic reaches 5, deterministic never: +inf, not NaN
    written = write_comparison(tmp_path, results, "toy", max_steps=10)
    loaded = json.loads((tmp_path / "comparison.json").read_text())  # strict JSON: no Infinity
    assert loaded["modes"]["deterministic"]["updates_to_5"]["median"] is None
    assert written["modes"]["deterministic"]["updates_to_5"]["median"] == math.inf
    assert (tmp_path / "comparison.md").read_text() == text
