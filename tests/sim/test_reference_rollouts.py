"""Every shipped checkpoint still predicts what it predicted when the references were written,
bit for bit: the plain, sleeping, fixed-shape and sampled rollouts and the RL dynamics' step
(``reference_rollouts.py`` says how they were made)."""

import numpy as np
import pytest
import reference_rollouts as ref


@pytest.fixture(scope="module")
def stored():
    return ref.read()


@pytest.fixture(scope="module")
def computed(stored):
    return ref.compute(ref.stored_episodes(stored))


def test_the_references_are_of_the_shipped_checkpoints(stored):
    digests = ref.checkpoint_digests()
    assert {k: str(stored[f"digest/{k}"]) for k in digests} == digests


def test_every_reference_rollout_is_reproduced_bit_for_bit(stored, computed):
    expected = {k for k in stored if not k.startswith(("episode/", "digest/"))}
    assert set(computed) == expected
    differ = [k for k in sorted(expected) if not np.array_equal(computed[k], stored[k])]
    assert not differ, f"rollouts differ from the references: {differ}"
