"""Ground-truth ensembles from perturbed pybullet starts (hrn_pyg.sampling.ensemble)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from hrn_pyg.data.episodes import simulate_episode, simulate_episode_alone
from hrn_pyg.data.scene_file import read_scene_file
from hrn_pyg.data.graph import NODE, object_centres
from hrn_pyg.sampling.ensemble import (
    PerturbationConfig,
    MemberNudge,
    draw_offsets,
    episode_state,
    ground_truth_ensemble,
)

STEPS = 4


@pytest.fixture(scope="module")
def reference():
    return simulate_episode("wedge", 5, steps=STEPS)


def test_zero_perturbation_replays_the_episode(reference):
    members = ground_truth_ensemble("wedge", 5, 2, steps=STEPS, perturbation=PerturbationConfig(0.0, 0.0))
    assert members.shape == (2,) + reference["positions"].shape
    np.testing.assert_array_equal(members[0], reference["positions"])
    np.testing.assert_array_equal(members[1], reference["positions"])


def test_perturbation_moves_the_ball_sideways_only_and_repeats(reference):
    pert = PerturbationConfig(position_std=0.002, seed=4)
    members = ground_truth_ensemble("wedge", 5, 3, steps=STEPS, perturbation=pert)
    again = ground_truth_ensemble("wedge", 5, 3, steps=STEPS, perturbation=pert)
    np.testing.assert_array_equal(members, again)
    obj, mass = torch.as_tensor(reference["leaf_object"]).long(), torch.as_tensor(reference["leaf_mass"])
    centres = object_centres(torch.as_tensor(members[:, 0]), obj, 2, mass)
    ref = object_centres(torch.as_tensor(reference["positions"][0]), obj, 2, mass)
    shift = (centres - ref).numpy()  # [M, O=2 (ball, wedge), 3]
    rng = np.random.default_rng(4)
    for m in range(3):
        expected, _ = draw_offsets(rng, reference["object_material"], pert)
        np.testing.assert_allclose(shift[m], expected, atol=2e-6)
    assert np.all(np.abs(shift[:, 0, :2]) > 0)  # ball moved in x and y
    assert np.all(shift[:, :, 2] == 0) and np.all(shift[:, 1] == 0)  # no z offset; wedge static


def test_soft_members_do_not_inherit_each_others_solver_state():
    """Unnudged members of a cloth-on-soft ensemble are the episode itself, each of them: every
    member runs in a fresh process, so pybullet's soft-body state from the member before adds no
    spread (run one after another in this process, the same seed differs by centimetres)."""
    folder = Path(__file__).resolve().parents[2] / "data" / "plausibility"
    spec = read_scene_file(folder / "cloth_on_soft.toml")
    spec = dataclasses.replace(spec, config=dataclasses.replace(spec.config, pitch=0.08, steps=12))
    simulate_episode(spec, 2)  # leaves soft-body state in this process
    members = ground_truth_ensemble(spec.name, 1, 2, perturbation=PerturbationConfig(0.0, 0.0), config=spec)
    alone = simulate_episode_alone(spec, 1)["positions"]
    assert np.array_equal(members[0], alone) and np.array_equal(members[1], alone)


def test_member_nudge_is_draw_m_of_the_stream():
    pert = PerturbationConfig(position_std=0.002, velocity_std=0.01, seed=7)
    material = np.array([0, 1, 2])
    rng = np.random.default_rng(7)
    draws = [draw_offsets(rng, material, pert) for _ in range(3)]

    class Recorder:
        object_material = material

        def nudge(self, offsets, velocities):
            self.got = (offsets, velocities)

    for m in range(3):
        sim = Recorder()
        MemberNudge(pert, m)(sim)
        np.testing.assert_array_equal(sim.got[0], draws[m][0])
        np.testing.assert_array_equal(sim.got[1], draws[m][1])


def test_episode_state_matches_the_episode(reference):
    graph = episode_state(reference, start=2, steps=2)
    store = graph[NODE]
    leaves = store.is_leaf
    pos = torch.as_tensor(reference["positions"])
    torch.testing.assert_close(store.pos[leaves], pos[2])
    torch.testing.assert_close(store.prev_prev_pos[leaves], pos[0])
    assert store.pos_seq.shape == (store.num_nodes, 5, 3)
    torch.testing.assert_close(store.pos_seq[leaves][:, -1], pos[4])
    assert store.force_seq.shape == (store.num_nodes, 2, 3)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda ep: episode_state(ep, start=1), r"start must be in \[2, 3\] for an episode of 4 steps, got 1"),
        (lambda ep: episode_state(ep, start=2, steps=STEPS), r"steps must be in \[1, 2\] from start 2, got 4"),
        (lambda ep: ground_truth_ensemble("wedge", 5, 0, steps=STEPS), r"members must be an integer >= 1, got 0"),
        (lambda ep: PerturbationConfig(position_std=-1.0), r"position_std must be finite and >= 0, got -1.0"),
    ],
)
def test_bad_input_raises(reference, call, message):
    with pytest.raises(ValueError, match=message):
        call(reference)
