"""The one MLP constructor of hrn_pyg, with an optional dropout mask handed in from outside.

Every learned function of the HRN is an :class:`MLP` of one :class:`MLPConfig`. Monte Carlo
graph-convolutional dropout (seed paper, 3.2) needs one mask per step per trajectory, shared by
all its nodes and edges, so the mask is passed in as a ``[B, H]`` table looked up by batch id.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import Tensor, nn

#: activation name -> constructor; a name keeps the config a plain, saveable dataclass
ACTIVATIONS: dict[str, type[nn.Module]] = {
    "relu": nn.ReLU,
    "silu": nn.SiLU,
    "tanh": nn.Tanh,
    "gelu": nn.GELU,
}

#: the activations that can overwrite their input (used where no gradient is recorded)
IN_PLACE_ACTIVATIONS: dict[str, Callable[[Tensor], Tensor]] = {
    "relu": torch.relu_,
    "tanh": torch.tanh_,
    "silu": lambda h: nn.functional.silu(h, inplace=True),
}


@dataclass(frozen=True)
class MLPConfig:
    """Shape of every MLP in the model.

    Attributes:
        hidden: width of each hidden layer.
        depth: number of hidden layers (``depth + 1`` linear maps in all).
        activation: a key of :data:`ACTIVATIONS`.
    """

    hidden: int = 64
    depth: int = 2
    activation: str = "relu"

    def __post_init__(self) -> None:
        if self.hidden < 1:
            raise ValueError(f"MLPConfig.hidden must be >= 1, got {self.hidden}")
        if self.depth < 1:
            raise ValueError(f"MLPConfig.depth must be >= 1, got {self.depth}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(
                f"MLPConfig.activation must be one of {sorted(ACTIVATIONS)}, got {self.activation!r}"
            )


class NetworkConfig:
    """What the configs of the networks (HRN, GNS) share, for a frozen dataclass with the fields
    ``hidden``, ``depth``, ``activation`` and ``dropout_modules``: the :class:`MLPConfig` of its
    MLPs, and a JSON-ready dict and back (how checkpoints store it)."""

    @property
    def mlp(self) -> MLPConfig:
        return MLPConfig(hidden=self.hidden, depth=self.depth, activation=self.activation)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["dropout_modules"] = list(self.dropout_modules)
        return d

    #: fields of earlier releases that a saved config may still hold, each at the value that builds
    #: the network this release builds (a subclass names its own)
    REMOVED_FIELDS: dict[str, Any] = {}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Any:
        """The config a saved dict describes; a field of :data:`REMOVED_FIELDS` is dropped at its
        value, and is an error at any other (the network it describes is not built any more)."""
        d = dict(d)
        for name, value in cls.REMOVED_FIELDS.items():
            if name in d and d.pop(name) != value:
                raise ValueError(f"{cls.__name__}: this config sets {name}, which hrn_pyg no longer builds; "
                                 "an earlier release reads it")
        return cls(**d)


def dropout_mask(
    num_copies: int,
    hidden: int,
    rate: float,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    r"""Draw one inverted-dropout mask per trajectory copy.

    .. math::
        m_{b,h} = \frac{\mathbb{1}[u_{b,h} \ge p]}{1 - p}, \qquad u_{b,h} \sim U[0, 1)

    Rate 0 gives a mask of exact ones, so the masked model equals the deterministic one bit for bit.

    **Shapes:** output :math:`(B, H)` with ``B = num_copies`` and ``H = hidden``.
    """
    if num_copies < 1:
        raise ValueError(f"num_copies must be >= 1, got {num_copies}")
    if not 0.0 <= rate < 1.0:
        raise ValueError(f"dropout rate must be in [0, 1), got {rate}")
    if rate == 0.0:
        return torch.ones(num_copies, hidden, device=device)
    u = torch.rand(num_copies, hidden, generator=generator, device=device)
    return (u >= rate).to(torch.float32) / (1.0 - rate)


def in_degree(edge_index: Tensor, num_nodes: int, edge_weight: Tensor | None = None) -> Tensor:
    """Number of edges into each node, ``[num_nodes]`` long, or with ``edge_weight`` ``[E]`` the sum
    of their weights; one ``index_add`` (no host read, unlike ``torch.bincount``)."""
    dst = edge_index[1]
    if edge_weight is None:
        return torch.zeros(num_nodes, dtype=torch.long, device=dst.device).index_add_(0, dst, torch.ones_like(dst))
    return edge_weight.new_zeros(num_nodes).index_add_(0, dst, edge_weight)


def sum_by_index(values: Tensor, index: Tensor, num_rows: int) -> Tensor:
    r"""Rows of ``values`` summed by ``index``: :math:`y_i = \sum_{e:\, \mathrm{index}_e = i} v_e`,
    PyG's ``aggr="add"`` bit for bit (one ``scatter_add_``).

    **Shapes:** values ``(E, F)``, index ``(E,)`` long in ``[0, num_rows)``; returns ``(num_rows, F)``.
    """
    expanded = index.unsqueeze(-1).expand_as(values)
    return values.new_zeros(num_rows, values.size(-1)).scatter_add_(0, expanded, values)



def check_state(who: str, state: Tensor, state_dim: int) -> int:
    """The node count ``N``; a one-line ValueError naming ``who`` unless ``state`` is ``[N, state_dim]``."""
    if state.dim() != 2 or state.size(1) != state_dim:
        raise ValueError(f"{who}: state must be [N, {state_dim}], got {tuple(state.shape)}")
    return state.size(0)


def check_edges(who: str, num_nodes: int, pos: Tensor, edge_index: Tensor, mask: Tensor | None,
                batch: Tensor | None, edge_weight: Tensor | None = None) -> None:
    """The checks an edge module makes before it reads its inputs: a one-line ValueError naming
    ``who`` unless ``pos`` is ``[N, 3]``, ``edge_index`` ``[2, E]``, ``edge_weight`` ``[E]`` (when
    given), and a dropout mask comes with the node batch vector."""
    if pos.shape != (num_nodes, 3):
        raise ValueError(f"{who}: pos must be [N, 3], got {tuple(pos.shape)}")
    if edge_index.dim() != 2 or edge_index.size(0) != 2:
        raise ValueError(f"{who}: edge_index must be [2, E], got {tuple(edge_index.shape)}")
    if edge_weight is not None and edge_weight.shape != (edge_index.size(1),):
        raise ValueError(f"{who}: edge_weight must be [{edge_index.size(1)}], got {tuple(edge_weight.shape)}")
    if mask is not None and batch is None:
        raise ValueError(f"{who}: a dropout mask needs the node batch vector")


def check_force(who: str, force: Tensor | None, num_nodes: int) -> None:
    """A one-line ValueError naming ``who`` unless ``force`` is ``[N, 3]`` (a module that reads it)."""
    if force is None or force.shape != (num_nodes, 3):
        raise ValueError(f"{who} needs force [N, 3], got {None if force is None else tuple(force.shape)}")

class MLP(nn.Module):
    r"""Fully connected network with an optional per-trajectory mask on its hidden activations.

    .. math::
        h_0 = x, \quad h_k = m_{b(r)} \odot \sigma(W_k h_{k-1} + b_k)\ (k = 1..D),
        \quad y = W_{D+1} h_D + b_{D+1}

    where :math:`b(r)` is the batch id (trajectory copy) of row :math:`r` and :math:`m` the mask
    table; without a mask :math:`m = 1`. The same mask row is applied at every hidden layer.

    **Shapes:**
        - **input:** ``x`` :math:`(M, F_{in})`, ``mask`` :math:`(B, H)` or None,
          ``index`` :math:`(M,)` long in ``[0, B)`` (required with a mask)
        - **output:** :math:`(M, F_{out})`
    """

    def __init__(self, in_dim: int, out_dim: int, config: MLPConfig = MLPConfig()) -> None:
        super().__init__()
        if in_dim < 1 or out_dim < 1:
            raise ValueError(f"MLP dims must be >= 1, got in_dim={in_dim}, out_dim={out_dim}")
        self.in_dim = in_dim
        self.out_dim = out_dim
        self.config = config
        dims = [in_dim] + [config.hidden] * config.depth
        self.hidden_layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        self.activation = ACTIVATIONS[config.activation]()
        self.output_layer = nn.Linear(config.hidden, out_dim)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        for layer in self.hidden_layers:
            layer.reset_parameters()
        self.output_layer.reset_parameters()

    def forward(self, x: Tensor, mask: Tensor | None = None, index: Tensor | None = None) -> Tensor:
        return self.forward_from_first(self.hidden_layers[0](x), mask, index, pre_is_scratch=True)

    def split_first_weight(self, sizes: Sequence[int]) -> tuple[Tensor, ...]:
        r"""The first layer's weight cut by input columns, :math:`W_1 = [W_1^{(1)} | W_1^{(2)} | \dots]`,
        so an edge MLP applies each per-node block once per node (:meth:`forward_from_first`)."""
        if sum(sizes) != self.in_dim:
            raise ValueError(f"MLP: column blocks {list(sizes)} do not add up to in_dim={self.in_dim}")
        return torch.split(self.hidden_layers[0].weight, list(sizes), dim=1)

    @property
    def first_bias(self) -> Tensor:
        return self.hidden_layers[0].bias

    def forward_from_first(self, pre: Tensor, mask: Tensor | None = None, index: Tensor | None = None,
                           pre_is_scratch: bool = False) -> Tensor:
        """The MLP from the first layer's pre-activation :math:`W_1 x + b_1` onwards.

        **Shapes:** ``pre`` :math:`(M, H)`; mask and index as in :meth:`forward`; output
        :math:`(M, F_{out})`; ``pre_is_scratch`` as in :meth:`last_hidden_from_first`.
        """
        return self.output_layer(self.last_hidden_from_first(pre, mask, index, pre_is_scratch))

    def last_hidden_from_first(self, pre: Tensor, mask: Tensor | None = None,
                               index: Tensor | None = None, pre_is_scratch: bool = False) -> Tensor:
        """The last (masked) hidden activation :math:`h_D` from the first layer's pre-activation; without
        autograd in place (on ``pre`` too when ``pre_is_scratch``).

        **Shapes:** ``pre`` :math:`(M, H)`; output :math:`(M, H)`.
        """
        row_mask = None
        if mask is not None:
            if index is None:
                raise ValueError("MLP: a dropout mask needs the batch index of every row")
            if mask.dim() != 2 or mask.size(1) != self.config.hidden:
                raise ValueError(
                    f"MLP: mask must be [B, {self.config.hidden}], got {tuple(mask.shape)}"
                )
            row_mask = mask.index_select(0, index)
        no_grad = not torch.is_grad_enabled()
        h = pre
        for k, layer in enumerate(self.hidden_layers):
            if k > 0:
                h = layer(h)
            in_place = no_grad and (k > 0 or pre_is_scratch)  # h is a tensor nobody else holds
            h = self._activate(h, in_place)
            if row_mask is not None:
                h = h.mul_(row_mask) if in_place else h * row_mask
        return h

    def _activate(self, h: Tensor, in_place: bool) -> Tensor:
        name = self.config.activation
        if in_place and name in IN_PLACE_ACTIVATIONS:
            return IN_PLACE_ACTIVATIONS[name](h)
        return self.activation(h)

    def output_of_sum(self, hidden_sum: Tensor, count: Tensor) -> Tensor:
        r"""The output layer applied to a sum of ``count`` last hidden activations, since it is affine:

        .. math::
            \sum_{e \to i} (W h_e + b) = W \Bigl(\sum_{e \to i} h_e\Bigr) + n_i\, b

        (once per node instead of per edge; a node without edges gets an exact zero).

        **Shapes:** ``hidden_sum`` :math:`(N, H)`, ``count`` :math:`(N,)`; output :math:`(N, F_{out})`.
        """
        bias = count.to(hidden_sum.dtype).unsqueeze(1) * self.output_layer.bias
        return torch.addmm(bias, hidden_sum, self.output_layer.weight.T)

    def __repr__(self) -> str:
        c = self.config
        return (
            f"{self.__class__.__name__}({self.in_dim}, {self.out_dim}, hidden={c.hidden}, "
            f"depth={c.depth}, activation={c.activation})"
        )
