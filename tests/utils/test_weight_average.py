"""``hrn_pyg.utils.weight_average``: the exponential moving average of a network's weights."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from hrn_pyg.utils.weight_average import WeightAverage


def _net() -> nn.Module:
    torch.manual_seed(0)
    net = nn.Sequential(nn.Linear(3, 4), nn.BatchNorm1d(4), nn.Linear(4, 2)).double()
    return net


def test_the_average_is_the_geometric_weighting_of_the_steps_weights():
    """After steps with weights w_1..w_n from w_0: avg = d^n w_0 + sum_k (1 - d) d^(n-k) w_k."""
    net, d = _net(), 0.8
    average = WeightAverage(net, d)
    history = [{k: p.detach().clone() for k, p in net.named_parameters()}]
    for step in range(5):
        with torch.no_grad():
            for p in net.parameters():
                p.add_(torch.randn_like(p) * (step + 1))
        history.append({k: p.detach().clone() for k, p in net.named_parameters()})
        average.update()
    n = len(history) - 1
    for name in history[0]:
        expected = d ** n * history[0][name] + sum((1 - d) * d ** (n - k) * history[k][name] for k in range(1, n + 1))
        assert torch.allclose(average.average[name], expected, rtol=0, atol=1e-12), name
    assert set(average.average) == {k for k, _ in net.named_parameters()}   # buffers are not averaged


def test_applied_holds_the_average_inside_and_the_trained_weights_after_even_on_error():
    net = _net()
    average = WeightAverage(net, 0.5)
    with torch.no_grad():
        for p in net.parameters():
            p.mul_(3.0)
    average.update()
    trained = {k: v.clone() for k, v in net.state_dict().items()}
    x = torch.randn(5, 3, dtype=torch.float64)
    net.eval()
    with average.applied() as inside:
        assert inside is net
        for name, p in net.named_parameters():
            assert torch.equal(p, average.average[name])
        averaged_output = net(x)
    assert all(torch.equal(v, trained[k]) for k, v in net.state_dict().items())
    assert not torch.allclose(averaged_output, net(x))
    with pytest.raises(RuntimeError, match="inside"):
        with average.applied():
            raise RuntimeError("inside")
    assert all(torch.equal(v, trained[k]) for k, v in net.state_dict().items())


def test_state_round_trips_and_a_foreign_state_is_refused_by_name():
    net = _net()
    average = WeightAverage(net, 0.9)
    with torch.no_grad():
        next(net.parameters()).add_(1.0)
    average.update()
    other = WeightAverage(_net(), 0.9)
    other.load_state_dict(average.state_dict())
    assert all(torch.equal(other.average[k], v) for k, v in average.average.items())
    state = average.state_dict()
    state["0.weight"] = torch.zeros(2, 2, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"0\.weight is \(2, 2\)"):
        other.load_state_dict(state)
    with pytest.raises(ValueError, match="does not fit"):
        other.load_state_dict({"nope": torch.zeros(1)})
    for decay in (0.0, 1.0, -0.1, 1.5):
        with pytest.raises(ValueError, match="decay must be in"):
            WeightAverage(net, decay)
