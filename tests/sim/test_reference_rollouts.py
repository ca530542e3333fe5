"""Every shipped checkpoint still predicts what it predicted when the references were written:
the plain, sleeping, fixed-shape and sampled rollouts and the RL dynamics' step
(``reference_rollouts.py`` says how they were made), within
:data:`reference_rollouts.CROSS_MACHINE_ATOL`: machines of one kind (torch version, CPU vector
unit) still differ in the kernels their math libraries pick, so bit for bit is not asked."""

import hashlib

import numpy as np
import pytest
import reference_rollouts as ref
import torch

import hrn_pyg
from hrn_pyg.sim.rollout import rollout as rollout_nodes
from hrn_pyg.checkpoints import CHECKPOINT_DIR, load_model


@pytest.fixture(scope="module")
def stored():
    return ref.read()


@pytest.fixture(scope="module")
def computed(stored):
    return ref.compute(ref.stored_episodes(stored))


def differing(computed: dict, stored: dict) -> list[str]:
    """The keys of ``computed`` whose rollouts are further than the tolerance from those stored."""
    return [k for k in sorted(computed)
            if not np.allclose(computed[k], stored[k], rtol=0, atol=ref.CROSS_MACHINE_ATOL)]


def test_the_references_are_of_the_shipped_checkpoints(stored):
    digests = ref.checkpoint_digests()
    assert {k: str(stored[f"digest/{k}"]) for k in digests} == digests


def test_every_shipped_model_has_a_reference():
    """A checkpoint added to the package without a reference rollout fails here (a file with
    the same bytes as one that has a reference, such as an alias, is covered by it)."""
    covered = set(ref.checkpoint_digests().values())
    for path in sorted(CHECKPOINT_DIR.glob("*.pt")):
        if path.stem in ref.NOT_MODELS:
            continue
        digest = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
        assert digest in covered, f"{path.name} has no reference rollout: add it to SCENE_OF in reference_rollouts.py"


def test_every_reference_rollout_is_reproduced(stored, computed):
    expected = {k for k in stored if not k.startswith(("episode/", "digest/", "machine/"))}
    assert set(computed) == expected
    differ = differing(computed, stored)
    assert not differ, f"rollouts differ from the references by more than {ref.CROSS_MACHINE_ATOL} m: {differ}"


@pytest.mark.parametrize("name", ["shapes", "shapes_d4", "wedge", "soft_bounce"])
def test_the_cross_machine_tolerance_sees_a_changed_step_from_rest(stored, name):
    """Every weight 0.1 % larger: the late (near rest) start's rollout leaves the tolerance."""
    scene = ref.scene_key(ref.SCENE_OF[name])
    model = load_model(CHECKPOINT_DIR / f"{name}.pt")
    with torch.no_grad():
        for p in model.parameters():
            p.mul_(1.001)
        state = ref.start_state(model, ref.stored_episodes(stored)[scene], ref.LATE_START)
        changed = rollout_nodes(model, state, ref.STEPS, ref.push(state, ref.STEPS), sleep=None).numpy()
    key = f"{name}/start{ref.LATE_START}/plain"
    assert differing({key: changed}, stored) == [key]
