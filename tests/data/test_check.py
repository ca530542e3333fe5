"""``hrn-pyg check-data``: a valid folder passes with one summary line; each kind of broken
episode is one line naming the file and the problem, and exit code 2."""

import numpy as np
import pytest

from hrn_pyg.cli import main
from hrn_pyg.data.check import tree_roots
from hrn_pyg.data.hierarchy import build_hierarchy
from hrn_pyg.data.io import save_episode


def _episode(seed=0, steps=5):
    """Two rigid 2 x 2 x 2 blocks (pitch 0.1) falling side by side, as the format asks."""
    block = np.stack(np.meshgrid(*[[0.0, 0.1]] * 3, indexing="ij"), -1).reshape(-1, 3)
    x0 = np.concatenate([block + [0, 0, 0.3], block + [0.5, 0, 0.3]])
    fall = -0.5 * 9.81 * (np.arange(steps + 1) / 30.0) ** 2
    positions = (x0[None] + fall[:, None, None] * np.array([0, 0, 1.0])).astype(np.float32)
    leaf_object = np.repeat([0, 1], 8)
    mass = np.full(16, 0.1, dtype=np.float32)
    return {
        "positions": positions, "forces": np.zeros((steps, 16, 3), np.float32), "leaf_mass": mass,
        "leaf_object": leaf_object, "object_material": np.array([0, 0]),
        "object_stiffness": np.ones(2, np.float32),
        "hierarchy_parent": np.asarray(build_hierarchy(x0, mass.astype(float), leaf_object), dtype=np.int64),
        "seed": np.array(seed), "scene": np.array("blocks"),
        "params": np.array('{"config": {"pitch": 0.1}}'), "dt": np.array(1 / 30),
    }


def test_a_valid_folder_passes_with_a_summary(tmp_path, capsys):
    for seed in (0, 8, 9):
        save_episode(tmp_path / f"episode_{seed:06d}.npz", _episode(seed))
    assert main(["check-data", str(tmp_path)]) == 0
    out = capsys.readouterr().out.strip()
    assert out == (f"{tmp_path}: 3 episodes (train 1, val 1, test 1), 5 steps, 16 leaves, rigid, "
                   "pitch 0.1 m, dt 0.0333333 s: ok")


def _broken(change):
    episode = _episode()
    change(episode)
    return episode


def _two_roots(ep):
    """Object 1's leaves split between its root and a new one."""
    parent = ep["hierarchy_parent"]
    ep["hierarchy_parent"] = np.concatenate([parent, [-1]])
    ep["hierarchy_parent"][15] = len(parent)


def _under_ground(ep):
    ep["positions"][-1, 0, 2] = -0.5


def _static_moves(ep):
    ep["object_material"] = np.array([0, 3])


def _too_short(ep):
    ep["positions"], ep["forces"] = ep["positions"][:3], ep["forces"][:2]


@pytest.mark.parametrize("change, says", [
    (_two_roots, "hierarchy_parent: the leaves of object 1 hang under 2 roots, not one"),
    (_under_ground, "under the ground z = 0"),
    (_static_moves, "object 1 is static and moves"),
    (_too_short, "fewer than the 3 of one training window"),
    (lambda ep: ep.update(dt=np.array(0.0)), "dt: must be > 0"),
    (lambda ep: ep.update(params=np.array("{not json")), "params: not JSON"),
])
def test_each_problem_is_one_line_naming_the_file(tmp_path, capsys, change, says):
    save_episode(tmp_path / "episode_000000.npz", _episode())
    bad = tmp_path / "episode_000001.npz"
    np.savez(bad, **_broken(change))  # np.savez: a file the package's own writer would refuse
    assert main(["check-data", str(tmp_path)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 2 and lines[0].startswith(f"{bad}: ") and says in lines[0]
    assert lines[1].endswith(f"1 of 2 episode files in {tmp_path} fail the checks")


def test_a_missing_key_and_an_empty_folder(tmp_path, capsys):
    episode = _episode()
    del episode["leaf_mass"]
    np.savez(tmp_path / "episode_000004.npz", **episode)
    assert main(["check-data", str(tmp_path)]) == 2
    assert "missing key 'leaf_mass'" in capsys.readouterr().err
    assert main(["check-data", str(tmp_path / "nothing")]) == 2
    assert capsys.readouterr().err.strip() == f"hrn-pyg check-data: error: {tmp_path / 'nothing'} is not a folder"


def test_tree_roots_and_cycles():
    assert tree_roots(np.array([3, 3, 4, -1, -1])).tolist() == [3, 3, 4, 3, 4]
    with pytest.raises(ValueError, match="cycle"):
        tree_roots(np.array([1, 2, 1]))
