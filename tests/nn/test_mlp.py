import pytest
import torch

from hrn_pyg.nn.mlp import MLP, MLPConfig, dropout_mask, in_degree


def test_layers_and_config_errors():
    m = MLP(3, 2, MLPConfig(hidden=8, depth=3, activation="tanh"))
    assert len(m.hidden_layers) == 3 and m(torch.randn(5, 3)).shape == (5, 2)
    assert repr(m) == "MLP(3, 2, hidden=8, depth=3, activation=tanh)"
    with pytest.raises(ValueError, match="activation"):
        MLPConfig(activation="swish2")
    with pytest.raises(ValueError, match="depth"):
        MLPConfig(depth=0)


def test_dropout_mask_values_and_seed():
    assert torch.equal(dropout_mask(3, 8, 0.0), torch.ones(3, 8))
    a = dropout_mask(4, 64, 0.25, torch.Generator().manual_seed(1))
    b = dropout_mask(4, 64, 0.25, torch.Generator().manual_seed(1))
    assert torch.equal(a, b)
    assert torch.isin(a, torch.tensor([0.0, 1.0 / 0.75])).all()
    assert not torch.equal(a[0], a[1])
    with pytest.raises(ValueError, match="rate"):
        dropout_mask(1, 8, 1.0)


def test_mask_scales_hidden_units_per_row():
    torch.manual_seed(0)
    m = MLP(3, 2, MLPConfig(hidden=8, depth=1))
    x = torch.randn(4, 3)
    mask = torch.stack([torch.ones(8), torch.full((8,), 2.0)])
    out = m(x, mask, torch.tensor([0, 1, 0, 1]))
    torch.testing.assert_close(out[[0, 2]], m(x[[0, 2]]))
    h = torch.relu(m.hidden_layers[0](x[[1, 3]]))
    torch.testing.assert_close(out[[1, 3]], m.output_layer(2.0 * h))


def test_output_of_a_sum_equals_the_sum_of_outputs():
    # what the message-passing layers rely on: aggregate the last hidden layer, then apply the
    # affine output layer once per node with the edge count times the bias
    torch.manual_seed(0)
    m = MLP(5, 3, MLPConfig(hidden=8, depth=2))
    x = torch.randn(6, 5)
    dst = torch.tensor([2, 0, 2, 2, 0, 3])
    edge_index = torch.stack([torch.arange(6), dst])
    count = in_degree(edge_index, 5)
    assert count.tolist() == [2, 0, 3, 1, 0]
    per_row = m(x)
    expected = torch.zeros(5, 3).index_add_(0, dst, per_row)
    hidden = m.last_hidden_from_first(m.hidden_layers[0](x))
    summed = m.output_of_sum(torch.zeros(5, 8).index_add_(0, dst, hidden), count)
    torch.testing.assert_close(summed, expected)
    assert torch.equal(summed[[1, 4]], torch.zeros(2, 3))  # no edge: exact zero
    assert torch.equal(m.output_layer(hidden), m.forward_from_first(m.hidden_layers[0](x)))


@pytest.mark.parametrize("activation", ["relu", "tanh", "silu", "gelu"])
def test_in_place_inference_path_equals_the_autograd_path(activation):
    torch.manual_seed(0)
    mlp = MLP(5, 3, MLPConfig(hidden=16, depth=3, activation=activation))
    x = torch.randn(40, 5)
    mask = dropout_mask(4, 16, 0.3, torch.Generator().manual_seed(1))
    index = torch.randint(0, 4, (40,))
    with_grad = mlp(x, mask, index)
    pre = mlp.hidden_layers[0](x)
    kept = pre.clone()
    with torch.no_grad():
        assert torch.equal(mlp(x, mask, index), with_grad.detach())
        # a caller's tensor that is not marked scratch is left as it was
        assert torch.equal(mlp.last_hidden_from_first(pre.detach(), mask, index), mlp.last_hidden_from_first(kept.detach(), mask, index))
    assert torch.equal(pre, kept)
    with_grad.sum().backward()  # the autograd path still records a graph
    assert mlp.hidden_layers[0].weight.grad is not None


def test_in_degree_counts_and_weighs_incoming_edges():
    from hrn_pyg.nn.mlp import in_degree

    edges = torch.tensor([[0, 1, 2, 3], [1, 1, 3, 0]])
    assert torch.equal(in_degree(edges, 5), torch.tensor([1, 2, 0, 1, 0]))
    assert in_degree(edges, 5).dtype == torch.long
    weighted = in_degree(edges, 5, torch.tensor([1.0, 0.0, 1.0, 1.0]))
    assert torch.equal(weighted, torch.tensor([1.0, 1.0, 0.0, 1.0, 0.0]))
    assert torch.equal(in_degree(torch.zeros(2, 0, dtype=torch.long), 3), torch.zeros(3, dtype=torch.long))


def test_sum_by_index_is_pyg_add_aggregation_bit_for_bit():
    from torch_geometric.utils import scatter

    from hrn_pyg.nn.mlp import sum_by_index

    gen = torch.Generator().manual_seed(3)
    values = torch.randn(40, 7, generator=gen)
    index = torch.randint(0, 9, (40,), generator=gen)
    out = sum_by_index(values, index, 11)
    assert torch.equal(out, scatter(values, index, dim=0, dim_size=11, reduce="sum"))
    assert torch.equal(out[9:], torch.zeros(2, 7))
