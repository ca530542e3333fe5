""":mod:`hrn_pyg.sim.plausibility`: energy gains beyond the pushes' work, interpenetration depth,
bodies left hanging at rest and blow-ups, each found where it is and nowhere else; pybullet's own
episode is plausible."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.kinds import RIGID, SOFT
from hrn_pyg.sim.plausibility import ENERGY_TOLERANCE, Scene, plausibility, summary_line

PITCH = 0.05
DT = 1.0 / 30.0


def cube(n: int, origin) -> torch.Tensor:
    ticks = torch.arange(n, dtype=torch.float64) * PITCH
    grid = torch.stack(torch.meshgrid(ticks, ticks, ticks, indexing="ij"), dim=-1).reshape(-1, 3)
    return grid + torch.tensor(origin, dtype=torch.float64)


def two_cubes(material=RIGID) -> tuple[Scene, torch.Tensor]:
    """A 4x4x4 rigid cube on the ground (object 0) and a 3x3x3 cube of ``material`` 1 m above it
    (object 1); the rest positions and the scene."""
    below, above = cube(4, (0.0, 0.0, 0.0)), cube(3, (0.0, 0.0, 1.0))
    rest = torch.cat([below, above])
    scene = Scene(torch.full((91,), 0.1, dtype=torch.float64), torch.tensor([0] * 64 + [1] * 27),
                  torch.tensor([RIGID, material]), rest, PITCH, DT)
    return scene, rest


def still(rest: torch.Tensor, steps: int) -> torch.Tensor:
    return rest.expand(steps, *rest.shape).clone()


def test_a_still_scene_is_plausible_and_a_hanging_body_is_not_supported():
    scene, rest = two_cubes()
    report = plausibility(still(rest, 10), still(rest, 2), scene)[0]
    assert report.energy_rise == 0.0 and report.depth == 0.0 and report.first_non_finite == 0
    assert report.unsupported == 1  # the upper cube hangs 1 m up, at rest
    landed = rest.clone()
    landed[64:, 2] -= 1.0 - 4 * PITCH  # on top of the lower cube, one pitch above its top leaves
    assert plausibility(still(landed, 10), still(landed, 2), scene)[0].unsupported == 0


def test_a_body_that_rises_gains_energy_unless_a_push_pays_for_it():
    scene, rest = two_cubes()
    futures = still(rest, 10)
    futures[:, 64:, 2] += torch.linspace(0.01, 0.1, 10, dtype=torch.float64)[:, None]  # the upper cube climbs
    report = plausibility(futures, still(rest, 2), scene)[0]
    gained = 27 * 0.1 * 9.81 * 0.1  # m g h of the climb, plus a little kinetic energy
    assert report.energy_rise == pytest.approx(gained + 0.5 * 2.7 * (0.01 / DT) ** 2, rel=1e-6)
    assert report.gains_energy and report.energy_share > ENERGY_TOLERANCE
    forces = torch.zeros(10, 91, 3, dtype=torch.float64)
    forces[:, 64:, 2] = 0.1 * 9.81 * 2  # a push of twice the weight, upward: it pays for the climb
    paid = plausibility(futures, still(rest, 2), scene, forces)[0]
    assert paid.energy_rise == 0.0


def test_a_body_pushed_into_another_is_found_inside_and_how_deep():
    scene, rest = two_cubes()
    futures = still(rest, 10)
    sunk = rest.clone()
    sunk[64:] += torch.tensor([0.05, 0.05, -0.95], dtype=torch.float64)  # the upper cube wholly inside the lower
    futures[5:] = sunk
    report = plausibility(futures, still(rest, 2), scene, stride=1)[0]
    assert report.leaves_inside > 0
    assert PITCH * 0.9 <= report.depth <= PITCH * 1.5
    soft_scene, _ = two_cubes(SOFT)
    assert plausibility(futures, still(rest, 2), soft_scene, stride=1)[0].depth == pytest.approx(report.depth)


def test_a_blow_up_is_reported_at_its_step_and_the_rest_is_still_judged():
    scene, rest = two_cubes()
    futures = still(rest, 8)
    futures[3:, 70] = float("nan")
    report = plausibility(futures, still(rest, 2), scene)[0]
    assert report.first_non_finite == 4
    assert np.isfinite(report.energy_rise) and report.energy_rise == 0.0
    line = summary_line([report, report], PITCH)
    assert line.startswith("plausibility of 2 futures: 2 blew up, 0 gained more than 5% energy")


def test_bad_shapes_are_one_clear_error():
    scene, rest = two_cubes()
    with pytest.raises(ValueError, match="futures must be"):
        plausibility(torch.zeros(2, 5, 90, 3), still(rest, 2), scene)
    with pytest.raises(ValueError, match="start must be"):
        plausibility(still(rest, 5), still(rest, 3), scene)


def test_pybullet_is_its_own_plausible_reference():
    episode = simulate_episode("cube_collision", seed=8, steps=40)
    scene = Scene.of_episode(episode)
    truth = torch.as_tensor(episode["positions"], dtype=torch.float64)
    forces = torch.as_tensor(episode["forces"], dtype=torch.float64)
    report = plausibility(truth[2:], truth[:2], scene, forces[1:])[0]
    assert report.first_non_finite == 0 and not report.gains_energy
    assert report.depth <= scene.pitch
