"""experiments.finetune: the engines' floor is evaluate's position MSE of one engine's leaves
against the other's, a cell folder holds the first training episodes and every validation one,
and the table shows what it is given."""

import numpy as np
import pytest

from experiments.finetune.run import HORIZONS, START, cell_folder, engine_floor, table
from hrn_pyg.data.io import save_episode


def _episode(seed, offset):
    """One rigid object (2 leaves) and one static (1 leaf); the rigid leaves shifted by ``offset``."""
    steps = START + max(HORIZONS)
    positions = np.zeros((steps + 1, 3, 3), np.float32)
    positions[:, :2, 0] = np.arange(steps + 1)[:, None] * 0.01 + offset
    positions[:, 2] = [1.0, 0.0, 0.0]
    return {"positions": positions, "forces": np.zeros((steps, 3, 3), np.float32),
            "leaf_mass": np.ones(3, np.float32), "leaf_object": np.array([0, 0, 1]),
            "object_material": np.array([0, 3]), "object_stiffness": np.ones(2, np.float32),
            "hierarchy_parent": np.array([3, 3, 4, -1, -1]), "seed": np.array(seed), "scene": np.array("t"),
            "params": np.array("{}"), "dt": np.array(1 / 30)}


def test_the_floor_is_the_mean_square_distance_of_the_moving_leaves(tmp_path):
    for seed, offset in ((9, 0.1), (19, 0.3)):
        save_episode(tmp_path / "pybullet" / f"episode_{seed:06d}.npz", _episode(seed, offset))
        save_episode(tmp_path / "mujoco" / f"episode_{seed:06d}.npz", _episode(seed, 0.0))
    floor = engine_floor(tmp_path)["position"]
    # x differs by the offset on the 2 moving leaves, nothing on y and z: MSE = offset^2 / 3
    values = [0.1**2 / 3, 0.3**2 / 3]
    for h in HORIZONS:
        assert floor[f"t+{h}"]["mean"] == pytest.approx(np.mean(values), rel=1e-5)
        assert floor[f"t+{h}"]["sem"] == pytest.approx(np.std(values, ddof=1) / np.sqrt(2), rel=1e-5)
        assert floor[f"t+{h}"]["n"] == 2


def test_a_cell_links_the_first_training_episodes_and_the_validation_ones(tmp_path):
    for seed in range(20):
        save_episode(tmp_path / "mujoco" / f"episode_{seed:06d}.npz", _episode(seed, 0.0))
    folder = cell_folder(tmp_path, 3)
    assert sorted(p.name for p in folder.iterdir()) == [f"episode_{s:06d}.npz" for s in (0, 1, 2, 8, 18)]
    with pytest.raises(ValueError, match="17 training episodes asked, 16 generated"):
        cell_folder(tmp_path, 17)


def test_the_table_has_a_row_per_model():
    result = {"position": {"t+15": {"mean": 0.00123, "sem": 0.0001}}}
    lines = table([("a", "1.5", result)]).splitlines()
    assert lines[0].startswith("| model | CPU min | position MSE t+15")
    assert lines[2] == "| a | 1.5 | 0.00123 ± 0.0001 | - | - | - |"
