"""The viewer in a real browser: Debian's Chromium, headless, driven by Playwright's Python
client (no browser downloaded). The served page loads, its 3D canvas is not blank, hiding a
future changes the picture, and the same page opens from disk without a server.

Skips, saying why, where Chromium or Playwright is not installed (``.ci/run`` installs both).
``HRN_PYG_UPDATE_FIGURES=1`` also writes the screenshot to ``docs/figures/viewer.png``;
``HRN_PYG_VIEWER_RESULT=<folder of hrn-pyg sample>`` views that result instead of the test's
own (the pybullet episode as truth, shifted copies as futures), e.g. for the docs' picture.
"""

from __future__ import annotations

import os
import shutil
import threading
from pathlib import Path

import numpy as np
import pytest

from hrn_pyg.cli import main
from hrn_pyg.export.view import VIEWER_NAME, serve
from hrn_pyg.export.viewer import VIEWER_DIV
from results import write_result

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
#: the flags a root, offline, GPU-less machine needs (without the networking ones Chromium
#: waits on refused connections)
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--disable-quic"]
FIGURE = Path(__file__).resolve().parents[2] / "docs" / "figures" / "viewer.png"
#: a pixel whose channels differ by more than this is coloured (an object), not the white,
#: grey or blue-grey of the page, the ground and the axes
SATURATED = 60

pytestmark = [pytest.mark.skipif(CHROMIUM is None, reason="no chromium on PATH (apt-get install -y chromium)"),
              pytest.mark.filterwarnings("ignore::DeprecationWarning")]


def pixels(png: bytes) -> np.ndarray:
    import io

    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int16)


def coloured_share(image: np.ndarray) -> float:
    return float(((image.max(axis=2) - image.min(axis=2)) > SATURATED).mean())


def wait_for_plot(page) -> None:
    page.wait_for_function(f"""() => {{ const gd = document.getElementById("{VIEWER_DIV}");
        return gd && gd._fullLayout && gd.querySelector(".gl-container canvas"); }}""", timeout=20_000)
    page.wait_for_timeout(800)  # the WebGL scene draws after the canvas exists


def test_the_viewer_draws_and_a_future_can_be_hidden(pybullet_run, tmp_path):
    playwright = pytest.importorskip("playwright.sync_api", reason="no playwright (pip install playwright)")
    given = os.environ.get("HRN_PYG_VIEWER_RESULT")
    result = Path(given) if given else write_result(tmp_path / "result", pybullet_run, futures=2, steps=4)
    assert main(["view", str(result), "--no-serve"]) == 0
    server = serve(result, port=0)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch_persistent_context(
                str(tmp_path / "profile"), executable_path=CHROMIUM, headless=True, args=FLAGS,
                viewport={"width": 960, "height": 640})
            try:
                page = browser.new_page()
                host, port = server.server_address[:2]
                page.goto(f"http://{host}:{port}/{VIEWER_NAME}")
                wait_for_plot(page)
                plot = page.locator(f"#{VIEWER_DIV}")
                first = plot.screenshot()
                assert coloured_share(pixels(first)) > 0.01, "the 3D scene drew nothing"
                page.evaluate(f"""() => {{ const gd = document.getElementById("{VIEWER_DIV}");
                    return Plotly.animate(gd, [gd._transitionData._frames.at(-1).name],
                                          {{frame: {{duration: 0, redraw: true}}, mode: "immediate"}}); }}""")
                page.wait_for_timeout(800)
                shown = plot.screenshot()  # the last frame: the futures apart from the truth
                moved = (np.abs(pixels(first) - pixels(shown)).max(axis=2) > 30).mean()
                assert moved > 0.002, f"the last frame differs from the first in {moved:.2%} of the picture"
                page.locator(f"#{VIEWER_DIV} g.legend g.traces").nth(1).click()  # hide future_00
                page.wait_for_function(f"""() => document.getElementById("{VIEWER_DIV}")
                    ._fullData.some(t => t.name === "future_00" && t.visible === "legendonly")""", timeout=5_000)
                page.wait_for_timeout(800)
                hidden = plot.screenshot()
                changed = (np.abs(pixels(shown) - pixels(hidden)).max(axis=2) > 30).mean()
                assert changed > 0.002, f"hiding a future changed {changed:.2%} of the picture"
                if os.environ.get("HRN_PYG_UPDATE_FIGURES") == "1":
                    FIGURE.parent.mkdir(parents=True, exist_ok=True)
                    FIGURE.write_bytes(shown)

                offline = browser.new_page()  # the same file, from disk: no server
                offline.goto((result / VIEWER_NAME).resolve().as_uri())
                wait_for_plot(offline)
                assert coloured_share(pixels(offline.locator(f"#{VIEWER_DIV}").screenshot())) > 0.01
            finally:
                browser.close()
    finally:
        server.shutdown()
        server.server_close()
