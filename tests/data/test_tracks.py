"""``hrn-pyg import``: pybullet episodes written out as tracks come back as the same episodes (and
so train and evaluate to the same numbers); lattice leaves, rigid motion, soft cells, the
learning_to_simulate layout, and one-line errors."""

import json

import numpy as np
import pytest
import torch

from hrn_pyg.cli import main
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.io import load_episode
from hrn_pyg.data.tracks import (
    ImportConfig,
    read_learning_to_simulate,
    rigid_motion,
    save_tracks,
    to_z_up,
    tracks_from_points,
    tracks_of_episode,
    tracks_to_episode,
)
from hrn_pyg.data.kinds import SOFT, STATIC

NUMERIC = ("positions", "forces", "leaf_mass", "leaf_object", "object_material", "object_stiffness",
           "hierarchy_parent", "seed", "dt")


@pytest.fixture(scope="module")
def round_trip(tiny_episodes, tmp_path_factory):
    """The tiny pybullet folder written out as tracks files and imported again."""
    root = tmp_path_factory.mktemp("tracks")
    files = []
    for path in sorted(tiny_episodes.glob("episode_*.npz")):
        files.append(root / path.name.replace("episode", "tracks"))
        save_tracks(files[-1], tracks_of_episode(load_episode(path)))
    out = root / "imported"
    assert main(["import", *[a for f in files for a in ("--tracks", str(f))], "--out", str(out)]) == 0
    return out


def test_an_episode_comes_back_as_it_was(tiny_episodes, round_trip):
    for path in sorted(tiny_episodes.glob("episode_*.npz")):
        original, imported = load_episode(path), load_episode(round_trip / path.name)
        for key in NUMERIC:
            assert imported[key].dtype == original[key].dtype, key
            np.testing.assert_array_equal(imported[key], original[key], err_msg=key)
        assert json.loads(str(imported["params"]))["config"]["pitch"] == 0.05


def _train(data, out):
    assert main(["train", "--preset", "hrn", "--data", str(data), "--out", str(out), "--train-steps", "2",
                 "--batch-size", "2", "--model-hidden", "16", "--model-depth", "1", "--model-effect-dim", "16",
                 "--seed", "3", "--no-progress"]) == 0
    return out / "model.pt"


def test_training_and_evaluation_give_the_same_numbers(tiny_episodes, round_trip, tmp_path):
    models = {name: _train(folder, tmp_path / name) for name, folder in
              (("pybullet", tiny_episodes), ("imported", round_trip))}
    weights = [torch.load(m, weights_only=True)["model"] for m in models.values()]
    assert weights[0].keys() == weights[1].keys()
    for key in weights[0]:
        torch.testing.assert_close(weights[0][key], weights[1][key], rtol=1e-6, atol=1e-7)
    results = []
    for name, folder in (("pybullet", tiny_episodes), ("imported", round_trip)):
        assert main(["evaluate", "--data", str(folder), "--model", f"m={models['pybullet']}", "--out",
                     str(tmp_path / f"eval_{name}"), "--horizons", "2,5", "--stride", "1"]) == 0
        results.append(json.loads((tmp_path / f"eval_{name}" / "results.json").read_text())["results"]["m"])
    for metric in ("position", "shape"):
        for horizon in ("t+2", "t+5"):
            assert results[1][metric][horizon]["mean"] == pytest.approx(results[0][metric][horizon]["mean"],
                                                                        rel=1e-6, abs=1e-12)


def test_lattice_leaves_of_a_rigid_episode_are_its_own():
    """The wedge's ball and wedge start unrotated, so their leaves lie on the world lattice: snapped
    and moved by the fitted rigid motion (the wedge kept still), they are the same leaves to float
    rounding."""
    episode = simulate_episode("wedge", 3, steps=8)
    again = tracks_to_episode(tracks_of_episode(episode), ImportConfig(leaves="lattice", pitch=0.05), seed=3)
    assert again["positions"].shape == episode["positions"].shape
    for obj in range(len(episode["object_material"])):
        mine, theirs = (e["positions"][:, e["leaf_object"] == obj] for e in (again, episode))
        # the same points, perhaps in another order: match them at step 0
        order = np.argmin(((mine[0][:, None] - theirs[0][None]) ** 2).sum(-1), axis=1)
        assert sorted(order.tolist()) == list(range(theirs.shape[1]))
        np.testing.assert_allclose(mine, theirs[:, order], atol=2e-6)


def test_rigid_motion_recovers_a_rotation():
    rng = np.random.default_rng(0)
    rest = rng.normal(size=(20, 3))
    angle = np.linspace(0, 2.5, 4)
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.zeros((4, 3, 3))
    rotation[:, 0, 0], rotation[:, 0, 1], rotation[:, 1, 0], rotation[:, 1, 1], rotation[:, 2, 2] = c, -s, s, c, 1
    frames = np.einsum("tij,pj->tpi", rotation, rest - rest.mean(0)) + np.array([0.0, 1.0, 2.0])
    got, centre = rigid_motion(rest, frames)
    np.testing.assert_allclose(got, rotation, atol=1e-12)
    np.testing.assert_allclose(centre, np.broadcast_to([0.0, 1.0, 2.0], (4, 3)), atol=1e-12)


def test_a_soft_lattice_leaf_moves_with_its_points():
    """Four points in two cells of pitch 0.1: each leaf is its cell's centre plus the mean
    displacement of its points; the static object stays where it rests."""
    rest = np.array([[0.0, 0, 0.2], [0.02, 0, 0.2], [0.1, 0, 0.2], [0.11, 0, 0.21], [1.0, 0, 0.0]])
    moved = rest + np.array([[0, 0, -0.01], [0, 0, -0.03], [0.01, 0, 0], [0.03, 0, 0], [0.2, 0, 0]])
    tracks = tracks_from_points(np.stack([rest, moved]), np.array([7, 7, 7, 7, 2]),
                                np.array(["soft"] * 4 + ["static"]), dt=0.1, object_mass=2.0)
    episode = tracks_to_episode(tracks, ImportConfig(leaves="lattice", pitch=0.1))
    assert episode["object_material"].tolist() == [STATIC, SOFT]  # objects in increasing id order
    np.testing.assert_allclose(episode["positions"][1], [[1.0, 0, 0], [0, 0, 0.18], [0.12, 0, 0.2]], atol=1e-7)
    np.testing.assert_allclose(episode["leaf_mass"], [2.0, 1.0, 1.0])
    assert episode["object_stiffness"].tolist() == [1.0, 0.5]


def test_the_learning_to_simulate_layout_converts(tmp_path, capsys):
    """Two 2-D trajectories (y up) of a boundary (type 3) and a falling blob (type 5)."""
    t = np.arange(6) / 100
    blob = np.array([[0.5, 0.6], [0.52, 0.6], [0.5, 0.62]])[None] - np.array([0, 1.0])[None, None] * (4.9 * t**2)[:, None, None]
    wall = np.broadcast_to(np.array([[0.1, 0.1], [0.9, 0.1]]), (6, 2, 2))
    position = np.concatenate([wall, blob], axis=1).astype(np.float32)
    types = np.array([3, 3, 5, 5, 5])
    np.savez(tmp_path / "lts.npz", position_0=position, particle_type_0=types, position_1=position[:4],
             particle_type_1=types)
    tracks = read_learning_to_simulate(tmp_path / "lts.npz", {3: STATIC, 5: SOFT}, dt=0.01, ground=0.1)
    assert [len(tr.positions) for tr in tracks] == [6, 4]
    np.testing.assert_allclose(tracks[0].positions[:, 2], to_z_up(position, "y", 0.1)[:, 2])
    np.testing.assert_allclose(tracks[0].positions[0, 2], [0.5, 0, 0.5], atol=1e-6)  # (x, y) -> (x, 0, y - ground)
    out = tmp_path / "out"
    assert main(["import", "--tracks", str(tmp_path / "lts.npz"), "--format", "learning_to_simulate", "--out",
                 str(out), "--dt", "0.01", "--ground", "0.1", "--particle-materials", "3=static,5=soft",
                 "--pitch", "0.02"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["episode_000000.npz", "episode_000001.npz"]
    assert main(["check-data", str(out)]) == 0
    assert "2 episodes" in capsys.readouterr().out
    assert main(["import", "--tracks", str(tmp_path / "lts.npz"), "--format", "learning_to_simulate", "--out",
                 str(out), "--dt", "0.01", "--particle-materials", "3=static"]) == 2
    assert "particle type 5 has no material" in capsys.readouterr().err


@pytest.mark.parametrize("arrays, extra, says", [
    (dict(positions=np.zeros((3, 2, 3)), object=np.array([0, 0]), material=np.array([0, 1])), ["--dt", "0.1"],
     "the points of object 0 have more than one material"),
    (dict(positions=np.zeros((3, 2, 3)), object=np.array([0, 0]), material=np.array([0, 0])), [],
     "no dt in the file; give --dt"),
    (dict(positions=np.zeros((3, 2, 3)), object=np.array([0, 0]), material=np.array([0, 0]), dt=np.array(0.1)),
     ["--leaves", "lattice"], "--leaves lattice needs --pitch"),
])
def test_bad_tracks_are_one_line(tmp_path, capsys, arrays, extra, says):
    np.savez(tmp_path / "t.npz", **arrays)
    assert main(["import", "--tracks", str(tmp_path / "t.npz"), "--out", str(tmp_path / "o"), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and says in err
