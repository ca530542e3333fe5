"""The HRN's layers on a graph you build yourself: no pybullet, no dataset, no trainer.

Two objects of four particles each (a soft square and a rigid square), one parent per object,
hand-written edges. We run the collision operator and one propagation operator on their own,
then the whole model for three steps through the package's rollout loop.

    python examples/layers_on_your_graph.py [--fast]
"""

from __future__ import annotations

import argparse

import torch

from hrn_pyg import HRN, HRNConfig, rollout
from hrn_pyg.data.graph import (
    COLLISION,
    LEAF_TO_ANCESTOR,
    NODE,
    build_structure,
    set_state,
)
from hrn_pyg.nn import CollisionModule, PropagationModule


def make_scene() -> tuple:
    # leaves 0..7 (object 0: 0-3, object 1: 4-7), then one root per object: nodes 8 and 9
    parent = torch.tensor([8, 8, 8, 8, 9, 9, 9, 9, -1, -1])
    leaf_mass = torch.full((8,), 0.25)
    leaf_object = torch.tensor([0, 0, 0, 0, 1, 1, 1, 1])
    material = torch.tensor([1, 0])  # soft, rigid (see hrn_pyg.data.graph.MATERIALS)
    stiffness = torch.tensor([0.5, 1.0])
    structure = build_structure(parent, leaf_mass, leaf_object, material, stiffness)
    square = torch.tensor([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, 0.05, 0.0], [0.05, 0.05, 0.0]])
    leaves = torch.cat([square + torch.tensor([0.0, 0.0, 0.3]), square + torch.tensor([0.08, 0.0, 0.3])])
    # positions at t-2, t-1, t (leaves only; ancestors are derived), falling 1 cm per step
    fall = torch.tensor([0.0, 0.0, 0.01])
    graph = set_state(structure, leaves + 2 * fall, leaves + fall, leaves, radius=0.05)
    return graph


def main(fast: bool = False) -> None:
    torch.manual_seed(0)
    graph = make_scene()
    store = graph[NODE]
    print(f"{store.num_nodes} nodes; edges:", {t[1]: graph[t].edge_index.size(1) for t in graph.edge_types})

    # 1. one operator alone: collision effects over the collision edges
    state = torch.randn(store.num_nodes, 8)  # any per-particle features you like
    collision = CollisionModule(state_dim=8, effect_dim=16)
    e_c = collision(state, store.pos, graph[COLLISION].edge_index)
    print("collision effect", tuple(e_c.shape), "nonzero rows:", int(e_c.abs().sum(-1).gt(0).sum()))

    # 2. a propagation phase (leaf -> ancestor) on those effects
    l2a = PropagationModule(state_dim=8, effect_dim=16, name="l2a")
    e = e_c + l2a(state, e_c, store.pos, graph[LEAF_TO_ANCESTOR].edge_index)
    print("after L2A, root effects:", e[~store.is_leaf].norm(dim=-1).tolist())

    # 3. the whole HRN (untrained: identity normaliser) rolled out three steps
    model = HRN(HRNConfig(hidden=16, depth=1, effect_dim=16, collision_radius=0.05)).eval()
    with torch.no_grad():
        future = rollout(model, graph, steps=2 if fast else 3)
    print("rollout", tuple(future.shape), "finite:", bool(torch.isfinite(future).all()))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fast", action="store_true", help="the short run CI uses")
    main(parser.parse_args().fast)
