"""``hrn-pyg sample`` checks its sizes before it simulates or samples anything."""

import pytest
import torch
from torch_geometric.data import HeteroData

from hrn_pyg.cli import main
from hrn_pyg.data.graph import NODE
from hrn_pyg.sampling.cli import MAX_K, MAX_SAMPLE_BYTES, check_memory, check_sizes


@pytest.mark.parametrize("extra, words", [
    (["--k", "100000"], f"--k 100000: at most {MAX_K} futures"),
    (["--k", "2", "--horizon", "1000000000"], "--start plus --horizon is 1000000002 steps, more than 10000"),
])
def test_sizes_past_a_limit_are_one_line_before_anything_runs(tmp_path, capsys, extra, words):
    out = tmp_path / "out"
    assert main(["sample", "--scene", "cube_collision", "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and words in err and not out.exists()


def _graph(nodes: int, leaves: int, edges: int) -> HeteroData:
    graph = HeteroData()
    graph[NODE].is_leaf = torch.arange(nodes) < leaves
    graph[NODE].num_nodes = nodes
    graph[NODE, "e", NODE].edge_index = torch.zeros(2, edges, dtype=torch.long)
    return graph


def test_the_memory_estimate_grows_with_futures_steps_and_leaves():
    graph = _graph(nodes=80, leaves=54, edges=400)
    check_sizes(MAX_K, 10_000)
    check_memory(MAX_K, 30, graph, width=64)  # what the docs ask for, well inside
    per_future = 36 * 10_001 * 54 + 32 * 64 * 480
    fits = MAX_SAMPLE_BYTES // per_future
    check_memory(fits, 10_000, graph, width=64)
    with pytest.raises(ValueError, match=rf"--k {fits + 1} futures of 10000 steps of 54 leaves need about"):
        check_memory(fits + 1, 10_000, graph, width=64)
