"""The rollout loop: the model fed its own predictions, one :func:`~hrn_pyg.sim.step.step` a time.

:func:`iterate` is the loop, a generator of :class:`~hrn_pyg.sim.step.Step`; :func:`unroll`
keeps every step and :func:`rollout` their positions. Training, evaluation, sampling and the
stability checks all run through it. Before the first step it makes the scene's
:class:`~hrn_pyg.data.effects.EffectPlan` and objects once; objects at rest sleep unless told
not to (:mod:`hrn_pyg.sim.sleeping`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.data.candidates import VerletSearch
from hrn_pyg.data.effects import EffectPlan, SceneEffects, plan_effects
from hrn_pyg.data.graph import NODE, set_state
from hrn_pyg.nn.hrn import HRN, StepOptions
from hrn_pyg.nn.pitch import collision_radius_of
from hrn_pyg.sim import sleeping
from hrn_pyg.sim.rules import StepRules, step_rules
from hrn_pyg.sim.sleeping import DEFAULT_SLEEP, SleepConfig
from hrn_pyg.sim.step import MasksFn, Step, hierarchy_constants, object_of, require_state, step
from hrn_pyg.utils.checks import check_finite

#: the skin of a rollout's collision list (:func:`verlet_search`), in collision radii: a leaf may
#: move a quarter radius before the list is searched again
VERLET_SKIN = 0.5


def check_forces(graph: HeteroData, steps: int, forces: Tensor | None) -> None:
    """Raise ValueError unless ``steps >= 1`` and ``forces`` is None or a finite
    ``[steps' >= steps, N, 3]`` tensor for the ``N`` nodes of ``graph``."""
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    n = graph[NODE].num_nodes
    if forces is not None and (forces.dim() != 3 or forces.shape[0] < steps or forces.shape[1:] != (n, 3)):
        raise ValueError(f"forces must be [steps>={steps}, {n}, 3], got {tuple(forces.shape)}")
    if forces is not None:
        check_finite("forces", forces[:steps])


def iterate(
    model: HRN,
    graph: HeteroData,
    steps: int,
    forces: Tensor | None = None,
    masks_fn: MasksFn | None = None,
    sleep: SleepConfig | None = DEFAULT_SLEEP,
    effects: SceneEffects | None = None,
    hold_failed: bool = False,
) -> Iterator[Step]:
    """Feed the model its own predictions for ``steps`` steps, yielding each :class:`Step`.

    The start graph's collision edges are recomputed at the model's radius first. ``forces``
    ``[steps, N, 3]``: the force of each step (None: none). ``masks_fn(t, graph)``: dropout masks of
    step ``t`` (None: deterministic), seeing the whole graph. ``sleep``: objects at rest sleep
    (:data:`~hrn_pyg.sim.sleeping.DEFAULT_SLEEP`); None runs every object at every step (as
    training and ``hrn-pyg evaluate`` do). ``effects``: what the scene needs
    (:class:`~hrn_pyg.data.effects.SceneEffects`; None: what the data show). The model's rules
    after the network (:mod:`hrn_pyg.sim.rules`) are made once and applied every step.
    ``hold_failed``: a batch copy whose prediction is not finite is held and the others go on
    (``Step.failed``); else it is an error. Arguments are checked on the call; the steps run as
    they are taken.
    """
    check_forces(graph, steps, forces)
    plan = plan_effects(graph, steps, forces, effects)
    store = graph[NODE]
    radius = collision_radius_of(model.config, graph) if plan.collisions else None
    require_state(graph)  # once here, so no step has to
    graph = set_state(graph, store.prev_prev_pos, store.prev_pos, store.pos, radius=radius)
    # the tree does not change during a rollout: its objects are found once (one host read)
    sleeper = sleeping.Sleeper.start(sleep, graph) if sleep is not None and sleep.enabled else None
    if sleeper is not None:
        objects = sleeper.objects.of_node, sleeper.objects.count
    else:
        objects = object_of(graph) if model.config.rigid_fit else None
    # what every step is told rather than finds out: inputs checked here, the objects, the plan
    options = StepOptions(check=False, objects=objects, collisions=plan.collisions)
    # the rules after the network (cloth clearance, the energy limit, failed copies held), made once
    options = replace(options, rules=step_rules(model, graph, objects, hold_failed, plan.collisions))
    search = None
    if sleeper is None:  # every step runs on the whole graph: its hierarchy's constants are found once
        options = replace(options, hierarchy=hierarchy_constants(model, graph))
        search = verlet_search(radius)
    return _steps(model, graph, steps, forces, masks_fn, plan, sleeper, options, search)


def verlet_search(radius: float | Tensor | None, skin: float = VERLET_SKIN) -> VerletSearch | None:
    """The collision search of a rollout's steps: a :class:`~hrn_pyg.data.candidates.VerletSearch`
    with a skin of ``skin`` radii, which gives each step the edges of a search; None (every step
    searches) without collisions or with one radius per graph of a batch."""
    if radius is None or isinstance(radius, Tensor) or not radius > 0:
        return None
    return VerletSearch(radius, skin * radius)


def _steps(model: HRN, graph: HeteroData, steps: int, forces: Tensor | None, masks_fn: MasksFn | None,
           plan: EffectPlan, sleeper: sleeping.Sleeper | None, options: StepOptions,
           search: VerletSearch | None = None) -> Iterator[Step]:
    """The loop of :func:`iterate`, from its prepared start; ``options`` are every step's, less
    the plan's ``force_active`` of the step; ``search`` finds the collision edges of a step
    without sleeping (None: each step searches)."""
    no_force = torch.zeros_like(graph[NODE].pos) if forces is None else None
    for t in range(steps):  # time steps; each step is vectorised over particles
        force = forces[t] if forces is not None else no_force
        masks = masks_fn(t, graph) if masks_fn is not None else None
        step_options = replace(options, force_active=plan.force_active[t])
        if sleeper is not None:
            result = sleeper.step(model, graph, force, masks, step_options)
        else:
            result = step(model, graph, force, masks, step_options, search=search)
        if isinstance(options.rules, StepRules) and options.rules.hold_failed:
            result = result._replace(failed=options.rules.failed)
        yield result
        graph = result.graph


def unroll(
    model: HRN,
    graph: HeteroData,
    steps: int,
    forces: Tensor | None = None,
    masks_fn: MasksFn | None = None,
    sleep: SleepConfig | None = DEFAULT_SLEEP,
    effects: SceneEffects | None = None,
    hold_failed: bool = False,
) -> list[Step]:
    """Every :class:`Step` of :func:`iterate` (same arguments), in order."""
    return list(iterate(model, graph, steps, forces, masks_fn, sleep, effects, hold_failed))


def rollout(
    model: HRN,
    graph: HeteroData,
    steps: int,
    forces: Tensor | None = None,
    masks_fn: MasksFn | None = None,
    sleep: SleepConfig | None = DEFAULT_SLEEP,
    effects: SceneEffects | None = None,
) -> Tensor:
    """Positions of all nodes over ``steps`` predicted steps, ``[steps, N, 3]``
    (``x_{t+1..t+steps}``). See :func:`iterate` for the arguments."""
    return torch.stack([s.pos for s in iterate(model, graph, steps, forces, masks_fn, sleep, effects)])
