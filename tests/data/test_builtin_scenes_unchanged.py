"""The built-in scenes give, for the same seed, the episode arrays they gave when the reference
rollouts were written (tests/sim/reference_rollouts.npz), so shipped datasets stay valid."""

from pathlib import Path

import numpy as np
import pytest

from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.scene_file import SCENES

REFERENCE = Path(__file__).resolve().parents[1] / "sim" / "reference_rollouts.npz"
SEED, STEPS = 9, 60


@pytest.mark.parametrize("scene", sorted(SCENES))
def test_a_built_in_scene_repeats_its_recorded_episode(scene):
    with np.load(REFERENCE, allow_pickle=False) as stored:
        keys = [k for k in stored.files if k.startswith(f"episode/{scene}/")]
        expected = {k.rsplit("/", 1)[1]: stored[k] for k in keys}
    assert expected, f"no recorded episode of {scene}"
    episode = simulate_episode(scene, SEED, steps=STEPS)
    for name, value in expected.items():
        assert np.array_equal(episode[name], value), f"{scene}: {name} differs"
