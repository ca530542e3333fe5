"""``benchmarks/equivariance.py``: the eight lattice maps form the group, a model averaged over
them is equivariant to rounding and the same weights in one pass are not, end to end on tiny
cube_collision episodes."""

from __future__ import annotations

import importlib
import json

import pytest
import torch

from hrn_pyg.checkpoints import load_model
from hrn_pyg.data.dataset import read_episode
from hrn_pyg.sampling.ensemble import episode_state


@pytest.fixture(scope="module")
def bench():
    return importlib.import_module("benchmarks.equivariance")


def test_the_eight_maps_are_distinct_orthogonal_keep_z_and_form_a_group(bench):
    maps = [m for _, m in bench.lattice_symmetries()]
    assert len(maps) == 8 and torch.equal(maps[0], torch.eye(3))
    keys = {tuple(m.flatten().tolist()) for m in maps}
    assert len(keys) == 8
    for a in maps:
        torch.testing.assert_close(a @ a.T, torch.eye(3))
        assert torch.equal(a[2], torch.tensor([0.0, 0.0, 1.0]))
        for b in maps:
            assert tuple((a @ b).flatten().tolist()) in keys


def test_the_averaged_model_is_equivariant_and_one_pass_is_not(bench, tiny_episodes):
    variants = bench.variants_of("shapes_d4")
    assert set(variants) == {"as loaded", "one pass"}
    state = episode_state(read_episode(sorted(tiny_episodes.glob("*.npz"))[0]), 2, 4)
    averaged = bench.equivariance_errors(variants["as loaded"], state, [1, 4])
    single = bench.equivariance_errors(variants["one pass"], state, [1, 4])
    assert len(averaged["symmetries"]) == 7
    assert max(e[4] for e in averaged["symmetries"].values()) < 1e-10
    assert max(e[4] for e in single["symmetries"].values()) > 1e-8
    assert averaged["truth_mse"][4] > 0


def test_the_shipped_generalist_is_equivariant_in_one_pass(bench, tiny_episodes):
    variants = bench.variants_of("shapes")
    assert set(variants) == {"as loaded"} and not variants["as loaded"].config.mirror_average
    state = episode_state(read_episode(sorted(tiny_episodes.glob("*.npz"))[0]), 2, 4)
    errors = bench.equivariance_errors(variants["as loaded"], state, [1, 4])
    assert len(errors["symmetries"]) == 7
    assert max(e[4] for e in errors["symmetries"].values()) < 1e-10
    assert errors["truth_mse"][4] > 0


def test_the_command_writes_its_table(bench, tiny_episodes, tmp_path, capsys):
    out = tmp_path / "eq.json"
    assert bench.main(["--model", "cube_collision", "--data", str(tiny_episodes), "--split", "val",
                       "--horizons", "1,3", "--stride", "20", "--out", str(out)]) == 0
    record = json.loads(out.read_text())
    assert [r["variant"] for r in record["rows"]] == ["as loaded"]  # no mirror average: one variant
    assert record["rows"][0]["windows"] == 1 and set(record["rows"][0]["horizons"]) == {"1", "3"}
    assert "| cube_collision | as loaded | 1 |" in capsys.readouterr().out
    assert load_model("cube_collision").config.mirror_average is False
    with pytest.raises(SystemExit):
        bench.main(["--data", str(tmp_path), "--split", "test"])  # no episodes there
