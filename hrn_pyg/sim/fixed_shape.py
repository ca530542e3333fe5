"""A rollout whose steps have fixed shapes: no host read inside a step, capturable as a CUDA graph.

:func:`hrn_pyg.sim.rollout.iterate` waits for the device several times a step (the collision
search's counts, the pushed leaves, the NaN check); on a GPU each wait stalls the launch queue.
:func:`fixed_shape_rollout` gives the same positions with none of them inside a step:

- collision pairs come from a list with a skin (:mod:`hrn_pyg.data.candidates`), searched again
  only when a leaf has moved half the skin; each step weighs the pairs closer than the radius
  by 1, the others by 0;
- the force module runs on every row (``dense``); whether a step has a force comes from the
  rollout's :class:`~hrn_pyg.data.effects.EffectPlan`;
- the step returns a small report on the device (how far its input moved since the search, how
  far its output moves, whether it is finite).

The rollout runs up to ``check_every`` steps ahead, then reads all their reports at once. Steps
up to the first whose input moved past the list's limit are kept (a non-finite one raises);
from there the list is searched anew and the steps rerun with the same masks. So the result is
the plain rollout's (sleeping off), whatever the skin. How far to run ahead is predicted from
the last report.

``cuda_graph=True`` (CUDA) records each kind of step (force or not, each padded list size) once
and replays it. ``compile=True`` compiles each kind with ``torch.compile``, the list's length
dynamic; positions equal the eager step's up to rounding.

**Failed copies.** With ``hold_failed`` (as :func:`hrn_pyg.sim.rollout.iterate` takes it; the
sampler sets it) a batch copy whose prediction is not finite is held at :math:`x_t` with zero
velocity, on the device (before the rules and after them), and the rollout records the step it
failed at (:attr:`FixedShapeRollout.failed_at`); the other copies go on. Without it a non-finite
step is an error, as in the plain rollout.

**Rules that read the contacts.** The clearance (``cloth_clearance``, ``solid_clearance``) and
static friction (``rest_friction``) decide from the step's contacts which leaves move, so their
sizes are not fixed. With them the step is split: the network (and what it decodes) runs as the
fixed-shape part, compiled with ``compile=True``, and every rule of the model
(:mod:`hrn_pyg.sim.rules`, in its order) runs after it eagerly, on the collision edges of
:math:`x_t` taken from the candidate list, so the positions are still the plain rollout's. Such a
step reads the host, so it cannot be recorded as a CUDA graph (``cuda_graph=True`` refuses it).
"""

from __future__ import annotations

import copy
import types
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import NamedTuple

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.data.candidates import (
    CollisionCandidates,
    active_collisions,
    build_candidates,
    collisions_of,
    largest_move,
    move_limit,
    pad_candidates,
    padded_size,
)
from hrn_pyg.data.effects import SceneEffects, plan_effects
from hrn_pyg.data.graph import COLLISION, NODE, set_state
from hrn_pyg.nn.hrn import HRN, StepOptions
from hrn_pyg.nn.pitch import collision_radius_of
from hrn_pyg.sim.rules import StepRules, step_rules
from hrn_pyg.sim.rollout import check_forces
from hrn_pyg.sim.step import (NEXT_POS, MasksFn, Prediction, held_at_current, hierarchy_constants,
                              non_finite_copies, object_of, predict, require_state)
from hrn_pyg.utils.checks import non_finite_error


@dataclass(frozen=True)
class FixedShapeConfig:
    """How :func:`fixed_shape_rollout` trades searches against repeated steps.

    Attributes:
        skin: the candidate list's skin, a fraction of the collision radius (larger: rarer searches,
            more pairs per step).
        check_every: most steps run before the reports are read (one host read each time).
        cuda_graph: record each kind of step as a CUDA graph and replay it (CUDA only).
        compile: compile each kind of step with ``torch.compile``; the guards check only the inputs
            and torch's global state (:func:`step_input_guards`), so the model and the static graph
            must not be replaced (their weights may change).
    """

    skin: float = 0.5
    check_every: int = 8
    cuda_graph: bool = False
    compile: bool = False

    def __post_init__(self) -> None:
        if not self.skin > 0:
            raise ValueError(f"FixedShapeConfig.skin must be > 0, got {self.skin}")
        if self.check_every < 1:
            raise ValueError(f"FixedShapeConfig.check_every must be >= 1, got {self.check_every}")


class FixedShapeRollout(NamedTuple):
    """Result of :func:`fixed_shape_rollout`.

    Attributes:
        pos: ``[steps, N, 3]`` positions ``x_{t+1..t+steps}``, as :func:`hrn_pyg.sim.rollout.rollout`.
        searches: collision searches made (the first included; 0 without collisions).
        host_reads: reads of the step flags.
        repeated_steps: steps run again after a stale list was found.
        failed_at: ``[B]`` long, the step at which each batch copy's prediction first was not
            finite (``steps``: never), with ``hold_failed``; else None.
    """

    pos: Tensor
    searches: int
    host_reads: int
    repeated_steps: int
    failed_at: Tensor | None = None


#: ``(pos, prev, prev_prev, force, masks, edge_index, valid, reference) -> (next_pos, since, report)``,
#: ``since`` the next state's ``x_t`` (``pos``, or where the ground lift moved it: a
#: :class:`~hrn_pyg.sim.step.Prediction`'s ``prev_pos``), report ``[3]``: input's largest move
#: since the search, output's largest move, output not finite; then, when failed copies are held,
#: ``[B]`` more: 1 for each batch copy held this step
StepFn = Callable[..., tuple[Tensor, Tensor, Tensor]]

#: ``(copy of each node [N] long, B)``: the batch copies whose failures a step holds
Copies = tuple[Tensor, int]

#: the predicted moves are scaled by this before the look-ahead is chosen (motion speeds up)
SPEED_MARGIN = 1.25


def make_network_step(model: HRN, graph: HeteroData, options: StepOptions, radius: float, skin: float,
                      mask_names: tuple[str, ...], copies: Copies | None = None) -> Callable[..., tuple]:
    """The fixed-shape part of a step: the arguments of :func:`make_step` to the
    :class:`~hrn_pyg.sim.step.Prediction` (``options.rules`` applied, which must need no host read),
    the 0-d largest move of the input since the search (0 without collisions) and, with
    ``copies``, the ``[B]`` bool copies held as failed (else None)."""
    options = replace(options, check=False, fixed_shape=True)

    def network_step(pos: Tensor, prev: Tensor, prev2: Tensor, force: Tensor, masks: tuple[Tensor, ...],
                     edge_index: Tensor, valid: Tensor, reference: Tensor) -> tuple:
        current = graph_at(graph, pos, prev, prev2, edge_index)
        return _network_part(model, current, options, radius, skin, mask_names, force, masks, valid, reference,
                             copies)

    return network_step


def _network_part(model: HRN, current: HeteroData, options: StepOptions, radius: float, skin: float,
                  mask_names: tuple[str, ...], force: Tensor, masks: tuple[Tensor, ...], valid: Tensor,
                  reference: Tensor, copies: Copies | None) -> tuple:
    """:func:`make_network_step`'s step on ``current`` (the graph at :math:`x_t` with the candidates
    as its collision edges): called after :func:`graph_at`, so a compiled step breaks its graph
    only there."""
    pos = current[NODE].pos
    weight, moved = None, pos.new_zeros(())
    if radius > 0:
        candidates = CollisionCandidates(current[COLLISION].edge_index, valid, reference, radius, skin, -1)
        weight, moved = active_collisions(candidates, pos), largest_move(candidates, pos)
    prediction = predict(model, current, force, dict(zip(mask_names, masks)) or None,
                         replace(options, collision_weight=weight))
    failed = None
    if copies is not None:
        prediction, failed = held_failed_copies(current, prediction, copies)
    if options.rules is not None:
        prediction = options.rules(current, prediction, force, None)
        if copies is not None:  # what the rules made, too
            prediction, more = held_failed_copies(current, prediction, copies)
            failed = failed | more
    return prediction, moved, failed


def held_failed_copies(graph: HeteroData, prediction: Prediction, copies: Copies) -> tuple[Prediction, Tensor]:
    """``prediction`` with every batch copy that has a non-finite row held at :math:`x_t` (zero
    velocity, :func:`~hrn_pyg.sim.step.held_at_current`), and ``[B]`` bool: which copies were;
    no host read."""
    copy, count = copies
    bad = non_finite_copies(prediction.pos, copy, count)
    return held_at_current(graph, prediction, bad[copy]), bad


def step_report(pos: Tensor, prediction: Prediction, moved: Tensor,
                failed: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """A step's outputs from its input ``pos`` ``[N, 3]`` and final ``prediction``: next
    positions, the next state's :math:`x_t` and the report (:data:`StepFn`; ``failed`` ``[B]``
    bool the copies held, or None)."""
    next_pos = prediction.pos
    step = next_pos - pos
    speed = (step * step).sum(dim=-1).amax().sqrt()
    bad = (~torch.isfinite(next_pos).all()).to(pos.dtype)
    since = pos if prediction.prev_pos is None else prediction.prev_pos
    report = torch.stack([moved, torch.nan_to_num(speed, nan=float("inf")), bad])
    if failed is not None:
        report = torch.cat([report, failed.to(pos.dtype)])
    return next_pos, since, report


def make_step(model: HRN, graph: HeteroData, options: StepOptions, radius: float, skin: float,
              mask_names: tuple[str, ...], copies: Copies | None = None) -> StepFn:
    """The step of :func:`fixed_shape_rollout` as a function of tensors only (no host read): positions,
    force, masks (in ``mask_names`` order) and candidates come in as tensors, so it can be recorded
    once and replayed. It runs ``options`` with ``check=False``, ``fixed_shape=True`` and the
    candidates' weights; with ``copies`` it holds failed copies (:func:`held_failed_copies`)."""
    options = replace(options, check=False, fixed_shape=True)

    def fixed_step(pos: Tensor, prev: Tensor, prev2: Tensor, force: Tensor, masks: tuple[Tensor, ...],
                   edge_index: Tensor, valid: Tensor, reference: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        current = graph_at(graph, pos, prev, prev2, edge_index)
        prediction, moved, failed = _network_part(model, current, options, radius, skin, mask_names, force,
                                                  masks, valid, reference, copies)
        return step_report(pos, prediction, moved, failed)

    return fixed_step


def rules_after(network_step: Callable[..., tuple], rules: StepRules, graph: HeteroData,
                radius: float, skin: float, copies: Copies | None = None) -> StepFn:
    """A :data:`StepFn` that runs ``network_step`` (:func:`make_network_step`, compiled or not) and
    then ``rules`` eagerly on the graph at :math:`x_t` with its collision edges (the candidates
    within the radius, as the plain rollout's search gives them): the split step of the module
    docstring. It reads the host. With ``copies`` what the rules make is checked too."""

    def step(pos: Tensor, prev: Tensor, prev2: Tensor, force: Tensor, masks: tuple[Tensor, ...],
             edge_index: Tensor, valid: Tensor, reference: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        prediction, moved, failed = network_step(pos, prev, prev2, force, masks, edge_index, valid, reference)
        edges = edge_index
        if radius > 0:
            edges = collisions_of(CollisionCandidates(edge_index, valid, reference, radius, skin, -1), pos)
        current = graph_at(graph, pos, prev, prev2, edges)
        prediction = rules(current, prediction, force, None)
        if copies is not None:
            prediction, more = held_failed_copies(current, prediction, copies)
            failed = failed | more
        return step_report(pos, prediction, moved, failed)

    return step


#: the arguments of a step function (:func:`make_step`): what changes from one call to the next
STEP_INPUTS = frozenset({"pos", "prev", "prev2", "force", "masks", "edge_index", "valid", "reference"})
#: guards on torch's global state (grad mode, default device, ...) and on symbolic sizes
GLOBAL_GUARDS = frozenset({"GRAD_MODE", "GLOBAL_STATE", "DEFAULT_DEVICE", "DETERMINISTIC_ALGORITHMS",
                           "TORCH_FUNCTION_STATE", "AUTOGRAD_SAVED_TENSORS_HOOKS", "SHAPE_ENV"})


def step_input_guards(entries: list) -> list[bool]:
    """The ``guard_filter_fn`` of a compiled step: keep the guards on its arguments
    (:data:`STEP_INPUTS`) and torch's global state (:data:`GLOBAL_GUARDS`); drop those on the model,
    the static graph and the package's functions, which the simulator holds fixed (about a thousand
    guards, 5 % of a step on a pile of 10 objects)."""
    return [e.guard_type in GLOBAL_GUARDS or e.name.split("[")[0].split(".")[0] in STEP_INPUTS for e in entries]


def own_code(fn: StepFn) -> StepFn:
    """``fn`` with a code object of its own, so each simulator's kinds of step have their own
    ``torch._dynamo.config.recompile_limit`` (compiled graphs are kept per code object)."""
    return types.FunctionType(fn.__code__.replace(), fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)


@torch.compiler.disable
def graph_at(graph: HeteroData, pos: Tensor, prev: Tensor, prev2: Tensor, edge_index: Tensor) -> HeteroData:
    """A shallow copy of ``graph`` at ``x_t, x_{t-1}, x_{t-2}`` with collision candidates
    ``edge_index`` (no tensor computed)."""
    current = copy.copy(graph)
    store = current[NODE]
    store.pos, store.prev_pos, store.prev_prev_pos = pos, prev, prev2
    current[COLLISION].edge_index = edge_index
    return current


class RecordedStep:
    """A :data:`StepFn` recorded as a CUDA graph: inputs are copied into fixed buffers, the graph
    is replayed, and the outputs are copied out of its buffers (CUDA only)."""

    def __init__(self, fn: StepFn, example: tuple) -> None:
        self.inputs = [self._clone(a) for a in example]
        stream = torch.cuda.Stream()
        stream.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(stream):  # warm-up off the default stream, as recording needs
            for _ in range(2):
                fn(*self.inputs)
        torch.cuda.current_stream().wait_stream(stream)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):
            self.outputs = fn(*self.inputs)

    @staticmethod
    def _clone(value):
        return tuple(v.clone() for v in value) if isinstance(value, tuple) else value.clone()

    def __call__(self, *args) -> tuple[Tensor, Tensor, Tensor]:
        for buffer, value in zip(self.inputs, args):
            if isinstance(buffer, tuple):
                for b, v in zip(buffer, value):
                    b.copy_(v)
            else:
                buffer.copy_(value)
        self.graph.replay()
        return tuple(o.clone() for o in self.outputs)


def contact_rule_options(model: HRN) -> str:
    """The model's options of rules that read the step's contacts, as ``name=value, ...``."""
    names = ("cloth_clearance", "solid_clearance", "rest_friction")
    return ", ".join(f"{name}={float(getattr(model.config, name, 0.0)):g}" for name in names
                     if float(getattr(model.config, name, 0.0)) > 0)


def _steps_within(limit: float, moved: float, speed: float, most: int) -> int:
    """How many more steps (at most ``most``) keep a node that has ``moved`` and moves ``speed``
    per step (times :data:`SPEED_MARGIN`) within ``limit``; 0: search now."""
    if speed <= 0:
        return most
    return max(0, min(most, int((limit - moved) // (SPEED_MARGIN * speed))))


class FixedShapeSimulator:
    """A model and one scene at its start state, with the steps of :func:`fixed_shape_rollout` kept
    between rollouts (each kind recorded or compiled once); every :meth:`rollout` starts there."""

    def __init__(self, model: HRN, graph: HeteroData, config: FixedShapeConfig = FixedShapeConfig(),
                 hold_failed: bool = False) -> None:
        require_state(graph)
        store = graph[NODE]
        self.model, self.config = model, config
        # the batch copy of every node, for holding failed copies (module docstring)
        self.copies: Copies | None = None
        if hold_failed:
            copy_of = store.batch if "batch" in store else torch.zeros(store.num_nodes, dtype=torch.long,
                                                                      device=store.pos.device)
            self.copies = (copy_of, int(copy_of.max()) + 1 if copy_of.numel() else 1)
        self.graph = set_state(graph, store.prev_prev_pos, store.prev_pos, store.pos, radius=None)
        self.objects = object_of(self.graph) if model.config.rigid_fit else None
        rules = step_rules(model, self.graph, self.objects)
        # rules that read the contacts run after the fixed-shape part (module docstring); without
        # them the energy limit runs inside it, on every row, the unchanged ones selected
        self.host_rules = rules if rules is not None and (rules.cloth is not None or rules.rest_friction > 0) else None
        if self.host_rules is not None and config.cuda_graph:
            raise ValueError(f"fixed_shape_rollout: this model's rules read the step's contacts "
                             f"({contact_rule_options(model)}), which a CUDA graph cannot hold; use "
                             "FixedShapeConfig(compile=True) or hrn_pyg.sim.rollout")
        if config.cuda_graph and store.pos.device.type != "cuda":
            raise ValueError("FixedShapeConfig.cuda_graph needs the graph on a CUDA device")
        self.rules = None if rules is None or self.host_rules is not None else StepRules(
            None, rules.energy, rules.objects, rules.rigid_from_rest, host_reads=False)
        self.hierarchy = hierarchy_constants(model, self.graph)
        self._steps: dict[tuple, StepFn] = {}

    def _step_fn(self, force_active: bool, names: tuple[str, ...], radius: float, size: int, example: tuple) -> StepFn:
        # a recorded CUDA graph has the sizes it was recorded with; a compiled step takes any list size
        key = (force_active, names, radius, size if self.config.cuda_graph else None)
        if key not in self._steps:
            options = StepOptions(force_active=force_active, objects=self.objects, hierarchy=self.hierarchy,
                                  rules=self.rules)
            skin = self.config.skin * radius
            if self.host_rules is None:
                fn = make_step(self.model, self.graph, options, radius, skin, names, self.copies)
                if self.config.compile:
                    fn = torch.compile(own_code(fn), dynamic=None, options={"guard_filter_fn": step_input_guards})
            else:
                network = make_network_step(self.model, self.graph, options, radius, skin, names, self.copies)
                if self.config.compile:
                    network = torch.compile(own_code(network), dynamic=None,
                                            options={"guard_filter_fn": step_input_guards})
                fn = rules_after(network, self.host_rules, self.graph, radius, skin, self.copies)
            self._steps[key] = RecordedStep(fn, example) if self.config.cuda_graph else fn
        return self._steps[key]

    def rollout(self, steps: int, forces: Tensor | None = None, masks_fn: MasksFn | None = None,
                effects: SceneEffects | None = None) -> FixedShapeRollout:
        """``steps`` steps from the start state; the arguments are those of
        :func:`~hrn_pyg.sim.rollout.iterate` (see :func:`fixed_shape_rollout`)."""
        graph, config = self.graph, self.config
        check_forces(graph, steps, forces)
        plan = plan_effects(graph, steps, forces, effects)
        store = graph[NODE]
        radius = collision_radius_of(self.model.config, graph) if plan.collisions else 0.0
        if isinstance(radius, Tensor):
            raise ValueError("fixed_shape_rollout: the batch mixes graphs of different voxel pitches, whose "
                             "collision radii differ; roll each pitch out on its own (or use hrn_pyg.sim.rollout)")
        skin = config.skin * radius
        zero_force = torch.zeros_like(store.pos)
        empty_edges = torch.zeros(2, 0, dtype=torch.long, device=store.pos.device)
        no_valid = torch.zeros(0, dtype=torch.bool, device=store.pos.device)
        mask_cache: dict[int, Mapping[str, Tensor] | None] = {}

        def masks_of(t: int, state: tuple[Tensor, Tensor, Tensor]) -> Mapping[str, Tensor] | None:
            if masks_fn is None:
                return None
            if t not in mask_cache:
                shown = copy.copy(graph)
                shown[NODE].prev_prev_pos, shown[NODE].prev_pos, shown[NODE].pos = state
                mask_cache[t] = masks_fn(t, shown)
            return mask_cache[t]

        state = (store.prev_prev_pos, store.prev_pos, store.pos)  # x_{t-2}, x_{t-1}, x_t
        out: list[Tensor] = []
        failed_at = [steps] * (self.copies[1] if self.copies is not None else 0)
        searches = reads = repeated = 0
        candidates: CollisionCandidates | None = None
        limit = move_limit(skin)
        # the fastest node's last move: from the start state once, then from each read
        speed = float((state[2] - state[1]).norm(dim=-1).amax()) if radius > 0 else 0.0
        ahead = config.check_every
        with torch.no_grad():
            while len(out) < steps:
                t0 = len(out)
                fresh = radius > 0 and candidates is None
                if fresh:
                    candidates = build_candidates(graph, state[2], radius, skin)
                    if config.cuda_graph:  # pad to a size that rarely changes, so recordings are reused
                        candidates = pad_candidates(candidates, padded_size(candidates.pairs))
                    searches += 1
                    ahead = _steps_within(limit, 0.0, speed, config.check_every) + 1  # its first step moved 0
                edges = candidates.edge_index if candidates is not None else empty_edges
                valid = candidates.valid if candidates is not None else no_valid
                reference = candidates.reference if candidates is not None else state[2]
                trial, reports, s = [], [], state
                for t in range(t0, min(t0 + ahead, steps)):
                    masks = masks_of(t, s)
                    names = tuple(sorted(masks)) if masks else ()
                    force = forces[t] if forces is not None else zero_force
                    args = (s[2], s[1], s[0], force, tuple(masks[n] for n in names), edges, valid, reference)
                    nxt, since, report = self._step_fn(plan.force_active[t], names, radius, edges.size(1), args)(*args)
                    trial.append((since, nxt))
                    reports.append(report)
                    s = (s[1], since, nxt)
                read = torch.stack(reports).cpu().tolist()  # the one host read of these steps
                reads += 1
                kept = len(trial)
                for j, (moved, _, bad, *held) in enumerate(read):
                    if radius > 0 and moved > limit:
                        kept = j
                        break
                    if bad:
                        raise non_finite_error(NEXT_POS)
                    for b, flag in enumerate(held):  # copies held as failed at step t0 + j
                        if flag and failed_at[b] == steps:
                            failed_at[b] = t0 + j
                for since, nxt in trial[:kept]:
                    state = (state[1], since, nxt)
                    out.append(nxt)
                for t in range(t0, t0 + kept):
                    mask_cache.pop(t, None)
                if kept < len(trial):  # the list went stale at step t0 + kept: search again from there
                    if kept == 0 and fresh:  # cannot happen with finite positions; never loop
                        raise RuntimeError("fixed_shape_rollout: a fresh candidate list is stale")
                    repeated += len(trial) - kept
                    candidates = None
                if radius > 0 and kept > 0:  # how many steps the list should still last, at the last speed
                    moved, speed = read[kept - 1][:2]
                    ahead = _steps_within(limit, moved, speed, config.check_every)
                    if ahead == 0:
                        candidates = None
        failed = None if self.copies is None else torch.tensor(failed_at, dtype=torch.long, device=store.pos.device)
        return FixedShapeRollout(torch.stack(out), searches, reads, repeated, failed)


def fixed_shape_rollout(
    model: HRN,
    graph: HeteroData,
    steps: int,
    forces: Tensor | None = None,
    masks_fn: MasksFn | None = None,
    effects: SceneEffects | None = None,
    config: FixedShapeConfig = FixedShapeConfig(),
    hold_failed: bool = False,
) -> FixedShapeRollout:
    """The positions of :func:`hrn_pyg.sim.rollout.rollout` with ``sleep=None``, from fixed-shape steps
    (module docstring); inference only, the arguments of :func:`~hrn_pyg.sim.rollout.iterate`.
    ``masks_fn(t, graph)`` sees the graph without collision edges. ``hold_failed``: a batch copy
    whose prediction is not finite is held and the others go on
    (:attr:`FixedShapeRollout.failed_at`); else it is an error. To roll one scene out several
    times, keep a :class:`FixedShapeSimulator`."""
    return FixedShapeSimulator(model, graph, config, hold_failed).rollout(steps, forces, masks_fn, effects)
