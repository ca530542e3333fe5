""":mod:`hrn_pyg.sampling.start`: a built-in scene or a scene file to a start state in one call,
and ``rollout`` in ``sample``'s convention (leaves, no gradients unless asked, ``seed=``)."""

from __future__ import annotations

import pytest
import torch
from toy_scene import toy_model, toy_scene

import hrn_pyg
from hrn_pyg.data.graph import HISTORY, NODE
from hrn_pyg.data.scene_file import BUILTIN_DIR
from hrn_pyg.sim.rollout import rollout as rollout_nodes


def test_a_scene_by_name_or_file_is_the_same_start_state(tmp_path):
    by_name = hrn_pyg.scene("cube_collision", seed=8, steps=6)
    path = tmp_path / "cubes.toml"
    path.write_text((BUILTIN_DIR / "cube_collision.toml").read_text())
    by_file = hrn_pyg.scene(path, seed=8, steps=6)
    store = by_name[NODE]
    assert store.pos_seq.shape[1] == 6 + 1 and float(by_name.pitch) > 0
    assert torch.equal(store.pos, store.pos_seq[:, HISTORY])
    assert torch.allclose(by_file[NODE].pos_seq, store.pos_seq)
    with pytest.raises(ValueError, match="steps must be >= 3"):
        hrn_pyg.scene("cube_collision", steps=2)


def test_rollout_and_sample_share_one_convention():
    model, state = toy_model(), toy_scene()
    path = hrn_pyg.rollout(model, state, 4, sleep=None)
    leaves = int(state[NODE].is_leaf.sum())
    assert path.shape == (4, leaves, 3) and not path.requires_grad
    assert torch.equal(path, hrn_pyg.sample(model, state, k=1, steps=4, rate=0.0, sleep=None)[0])
    with torch.no_grad():
        nodes = rollout_nodes(model, state, 4, sleep=None)
    assert torch.allclose(path, nodes[:, state[NODE].is_leaf], atol=1e-6)
    tracked = hrn_pyg.rollout(model, state, 2, sleep=None, grad=True)
    assert tracked.requires_grad
    tracked.sum().backward()
    assert any(p.grad is not None for p in model.parameters())


def test_sample_takes_a_seed():
    model, state = toy_model(dropout_modules=("collision",)), toy_scene()
    first = hrn_pyg.sample(model, state, k=3, steps=3, rate=0.3, seed=4, sleep=None)
    again = hrn_pyg.sample(model, state, k=3, steps=3, rate=0.3, seed=4, sleep=None)
    other = hrn_pyg.sample(model, state, k=3, steps=3, rate=0.3, seed=5, sleep=None)
    assert torch.equal(first, again) and not torch.equal(first, other)
    with pytest.raises(ValueError, match="seed= or generator="):
        hrn_pyg.sample(model, state, k=1, steps=1, rate=0.3, seed=1, generator=torch.Generator())
