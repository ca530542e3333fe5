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
    """Bit for bit where torch and the CPU's vector unit are those the references were written
    with; elsewhere other kernels may round differently, and the rollouts must agree closely."""
    expected = {k for k in stored if not k.startswith(("episode/", "digest/", "machine/"))}
    assert set(computed) == expected
    same_machine = {k: str(stored[f"machine/{k}"]) for k in ref.machine()} == ref.machine()
    if same_machine:
        differ = [k for k in sorted(expected) if not np.array_equal(computed[k], stored[k])]
    else:
        differ = [k for k in sorted(expected) if not np.allclose(computed[k], stored[k], rtol=0, atol=1e-4)]
    assert not differ, f"rollouts differ from the references ({'bit for bit' if same_machine else 'to 0.1 mm'}): {differ}"
