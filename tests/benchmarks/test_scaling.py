"""``benchmarks/scaling.py --sections``: a run of some experiments keeps the others' rows."""

from __future__ import annotations

import importlib
import json

import pytest


@pytest.fixture(scope="module")
def bench():
    return importlib.import_module("benchmarks.scaling")


def test_the_shape_section_alone_keeps_the_step_rows(bench, tmp_path, monkeypatch):
    out = tmp_path / "scaling.json"
    old = {"particles": [{"leaves": 128, "ms_per_step": 4.0, "edges_total": 100, "peak_mb_per_step": 1.0,
                          "edges": {}, "nodes": 1, "depth": 2, "network_ms": 1.0}],
           "objects": [{"objects": 1, "ms_per_step": 4.0, "edges_total": 100, "edges": {}, "leaves": 125,
                        "peak_mb_per_step": 1.0}],
           "shape_loss_chunks": [{"leaves": 1, "chunk": 1, "ms": 99.0, "peak_mb": 9.0}], "shape_loss_sizes": [],
           "measured": {"particles": {"utc": "then"}}}
    out.write_text(json.dumps(old))
    kept = bench.kept_sections(out, ["particles", "objects"])
    assert kept["particles"] == old["particles"] and kept["objects"] == old["objects"]
    assert "shape_loss_chunks" not in kept
    assert kept["measured"] == {"particles": {"utc": "then"}, "objects": "with the other sections"}
    assert bench.kept_sections(out, []) == {}
    with pytest.raises(SystemExit, match="no earlier rows"):
        bench.kept_sections(tmp_path / "missing.json", ["shape"])


def test_an_unknown_section_is_refused(bench, tmp_path):
    with pytest.raises(SystemExit, match="--sections"):
        bench.main(["--sections", "shapes", "--out", str(tmp_path / "s.json")])
