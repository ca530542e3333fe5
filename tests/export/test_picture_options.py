"""The picture options of ``hrn-pyg sample``: each bad value is one line and exit code 2 before
anything runs; an MP4 is written where imageio-ffmpeg is installed."""

from __future__ import annotations

import numpy as np
import pytest

from hrn_pyg.cli import main
from hrn_pyg.viz import write_gif

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.mark.parametrize("extra, message", [
    (["--frames", "0,x"], "--frames: expected comma-separated numbers"),
    (["--frames", "0,40", "--horizon", "30"], "--frames: step 40 is past the horizon (30)"),
    (["--frames", "-1"], "--frames: steps are >= 0"),
    (["--size", "800"], "--size: expected WIDTHxHEIGHT"),
    (["--size", "10x10"], "--size: each side must be in [32, 8192]"),
    (["--fps", "0"], "--fps must be in (0, 120]"),
    (["--camera", "10"], "--camera: expected 2 comma-separated"),
    (["--export", "glb,stl"], "--export: choose from glb, ply, obj, vtk"),
])
def test_a_bad_picture_option_is_one_line(extra, message, capsys, tmp_path):
    assert main(["sample", "--scene", "soft_bounce", "--out", str(tmp_path / "o"), *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err, err
    assert not (tmp_path / "o").exists()


def test_an_mp4_of_the_chosen_size(tmp_path):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg", reason="no imageio-ffmpeg (pip install 'hrn_pyg[viewer]')")
    truth = np.cumsum(np.full((4, 5, 3), 0.02), axis=0)
    write_gif({"truth": truth}, np.array(["#0072B2"] * 5), tmp_path / "a.mp4", fps=5, samples=truth[None] + 0.01,
              size=(321, 160))
    frames = imageio_ffmpeg.read_frames(str(tmp_path / "a.mp4"))
    meta = next(frames)
    assert meta["size"] == (320, 160) and meta["fps"] == 5  # rounded down to even sides for H.264
    assert sum(1 for _ in frames) == 4
