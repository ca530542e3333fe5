"""Windows, splits and batching of the episode dataset, on tiny synthetic episode files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from torch_geometric.loader import DataLoader

from hrn_pyg.data.dataset import EpisodeWindows, repeated_episodes, split_of_seed
from hrn_pyg.data.graph import COLLISION, NODE
from hrn_pyg.data.hierarchy import build_hierarchy
from hrn_pyg.data.io import save_episode

SIZES = (12, 9)  # leaves per object


def write_episode(folder: Path, seed: int, steps: int = 10) -> Path:
    """A contract-valid episode: two objects drifting at constant velocity, a force on object 0."""
    rng = np.random.default_rng(seed)
    n_leaves = sum(SIZES)
    leaf_object = np.repeat(np.arange(len(SIZES)), SIZES).astype(np.int64)
    start = (rng.uniform(0.0, 0.1, size=(n_leaves, 3)) + np.array([0.08, 0.0, 0.0]) * leaf_object[:, None])
    velocity = rng.normal(size=(n_leaves, 3)) * 0.002
    positions = (start[None] + np.arange(steps + 1)[:, None, None] * velocity[None]).astype(np.float32)
    forces = np.zeros((steps, n_leaves, 3), dtype=np.float32)
    forces[:, leaf_object == 0, 0] = np.arange(steps, dtype=np.float32)[:, None] + 1.0
    leaf_mass = rng.uniform(0.01, 0.05, size=n_leaves).astype(np.float32)
    path = folder / f"episode_{seed:06d}.npz"
    save_episode(
        path,
        dict(
            positions=positions,
            forces=forces,
            leaf_mass=leaf_mass,
            leaf_object=leaf_object,
            object_material=np.array([0, 1], dtype=np.int64),
            object_stiffness=np.array([1.0, 0.3], dtype=np.float32),
            hierarchy_parent=build_hierarchy(positions[0], leaf_mass, leaf_object),
            seed=np.int64(seed),
            scene=np.str_("synthetic"),
            params=np.str_(json.dumps({"steps": steps})),
            dt=np.float64(1.0 / 30.0),
        ),
    )
    return path


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("episodes")
    for seed in range(20):
        write_episode(root, seed, steps=10 + seed % 3)
    (root / "notes.txt").write_text("not an episode")
    return root


def test_split_of_seed() -> None:
    assert [split_of_seed(s) for s in (0, 7, 8, 9, 18, 19, 100)] == [
        "train", "train", "val", "test", "val", "test", "train"]


def test_splits_are_disjoint_and_cover(folder: Path) -> None:
    seeds = {split: set(EpisodeWindows(folder, split).seeds) for split in ("train", "val", "test")}
    assert seeds["val"] == {8, 18} and seeds["test"] == {9, 19}
    assert not (seeds["train"] & seeds["val"]) and not (seeds["train"] & seeds["test"])
    assert seeds["train"] | seeds["val"] | seeds["test"] == set(range(20))


@pytest.mark.parametrize("horizon", [1, 3, 6])
def test_window_count_and_shapes(folder: Path, horizon: int) -> None:
    data = EpisodeWindows(folder, "train", horizon=horizon)
    steps = {s: 10 + s % 3 for s in data.seeds}
    assert len(data) == sum(s - horizon - 1 for s in steps.values())
    window = data[len(data) - 1]
    store = window[NODE]
    n = store.num_nodes
    assert store.pos_seq.shape == (n, horizon + 3, 3)
    assert store.force_seq.shape == (n, horizon, 3)
    for name in ("pos", "prev_pos", "prev_prev_pos", "force"):
        assert store[name].shape == (n, 3)
    # the last window ends at the episode's last step
    seed, t = int(window.episode_seed), int(window.start_step)
    assert t + horizon == steps[seed]


def test_window_content_matches_the_file(folder: Path) -> None:
    data = EpisodeWindows(folder, "train", horizon=2)
    window = data[5]
    seed, t = int(window.episode_seed), int(window.start_step)
    assert t >= 2
    with np.load(folder / f"episode_{seed:06d}.npz", allow_pickle=False) as npz:
        positions, forces, mass = npz["positions"], npz["forces"], npz["leaf_mass"]
    n_leaves = positions.shape[1]
    store = window[NODE]
    leaves = store.is_leaf
    assert int(leaves.sum()) == n_leaves
    np.testing.assert_array_equal(store.pos_seq[leaves].numpy(), positions[t - 2 : t + 3].transpose(1, 0, 2))
    np.testing.assert_array_equal(store.force_seq[leaves].numpy(), forces[t : t + 2].transpose(1, 0, 2))
    assert (store.force_seq[~leaves] == 0).all()
    assert torch.equal(store.pos_seq[:, 0], store.prev_prev_pos)
    assert torch.equal(store.pos_seq[:, 1], store.prev_pos)
    assert torch.equal(store.pos_seq[:, 2], store.pos)
    assert torch.equal(store.force_seq[:, 0], store.force)
    # roots: mass-weighted mean of their object's leaves, at every step of the window
    for root in torch.nonzero(store.is_root).flatten().tolist():
        obj = store.object[root]
        own = (store.object[:n_leaves] == obj).numpy()
        expected = (positions[t - 2 : t + 3, own] * mass[own, None]).sum(1) / mass[own].sum()
        np.testing.assert_allclose(store.pos_seq[root].numpy(), expected, rtol=1e-5, atol=1e-6)


def test_collision_edges_in_windows(folder: Path) -> None:
    window = EpisodeWindows(folder, "val", collision_radius=0.05)[0]
    col = window[COLLISION].edge_index
    store = window[NODE]
    assert col.shape[1] > 0
    assert (store.object[col[0]] != store.object[col[1]]).all() and store.is_leaf[col].all()
    assert EpisodeWindows(folder, "val")[0][COLLISION].edge_index.shape == (2, 0)


def test_dataloader_batches(folder: Path) -> None:
    data = EpisodeWindows(folder, "train", horizon=3, collision_radius=0.05, cache_episodes=2)
    loader = DataLoader(data, batch_size=5, shuffle=True, generator=torch.Generator().manual_seed(0))
    batch = next(iter(loader))
    store = batch[NODE]
    assert batch.num_graphs == 5
    assert store.pos_seq.shape == (store.num_nodes, 6, 3)
    assert store.force_seq.shape == (store.num_nodes, 3, 3)
    assert batch.episode_seed.shape == (5,) and batch.start_step.shape == (5,)
    col = batch[COLLISION].edge_index
    assert (store.batch[col[0]] == store.batch[col[1]]).all()
    l2a = batch[("particle", "leaf_to_ancestor", "particle")].edge_index
    assert (store.batch[l2a[0]] == store.batch[l2a[1]]).all()
    assert int(store.is_root.sum()) == 5 * len(SIZES)
    assert sum(1 for _ in loader) == -(-len(data) // 5)


def test_same_window_twice_is_identical(folder: Path) -> None:
    data = EpisodeWindows(folder, "test", horizon=2, cache_episodes=1)
    a, _, b = data[0], data[len(data) - 1], data[0]  # the middle read evicts episode 0
    for key in ("pos_seq", "force_seq", "mass"):
        assert torch.equal(a[NODE][key], b[NODE][key])


def test_errors(tmp_path: Path, folder: Path) -> None:
    with pytest.raises(FileNotFoundError):
        EpisodeWindows(tmp_path / "missing")
    with pytest.raises(ValueError, match="no episode"):
        EpisodeWindows(tmp_path)
    only_train = tmp_path / "train_only"
    only_train.mkdir()
    write_episode(only_train, 3)
    with pytest.raises(ValueError, match="split 'test'"):
        EpisodeWindows(only_train, "test")
    with pytest.raises(ValueError, match="split"):
        EpisodeWindows(folder, "validation")
    with pytest.raises(ValueError, match="horizon"):
        EpisodeWindows(folder, horizon=0)
    with pytest.raises(ValueError, match="shorter"):
        EpisodeWindows(folder, "val", horizon=20)
    with pytest.raises(ValueError, match="collision_radius"):
        EpisodeWindows(folder, collision_radius=-1.0)
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "episode_000001.npz").write_bytes(b"not a zip file")
    with pytest.raises(ValueError, match="episode_000001"):
        EpisodeWindows(broken)


def test_several_folders_pool_their_episodes_and_a_repeated_seed_is_refused(tmp_path: Path, folder: Path) -> None:
    """A second folder's episodes join the first's in every split; each window is the one its
    own folder gives; a seed in both folders is an error naming it."""
    extra = tmp_path / "extra"
    extra.mkdir()
    for seed in range(100, 110):
        write_episode(extra, seed)
    for split in ("train", "val", "test"):
        one, other = EpisodeWindows(folder, split, horizon=2), EpisodeWindows(extra, split, horizon=2)
        both = EpisodeWindows([folder, extra], split, horizon=2)
        assert sorted(both.seeds) == sorted(one.seeds + other.seeds)
        assert len(both) == len(one) + len(other)
    both, other = EpisodeWindows([folder, extra], "val", horizon=2), EpisodeWindows(extra, "val", horizon=2)
    theirs = {(int(w.episode_seed), int(w.start_step)): w for w in (other[i] for i in range(len(other)))}
    mine = [w for w in (both[i] for i in range(len(both))) if int(w.episode_seed) >= 100]
    assert len(mine) == len(theirs)
    for w in mine:
        torch.testing.assert_close(w[NODE].pos_seq, theirs[(int(w.episode_seed), int(w.start_step))][NODE].pos_seq)
    write_episode(extra, 3)
    with pytest.raises(ValueError, match=r"seed\(s\) \[3\] occur in more than one"):
        EpisodeWindows([folder, extra], "train")
    with pytest.raises(ValueError, match="no episode folder"):
        EpisodeWindows([], "train")


def test_a_seed_may_repeat_across_folders_of_different_scenes(tmp_path: Path) -> None:
    """Seed 3 of two scenes is two episodes and both are pooled; seed 3 twice of one scene, or of
    a folder whose ``meta.json`` names no scene, is refused."""
    folders = {}
    for name, scene in (("a", "cube_collision"), ("b", "multi_material"), ("c", "cube_collision"), ("d", None)):
        folders[name] = tmp_path / name
        folders[name].mkdir()
        write_episode(folders[name], 3)
        if scene is not None:
            (folders[name] / "meta.json").write_text(json.dumps({"scene": scene, "episodes": 1}))
    both = EpisodeWindows([folders["a"], folders["b"]], "train", horizon=2)
    assert both.seeds == [3, 3] and len(both) == 2 * len(EpisodeWindows(folders["a"], "train", horizon=2))
    for other in ("c", "d"):
        with pytest.raises(ValueError, match=r"seed\(s\) \[3\] occur in more than one"):
            EpisodeWindows([folders["a"], folders[other]], "train")
    assert repeated_episodes([(1, "x"), (1, "y"), (2, "x"), (2, "x"), (4, None), (4, "x"), (5, None)]) == [2, 4]
