"""The package's stability check of a long rollout, on hand-made trajectories of a real scene."""

from __future__ import annotations

import math

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


def _three_bodies():
    """A hand-made graph: a rigid square (object 0), a soft column 20 cm tall whose leaves weigh
    1, 1, 1 and 3 (object 1), a flat cloth at z = 0.5 (object 2), a static leaf and a non-leaf node."""
    from torch_geometric.data import HeteroData

    from hrn_pyg.data.graph import MATERIALS

    square = [[0.0, 0, 0.1], [0.1, 0, 0.1], [0.1, 0.1, 0.1], [0, 0.1, 0.1]]
    column = [[1.0, 0, 0.0], [1.0, 0, 0.1], [1.0, 0, 0.2], [1.1, 0, 0.1]]
    cloth = [[2.0, 0, 0.5], [2.1, 0, 0.5], [2.0, 0.1, 0.5], [2.1, 0.1, 0.5]]
    pos = torch.tensor(square + column + cloth + [[5.0, 0, 0], [0.05, 0.05, 0.1]])
    kinds = ["rigid"] * 4 + ["soft"] * 4 + ["cloth"] * 4 + ["rigid", "rigid"]
    graph = HeteroData()
    store = graph[NODE]
    store.pos = pos
    store.object = torch.tensor([0] * 4 + [1] * 4 + [2] * 4 + [3, 0])
    store.material = torch.nn.functional.one_hot(torch.tensor([MATERIALS.index(k) for k in kinds]), len(MATERIALS)).float()
    store.mass = torch.tensor([1.0] * 4 + [1.0, 1.0, 1.0, 3.0] + [1.0] * 4 + [1.0, 4.0])[:, None]
    store.is_leaf = torch.tensor([True] * 13 + [False])
    store.is_static = torch.tensor([False] * 12 + [True, False])
    return graph


def test_soft_and_cloth_heights_are_reported_per_object(cubes):
    assert math.isnan(stability_report(_still(cubes), cubes, settle=0)["soft_extent"])   # rigid only
    graph = _three_bodies()
    assert stability_report(_still(graph, 5), graph, settle=0)["soft_extent"] == 1.0
    traj = _still(graph, 5)
    traj[-1, 4:8, 2] = graph[NODE].pos[4:8, 2] * 0.5           # the column squashed to half its height
    report = stability_report(traj, graph, settle=0)
    assert report["soft_extent"] == pytest.approx(0.5)
    assert report["rigid_shape"] == 0.0 and report["passes_check"]
    traj[-1, 8, 2] += 0.01                                     # the flat cloth (height floored at 1 mm) waves 1 cm
    assert stability_report(traj, graph, settle=0)["soft_extent"] == pytest.approx(10.0, rel=1e-4)
    traj[-2, 4:8, 2] = 0.0                                     # only the last step counts
    assert stability_report(traj, graph, settle=0)["soft_extent"] == pytest.approx(10.0, rel=1e-4)


def test_drift_is_of_each_object_s_mass_weighted_centre():
    graph = _three_bodies()
    traj = _still(graph, 6)
    traj[3:, 7, 0] += 0.1                                      # the heavy leaf (3 of 6) of the column
    report = stability_report(traj, graph, settle=0)
    assert report["rest_drift"] == pytest.approx(0.05, rel=1e-5)
    assert report["max_move"] == pytest.approx(0.1, rel=1e-5)
    assert stability_report(traj, graph, settle=3)["rest_drift"] == 0.0
    traj[:, 12, 2] = -9.0                                      # the static leaf is not scored
    assert stability_report(traj, graph, settle=0)["min_z"] == 0.0


def test_the_limits_are_strict_where_the_docstring_says_so():
    graph = _three_bodies()
    still = _still(graph, 4)
    assert stability_report(still, graph, settle=0, limits=StabilityLimits(rigid_change=0.0))["holds"]  # at most
    assert not stability_report(still, graph, settle=0, limits=StabilityLimits(drift=0.0))["holds"]     # below
    moved = still.clone()
    moved[1:, 0:4, 0] += 0.5                                   # the square moves exactly 0.5 m
    assert not stability_report(moved, graph, settle=0, limits=StabilityLimits(bound=0.5))["passes_check"]
    assert stability_report(moved, graph, settle=0, limits=StabilityLimits(bound=0.75))["passes_check"]
    sunk = still.clone()
    sunk[2, 4, 2] = -0.5
    assert not stability_report(sunk, graph, settle=0, limits=StabilityLimits(sink_depth=0.5))["passes_check"]
    with pytest.raises(ValueError) as info:
        stability_report(_still(graph, 5), graph, settle=5)
    assert str(info.value) == "settle must be in [0, 5), got 5"


def test_mean_pairwise_distance_of_a_batch():
    square = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    got = mean_pairwise_distance(torch.stack([square, 2 * square]))
    assert got.tolist() == pytest.approx([(4 + 2 * 2 ** 0.5) / 6, 2 * (4 + 2 * 2 ** 0.5) / 6])
