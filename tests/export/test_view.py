"""``hrn-pyg view``: the page written from a result (meshes, or leaves for a result without
them), served on 127.0.0.1, and bad input as one line with exit code 2."""

from __future__ import annotations

import threading
import urllib.request

import numpy as np
import pytest

from hrn_pyg.cli import main
from hrn_pyg.export.view import VIEWER_NAME, load_result, serve
from hrn_pyg.export.viewer import VIEWER_DIV
from results import write_result

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def test_view_writes_one_page_with_every_future(pybullet_run, tmp_path, capsys):
    result = write_result(tmp_path / "result", pybullet_run, futures=3)
    assert main(["view", str(result), "--no-serve"]) == 0
    page = (result / VIEWER_NAME).read_text()
    assert capsys.readouterr().out.count("\n") == 1
    assert f'id="{VIEWER_DIV}"' in page and "Plotly.newPlot" in page
    assert "<script src=" not in page  # plotly.js is inside the page: it opens offline
    for name in ("truth", "future_00", "future_01", "future_02"):
        assert f'"name":"{name}"' in page
    assert page.count('"type":"mesh3d"') >= 5  # the ground, the truth and three futures


def test_a_result_without_meshes_shows_leaves(pybullet_run, tmp_path):
    result = write_result(tmp_path / "old", pybullet_run, meshes=False)
    trajectories, meshes, dt = load_result(result / "samples.npz")
    assert meshes is None and dt is None and list(trajectories) == ["truth", "future_00", "future_01"]
    np.testing.assert_array_equal(trajectories["future_00"][0], trajectories["truth"][0])
    assert main(["view", str(result), "--no-serve", "--out", str(tmp_path / "page.html")]) == 0
    assert '"type":"scatter3d"' in (tmp_path / "page.html").read_text()


def test_the_page_is_served_on_localhost(pybullet_run, tmp_path):
    result = write_result(tmp_path / "served", pybullet_run)
    assert main(["view", str(result), "--no-serve"]) == 0
    server = serve(result, port=0)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        host, port = server.server_address[:2]
        assert host == "127.0.0.1"
        with urllib.request.urlopen(f"http://{host}:{port}/{VIEWER_NAME}", timeout=10) as response:
            assert response.status == 200 and b"Plotly.newPlot" in response.read()
    finally:
        server.shutdown()
        server.server_close()


@pytest.mark.parametrize("argv, message", [
    (["view", "{tmp}/nowhere"], "no result at"),
    (["view", "{tmp}/bad.npz"], "not a samples file"),
    (["view", "{tmp}/result", "--fps", "0"], "--fps must be > 0"),
    (["view", "{tmp}/result", "--port", "70000"], "--port must be in"),
])
def test_bad_input_is_one_line(pybullet_run, tmp_path, capsys, argv, message):
    write_result(tmp_path / "result", pybullet_run)
    np.savez(tmp_path / "bad.npz", something=np.zeros(3))
    assert main([a.format(tmp=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err, err
