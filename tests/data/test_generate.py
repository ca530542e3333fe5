"""``hrn-pyg generate``: files, skip on rerun, resume after a kill, shards, CLI errors."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from hrn_pyg.cli import main
from hrn_pyg.data.io import load_episode


def _generate(out, *extra):
    return main(["generate", "--scene", "cube_collision", "--episodes", "3", "--out", str(out),
                 "--episode-steps", "4", "--no-progress", *extra])


def test_writes_episodes_and_meta(tmp_path):
    assert _generate(tmp_path) == 0
    files = sorted(f for f in os.listdir(tmp_path) if f.endswith(".npz"))
    assert files == [f"episode_{s:06d}.npz" for s in range(3)]
    ep = load_episode(tmp_path / files[1])
    assert int(ep["seed"]) == 1 and ep["positions"].shape[0] == 5
    meta = json.loads((tmp_path / "meta.json").read_text())
    assert meta["scene"] == "cube_collision" and meta["written"] == 3 and meta["complete"]
    assert meta["config"]["steps"] == 4


def test_rerun_skips_finished(tmp_path):
    assert _generate(tmp_path) == 0
    stamp = {f: os.stat(tmp_path / f).st_mtime_ns for f in os.listdir(tmp_path) if f.endswith(".npz")}
    assert _generate(tmp_path) == 0
    assert {f: os.stat(tmp_path / f).st_mtime_ns for f in stamp} == stamp
    assert json.loads((tmp_path / "meta.json").read_text())["written"] == 0


def test_shards_and_seed_offset(tmp_path):
    assert _generate(tmp_path, "--shard", "1/2", "--first-seed", "10") == 0
    assert sorted(f for f in os.listdir(tmp_path) if f.endswith(".npz")) == ["episode_000011.npz"]


def test_workers_give_the_same_bytes(tmp_path):
    assert _generate(tmp_path / "one") == 0
    assert _generate(tmp_path / "two", "--workers", "2") == 0
    for s in range(3):
        name = f"episode_{s:06d}.npz"
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "two" / name).read_bytes()


def test_resume_after_kill(tmp_path):
    out = tmp_path / "data"
    n = 30
    args = ["generate", "--scene", "cube_collision", "--episodes", str(n), "--out", str(out),
            "--episode-steps", "15", "--no-progress"]
    # the generate module alone (the full CLI imports every sub-command: slow to start)
    script = ("import argparse, sys; from hrn_pyg.data import generate as g; from hrn_pyg.commands import generate as a; "
              "p = argparse.ArgumentParser(); a.add_arguments(p); "
              "sys.exit(g.run(p.parse_args(sys.argv[1:])))")
    proc = subprocess.Popen([sys.executable, "-c", script, *args[1:]],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 180  # generous: a loaded machine starts Python slowly
        while time.time() < deadline and proc.poll() is None:
            if out.exists() and len([f for f in os.listdir(out) if f.endswith(".npz")]) >= 2:
                break
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    assert out.exists(), "the generator wrote nothing before it was killed"
    done_before = [f for f in os.listdir(out) if f.endswith(".npz")]
    assert 2 <= len(done_before) < n
    for f in done_before:  # whatever the kill left behind is whole
        load_episode(out / f)
    assert main(args) == 0
    files = sorted(os.listdir(out))
    assert [f for f in files if f.endswith(".npz")] == [f"episode_{s:06d}.npz" for s in range(n)]
    assert not [f for f in files if f.endswith(".tmp")]
    ep = load_episode(out / f"episode_{n - 1:06d}.npz")
    assert np.all(np.isfinite(ep["positions"]))


@pytest.mark.parametrize(
    "extra, word",
    [
        (["--scene", "nope"], "scene"),
        (["--scene", "wedge", "--pitch", "0"], "pitch"),
        (["--scene", "wedge", "--pitch", "-0.1"], "pitch"),
        (["--scene", "wedge", "--shard", "2/2"], "shard"),
        (["--scene", "wedge", "--shard", "x"], "shard"),
        (["--scene", "wedge", "--episode-steps", "0"], "steps"),
        (["--scene", "wedge", "--episodes", "0"], "episodes"),
        (["--scene", "wedge", "--episodes", "1000001"], "episodes: must be in [1, 1000000]"),
        (["--scene", "wedge", "--workers", "100000"], "workers: must be in [1, 256]"),
        (["--scene", "wedge", "--set", "offset_range"], "NAME=VALUE"),
        (["--scene", "wedge", "--set", "offset_range=[0.1,"], "must be JSON"),
        (["--scene", "wedge", "--set", "colour=3"], "unknown setting 'colour'; the settings are"),
        (["--scene", "wedge", "--set", "offset_range=[0.01,-0.01]"], "offset_range"),
        (["--scene", "wedge", "--set", "pitch=0.1"], "own option"),
    ],
)
def test_cli_errors(tmp_path, capsys, extra, word):
    out = tmp_path / "out"
    argv = ["generate", "--episodes", "2", "--out", str(out), "--no-progress"]
    # a later --episodes wins in argparse
    rc = main(argv + extra)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and word in err[0]
    assert not out.exists()  # nothing written


def test_other_config_in_same_folder_is_refused(tmp_path, capsys):
    assert _generate(tmp_path) == 0
    assert main(["generate", "--scene", "cube_collision", "--episodes", "3", "--out",
                 str(tmp_path), "--episode-steps", "5", "--no-progress"]) == 2
    assert "another scene/config" in capsys.readouterr().err


def test_set_overrides_a_scene_field_and_is_recorded(tmp_path):
    """``--set offset_range=[...]``: the wedge ball starts within 1 mm of the ridge (x = 0), and
    meta.json records the field."""
    out = tmp_path / "ridge"
    assert main(["generate", "--scene", "wedge", "--episodes", "3", "--out", str(out), "--episode-steps", "2",
                 "--set", "offset_range=[-0.001,0.001]", "--no-progress"]) == 0
    meta = json.loads((out / "meta.json").read_text())
    assert meta["config"]["offset_range"] == [-0.001, 0.001]
    for seed in range(3):
        ep = load_episode(out / f"episode_{seed:06d}.npz")
        ball = ep["leaf_object"] == 0
        assert abs(float(ep["positions"][0][ball, 0].mean())) <= 0.001 + 1e-6


def test_soft_and_cloth_episodes_do_not_depend_on_the_ones_before(tmp_path):
    """pybullet's soft-body state outlives a reset within a process; each episode of a scene with
    soft bodies or cloth runs in a fresh one, so a seed gives the same bytes alone or after others."""
    args = ["generate", "--scene", "multi_material", "--episode-steps", "10", "--no-progress"]
    assert main([*args, "--episodes", "2", "--out", str(tmp_path / "both")]) == 0
    assert main([*args, "--episodes", "1", "--first-seed", "1", "--out", str(tmp_path / "alone")]) == 0
    name = "episode_000001.npz"
    assert (tmp_path / "both" / name).read_bytes() == (tmp_path / "alone" / name).read_bytes()


def test_check_plausible_names_what_it_saw():
    from hrn_pyg.data.episodes import DivergedEpisode, check_plausible

    still = np.zeros((4, 5, 3), dtype=np.float32)
    still[..., 2] = 0.1
    check_plausible(still, 0.05, "fine")  # nothing to say
    check_plausible(still - [0, 0, 0.149], 0.05, "a leaf 4.9 cm under the ground is within a pitch")
    for change, word in ((lambda p: p.__setitem__((2, 1, 0), np.nan), "non-finite"),
                         (lambda p: p.__setitem__((3, 0, 1), 60.0), "from the origin"),
                         (lambda p: p.__setitem__((1, 4, 2), -0.051), "under the ground"),
                         (lambda p: p.__setitem__((3, 2, 0), 0.51), "in one step")):
        lost = still.copy()
        change(lost)
        with pytest.raises(DivergedEpisode, match=word):
            check_plausible(lost, 0.05, "scene seed 7")


def test_a_lost_episode_is_marked_skipped_and_counted(tmp_path, capsys):
    scene = tmp_path / "buried.toml"
    scene.write_text('steps = 3\npitch = 0.05\n[[objects]]\nmesh = "box"\nmaterial = "rigid"\n'
                     'size = 0.1\nmass = 1.0\nposition = '
                     '"[0.0, 0.0, uniform(-0.3, -0.2)]"\n')
    out = tmp_path / "out"
    args = ["generate", "--scene-file", str(scene), "--episodes", "2", "--out", str(out), "--no-progress"]
    assert main(args) == 0
    assert sorted(os.listdir(out)) == [".lock", "episode_000000.rejected", "episode_000001.rejected", "meta.json"]
    assert "under the ground" in (out / "episode_000000.rejected").read_text()
    assert capsys.readouterr().err.count("rejected: buried seed") == 2
    meta = json.loads((out / "meta.json").read_text())
    assert meta["rejected"] == 2 and meta["written"] == 0
    stamp = os.stat(out / "episode_000001.rejected").st_mtime_ns
    assert main(args) == 0  # a rerun skips them
    assert os.stat(out / "episode_000001.rejected").st_mtime_ns == stamp
    assert json.loads((out / "meta.json").read_text())["rejected"] == 2


def test_each_shard_keeps_its_record(tmp_path):
    assert _generate(tmp_path, "--shard", "0/2") == 0
    assert _generate(tmp_path, "--shard", "1/2") == 0
    shards = json.loads((tmp_path / "meta.json").read_text())["shards"]
    assert sorted(shards) == ["0/2", "1/2"]
    assert shards["0/2"]["written"] == 2 and shards["1/2"]["written"] == 1 and shards["1/2"]["complete"]


def test_a_killed_writers_temporaries_are_removed_by_the_next_run(tmp_path):
    stale = tmp_path / ".episode_000001.npz.x1y2z3.npz.tmp"
    stale.write_bytes(b"half an episode")
    assert _generate(tmp_path) == 0
    assert not stale.exists() and not list(tmp_path.glob(".*.tmp"))


#: a writer of the folder: holds its record's lock for a second, then writes on until told to stop
_HOLD_LOCK = ("import sys, time\nfrom hrn_pyg.utils.files import FolderLock\n"
              "with FolderLock(sys.argv[1]) as lock:\n"
              "    lock.shared()\n"
              "    with lock.exclusive():\n"
              "        print(lock.alone, flush=True)\n        time.sleep(float(sys.argv[2]))\n"
              "    sys.stdin.readline()\n")


def test_a_second_writer_with_other_settings_stops_with_one_line(tmp_path, capsys):
    """The check of meta.json and its first record are made under the folder's lock: a writer
    that comes while another holds it waits, then finds the other's settings."""
    assert _generate(tmp_path) == 0
    capsys.readouterr()
    holder = subprocess.Popen([sys.executable, "-c", _HOLD_LOCK, str(tmp_path), "1.0"],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "True"  # it took the folder alone
        stale = tmp_path / ".episode_000009.npz.abc.npz.tmp"
        stale.write_bytes(b"in flight")
        start = time.perf_counter()
        code = main(["generate", "--scene", "cube_collision", "--episodes", "3", "--out", str(tmp_path),
                     "--episode-steps", "5", "--no-progress"])
        waited = time.perf_counter() - start
    finally:
        holder.communicate("\n", timeout=60)
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "another scene/config" in err
    assert waited > 0.5  # it waited for the lock before reading meta.json
    assert stale.exists()  # another writer was running: its temporaries are not touched


def test_a_failed_first_run_leaves_no_folder(tmp_path, capsys, monkeypatch):
    import hrn_pyg.data.generate as generate

    def fail(*_):
        raise ValueError("pybullet could not make its collision shape")

    monkeypatch.setattr(generate, "simulate_episode", fail)
    out = tmp_path / "new"
    assert _generate(out) == 2
    assert "collision shape" in capsys.readouterr().err and not out.exists()
    monkeypatch.undo()
    assert _generate(tmp_path / "old") == 0
    before = (tmp_path / "old" / "meta.json").read_text()
    monkeypatch.setattr(generate, "simulate_episode", fail)
    (tmp_path / "old" / "episode_000002.npz").unlink()
    assert _generate(tmp_path / "old") == 2
    assert (tmp_path / "old" / "meta.json").read_text() == before  # as the failed run found it


def test_no_bar_is_drawn_into_a_redirected_stderr(tmp_path, capsys):
    """stderr is no terminal here: the progress is a plain line, no bar's carriage returns."""
    assert main(["generate", "--scene", "cube_collision", "--episodes", "2", "--out", str(tmp_path),
                 "--episode-steps", "4"]) == 0
    assert capsys.readouterr().err.splitlines() == ["generate cube_collision: 2/2 ep"]
    assert main(["generate", "--scene", "cube_collision", "--episodes", "3", "--out", str(tmp_path / "quiet"),
                 "--episode-steps", "4", "--no-progress"]) == 0
    assert capsys.readouterr().err == ""


def test_pybullets_refusal_of_a_mesh_is_one_line_and_leaves_nothing(tmp_path, capsys, monkeypatch):
    from hrn_pyg.data import scene_file

    def refuse(*_):
        raise scene_file.p.error("createCollisionShape failed.")

    monkeypatch.setattr(scene_file.FileScene, "_collision_shape", refuse)
    scene = tmp_path / "box.toml"
    scene.write_text('steps = 3\n[[objects]]\nmesh = "box"\nmaterial = "rigid"\nsize = 0.1\nposition = [0, 0, 0.05]\n')
    out = tmp_path / "out"
    assert main(["generate", "--scene-file", str(scene), "--episodes", "1", "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "objects[0]: pybullet could not make its collision shape" in err, err
    assert not out.exists()
