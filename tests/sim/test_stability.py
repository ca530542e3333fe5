"""The package's stability check of a long rollout, on hand-made trajectories of a real scene."""

from __future__ import annotations

import pytest
import torch

from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import NODE
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sim.stability import StabilityLimits, mean_pairwise_distance, stability_report


@pytest.fixture(scope="module")
def cubes():
    """cube_collision at step 2: two rigid cubes at rest on the ground."""
    return episode_state(simulate_episode("cube_collision", 8, steps=5), start=2, steps=3)


def _still(graph, steps: int = 30) -> torch.Tensor:
    return graph[NODE].pos.expand(steps, -1, -1).clone()


def test_objects_left_where_they_are_hold(cubes):
    report = stability_report(_still(cubes), cubes, settle=10)
    assert report["finite"] and report["passes_check"] and report["holds"]
    assert report["max_move"] == 0.0 and report["rest_drift"] == 0.0 and report["rigid_shape"] == 0.0
    assert report["min_z"] == pytest.approx(float(cubes[NODE].pos[cubes[NODE].is_leaf, 2].min()))


def test_drift_after_settling_breaks_only_the_drift_limit(cubes):
    traj = _still(cubes)
    traj[20:, :, 0] += 0.08  # every leaf slides 8 cm after step 20
    report = stability_report(traj, cubes, settle=10)
    assert report["rest_drift"] == pytest.approx(0.08, rel=1e-5)
    assert report["passes_check"] and not report["holds"]
    assert stability_report(traj, cubes, settle=25)["holds"]  # settled after the slide
    assert stability_report(traj, cubes, settle=10, limits=StabilityLimits(drift=0.1))["holds"]


def test_a_rigid_object_that_grows_two_percent_breaks_the_shape_limit(cubes):
    store = cubes[NODE]
    traj = _still(cubes)
    obj = store.is_leaf & (store.object == 0)
    centre = store.pos[obj].mean(0)
    traj[-1, obj] = centre + 1.02 * (store.pos[obj] - centre)
    report = stability_report(traj, cubes, settle=10)
    assert report["rigid_shape"] == pytest.approx(0.02, rel=1e-4)
    assert report["passes_check"] and not report["holds"]


def test_sinking_leaving_the_bound_and_nan_fail_the_check(cubes):
    leaf = int(torch.nonzero(cubes[NODE].is_leaf & ~cubes[NODE].is_static)[0])
    for value, axis in ((-0.06, 2), (60.0, 0), (float("nan"), 1)):
        traj = _still(cubes)
        traj[5, leaf, axis] = value
        report = stability_report(traj, cubes, settle=10)
        assert not report["passes_check"] and not report["holds"], value
    assert not stability_report(traj, cubes, settle=10)["finite"]


def test_bad_arguments_are_clear_errors(cubes):
    with pytest.raises(ValueError, match="traj must be"):
        stability_report(_still(cubes)[:, :3], cubes, settle=1)
    with pytest.raises(ValueError, match="settle must be"):
        stability_report(_still(cubes, 5), cubes, settle=5)


def test_mean_pairwise_distance_of_a_unit_square():
    square = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    assert float(mean_pairwise_distance(square)) == pytest.approx((4 * 1 + 2 * 2 ** 0.5) / 6)
