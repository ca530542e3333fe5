"""Tiny hand-made scenes for the model, loss and rollout tests (no pybullet, no k-means).

Three objects: a soft cube of 8 leaves under two groups and a root, a rigid square of 4 leaves
next to it (close enough to collide at the default radius), and a static body of 2 leaves on
the ground. Nodes: leaves 0..13, groups 14 and 15, roots 16 (soft), 17 (rigid), 18 (static).
"""

from __future__ import annotations

import torch
from torch_geometric.data import HeteroData

from hrn_pyg.data.graph import NODE, build_structure, set_state

#: seconds per model step of the toy trajectories (pybullet default: 8 substeps at 240 Hz)
DT = 1.0 / 30.0
GRAVITY = 9.81

PARENT = torch.tensor([14] * 4 + [15] * 4 + [17] * 4 + [18] * 2 + [16, 16, -1, -1, -1])
LEAF_OBJECT = torch.tensor([0] * 8 + [1] * 4 + [2] * 2)
MATERIAL = torch.tensor([1, 0, 3])
STIFFNESS = torch.tensor([0.5, 1.0, 1.0])


def leaf_rest_positions(separate: bool = False) -> torch.Tensor:
    """``[14, 3]`` leaf positions at rest; ``separate`` moves the rigid square out of reach."""
    corners = torch.tensor([[x, y, z] for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (-0.05, 0.05)])
    cube = corners + torch.tensor([0.0, 0.0, 0.3])
    square = torch.tensor([[0.1, -0.03, 0.28], [0.1, 0.03, 0.28], [0.1, -0.03, 0.34], [0.1, 0.03, 0.34]])
    if separate:
        square = square + torch.tensor([1.0, 0.0, 0.0])
    static = torch.tensor([[-0.5, 0.0, 0.0], [-0.4, 0.0, 0.0]])
    return torch.cat([cube, square, static])


def structure() -> HeteroData:
    leaf_mass = torch.cat([torch.full((8,), 0.1), torch.full((4,), 0.25), torch.full((2,), 1.0)])
    return build_structure(PARENT, leaf_mass, LEAF_OBJECT, MATERIAL, STIFFNESS)


def trajectory(steps: int, seed: int = 0, separate: bool = False) -> torch.Tensor:
    """``[steps + 1, 14, 3]`` leaf positions: the two free objects fall under gravity with a
    small seeded spin-like wobble; the static leaves stay put."""
    gen = torch.Generator().manual_seed(seed)
    x0 = leaf_rest_positions(separate)
    v0 = (torch.rand(1, 3, generator=gen) - 0.5) * 0.02
    wobble = (torch.rand(14, 3, generator=gen) - 0.5) * 0.004
    t = torch.arange(steps + 1, dtype=torch.float32)[:, None, None]
    fall = torch.tensor([0.0, 0.0, -0.5 * GRAVITY * DT**2]) * t**2
    pos = x0 + v0 * t + fall + wobble * torch.sin(0.7 * t)
    pos[:, 12:] = x0[12:]
    return pos


def toy_scene(seed: int = 0, separate: bool = False, force: bool = False, radius: float | None = 0.08) -> HeteroData:
    """The toy scene at a state ``x_{t-2}, x_{t-1}, x_t`` of :func:`trajectory`; ``force`` puts a
    push on leaf 0."""
    leaves = trajectory(2, seed, separate)
    f = torch.zeros(14, 3)
    if force:
        f[0] = torch.tensor([0.5, 0.0, 2.0])
    return set_state(structure(), leaves[0], leaves[1], leaves[2], radius=radius, force=f)


def toy_window(steps: int, seed: int = 0, separate: bool = False) -> HeteroData:
    """The state at the start of :func:`trajectory` plus ``pos_seq [N, steps + 3, 3]`` and a zero
    ``force_seq [N, steps, 3]``, like a dataset window."""
    leaves = trajectory(steps + 2, seed, separate)
    graph = set_state(structure(), leaves[0], leaves[1], leaves[2], radius=0.08)
    from hrn_pyg.data.graph import leaf_to_ancestor_mean

    n = graph[NODE].num_nodes
    full = torch.zeros(steps + 3, n, 3)
    full[:, :14] = leaves
    graph[NODE].pos_seq = leaf_to_ancestor_mean(full, graph).transpose(0, 1).contiguous()
    graph[NODE].force_seq = torch.zeros(n, steps, 3)
    return graph


def toy_model(**config):
    """A small seeded HRN (hidden 16, effect 8, the rigid fit, plus ``config``) with its
    normaliser fitted on toy windows, in eval mode."""
    from hrn_pyg.nn.hrn import HRN, HRNConfig
    from hrn_pyg.nn.normalizer import fit_normalizer

    torch.manual_seed(0)
    model = HRN(HRNConfig(**{"hidden": 16, "depth": 2, "effect_dim": 8, "rigid_fit": True, **config}))
    fit_normalizer([toy_window(4, seed=s) for s in range(3)], model.normalizer)
    return model.eval()
