"""The learned HRN as the environment's physics: :class:`HRNDynamics`.

A task scene (``cube_push`` or ``tower``) is drawn from a pool of pybullet initial states, one
per seed, so that an episode in the learned environment can be replayed in pybullet from the
very same start. The flattened per-environment state is

.. code-block:: text

    [ x_{t-2} (L*3) | x_{t-1} (L*3) | x_t (L*3) | still (R) | asleep (R) | pool index (1) ]

leaf positions (ancestors are derived, collision edges recomputed, exactly as in every other
rollout, :func:`hrn_pyg.sim.step.step`) and each of the scene's ``R`` objects' sleep state
(:class:`~hrn_pyg.sim.sleeping.SleepState`: consecutive still steps, asleep 0 or 1), carried
from step to step as a sleeping rollout carries it. A still count of -1 stands for the state the
history implies (:func:`~hrn_pyg.sim.sleeping.state_from_history`), where a sleeping rollout
starts: a reset state and a state made from positions alone (:meth:`HRNDynamics.state_of`) hold
it. One call of :meth:`HRNDynamics.sample_next`
steps ``B`` environments times ``k`` samples as one batched graph, each copy with its own
dropout masks (one per step per copy, the seed paper's graph-convolutional dropout).

Each pool entry's graph is built as an episode's (:func:`hrn_pyg.data.graph.episode_structure`),
so the environment steps a scene exactly as a rollout from the same pybullet start does. Speed:
the entries share one hierarchy, so the batched graph is collated once per copy count and only
the masses and rest shapes are gathered per step; at rate 0 the ``k`` samples are one prediction
repeated; a step is one :func:`hrn_pyg.sim.sleeping.predict_held` without the next graph's
collision search (the next call builds its graph from the new state).
"""

from __future__ import annotations

import copy
import hashlib
import os
from collections import OrderedDict
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor
from torch_geometric.data import Batch, HeteroData

from hrn_pyg.checkpoints import load_model
from hrn_pyg.checkpoints.domain import frames_domain, merge_all, report_outside
from hrn_pyg.data.graph import HISTORY, NODE, episode_structure, object_centres, set_state
from hrn_pyg.data.hierarchy import start_hierarchy
from hrn_pyg.nn.hrn import HRN, StepOptions
from hrn_pyg.nn.pitch import collision_radius_of
from hrn_pyg.rl.dynamics import ROOT_DIM
from hrn_pyg.rl.tasks import TaskConfig, get_task
from hrn_pyg.sampling.sample import draw_masks, model_device
from hrn_pyg.sim.rules import step_rules
from hrn_pyg.sim.sleeping import (
    DEFAULT_SLEEP,
    Objects,
    SleepConfig,
    SleepState,
    holds_movable,
    objects,
    predict_held,
    state_from_history,
    update,
)
from hrn_pyg.utils.checks import check_count, check_rate

#: seeds of the initial-state pool; far from the generated datasets' seeds (0..199), so the
#: agent starts from scenes the model never saw in training
POOL_SEEDS = tuple(range(10_000, 10_064))
#: seeds of validation scenes, apart from the training pool and the datasets: settings such as a
#: task's dropout rate and goal tolerance are chosen on them (:mod:`experiments.rl.partial_hits`)
VALIDATION_SEEDS = tuple(range(20_000, 20_032))
#: batched static graphs kept (one per copy count: training batch x k, the same at rate 0 with
#: k = 1, evaluation batches); a handful covers every count one PPO run uses
BATCH_CACHE_SIZE = 8


class HRNDynamics:
    """:class:`~hrn_pyg.rl.dynamics.StochasticDynamics` backed by a trained :class:`HRN`.

    Dropout masks are sampled for every module the model takes them on (so the random stream
    does not depend on the task) and applied only on :attr:`dropout_modules`: the task's, or,
    for a model calibrated by ``hrn-pyg calibrate`` (config ``dropout_rate > 0``), the modules
    its rate was chosen for. :attr:`calibrated_rate` is that rate (None: never calibrated); the
    PPO trainer uses it when no rate is given.

    Args:
        model: the trained HRN (its normaliser fitted); put in eval mode. Uncalibrated, it must
            take dropout on every module of ``task.dropout_modules``.
        task: the task (its ``name`` is the pybullet scene).
        pool_seeds: pybullet seeds of the initial states :meth:`reset_states` draws from.
        strict: a task scene outside the domain the model was trained on
            (:mod:`hrn_pyg.checkpoints.domain`) raises :class:`~hrn_pyg.checkpoints.domain.DomainError`;
            otherwise that is one line on stderr.

    The pool, the structures and every state live on the model's device (:attr:`device`);
    the pybullet pool is built on the CPU and moved there once.

    **Shapes:** states ``(B, 9 L + 2 R + 1)`` (``R`` objects, static ones included); roots
    ``(..., O, 6)``; forces ``(B, O, 3)`` Newton, one per object, spread evenly over its leaves
    (the datasets' convention).
    """

    object_dim = ROOT_DIM

    def __init__(self, model: HRN, task: str | TaskConfig, pool_seeds: Sequence[int] = POOL_SEEDS,
                 sleep: SleepConfig | None = DEFAULT_SLEEP, strict: bool = False) -> None:
        # pybullet only where a pool is built
        from hrn_pyg.data.scene_file import make_scene, scene_spec

        self.task = get_task(task)
        #: objects at rest sleep (:func:`hrn_pyg.sim.sleeping.state_from_history`); None: all awake
        self.sleep = sleep if sleep is not None and sleep.enabled else None
        self._objects: dict[int, Objects] = {}
        self.model = model.eval()
        #: the model's calibrated sampling rate (config ``dropout_rate``), None when it has none
        self.calibrated_rate = float(model.config.dropout_rate) if model.config.dropout_rate > 0 else None
        #: masked modules: a calibrated model's own (its rate was chosen for them), else the task's
        self.dropout_modules = tuple(model.config.dropout_modules if self.calibrated_rate is not None
                                     else self.task.dropout_modules)
        missing = set(self.dropout_modules) - set(model.config.dropout_modules)
        if missing:
            raise ValueError(f"the model takes no dropout on {sorted(missing)}, which task "
                             f"{self.task.name!r} samples on")
        if not pool_seeds:
            raise ValueError("pool_seeds must not be empty")
        histories, masses = [], []
        leaf_object = None
        for seed in pool_seeds:  # a few dozen scenes, built once
            scene = make_scene(self.task.scene_name, int(seed))
            try:
                frames = [scene.reset()]
                for _ in range(HISTORY):
                    frames.append(scene.step(scene.zero_action()))
                histories.append(np.stack(frames))
                masses.append(np.asarray(scene.leaf_mass, dtype=np.float32))
                if leaf_object is None:
                    leaf_object = np.asarray(scene.leaf_object)
                    material = np.asarray(scene.object_material)
                    stiffness = np.asarray(scene.object_stiffness, dtype=np.float32)
            finally:
                scene.close()
        pitch = scene_spec(self.task.scene_name).config.pitch
        report_outside(model, merge_all(frames_domain(h, leaf_object, material, pitch) for h in histories),
                       strict=strict)
        self.device = device = model_device(model)
        pool = np.stack(histories).astype(np.float32)  # [P, 3, L, 3]
        leaf_mass = torch.from_numpy(np.stack(masses))  # [P, L]
        leaf_object_t = torch.as_tensor(leaf_object, dtype=torch.long)  # [L]
        self.num_leaves = int(leaf_object_t.numel())
        self.num_objects = int(self.task.num_objects)
        if int(leaf_object_t.max()) + 1 < self.num_objects:
            raise ValueError(f"scene {self.task.scene_name!r} has fewer objects than the task's {self.num_objects}")
        # every pool entry shares one hierarchy, the one an episode of the first pool scene is
        # given (its first frame's); each entry keeps its own masses and rest shape (its first
        # frame), so entry 0 is the very graph a rollout from that episode starts from
        parent = start_hierarchy(pool[0, 0], masses[0], leaf_object)
        self._structures = [
            episode_structure({"positions": pool[i], "leaf_mass": masses[i], "leaf_object": leaf_object,
                               "object_material": material, "object_stiffness": stiffness,
                               "hierarchy_parent": parent}, pitch=pitch).to(device)
            for i in range(len(pool_seeds))
        ]
        self.num_roots = objects(self._structures[0]).count
        self.state_dim = 9 * self.num_leaves + 2 * self.num_roots + 1
        self.pool_seeds = torch.tensor(list(pool_seeds), dtype=torch.long, device=device)
        self.pool = torch.from_numpy(pool).to(device)
        self.leaf_mass = leaf_mass.to(device)
        self.leaf_object = leaf_object_t.to(device)
        self._leaf_count = torch.bincount(self.leaf_object, minlength=self.num_objects).float()
        self._varying = _varying_node_attributes(self._structures)  # {name: [P, N, ...]}
        self._batched: OrderedDict[int, HeteroData] = OrderedDict()

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike, task: str | TaskConfig,
                        device: str | torch.device | None = None,
                        pool_seeds: Sequence[int] = POOL_SEEDS,
                        sleep: SleepConfig | None = DEFAULT_SLEEP, strict: bool = False) -> HRNDynamics:
        """The dynamics of a checkpoint's model (a path or a shipped model's name) on ``device``
        (None: the CPU)."""
        return cls(load_model(path, device), task, pool_seeds, sleep, strict)

    def __repr__(self) -> str:
        """Names the model by its weights (a digest), so a run's record says which model it used
        and a resumed run can tell whether it steps the same one."""
        return (f"{type(self).__name__}(task={self.task.name!r}, model={self.model!r}, "
                f"weights={weights_digest(self.model)}, pool={len(self.pool_seeds)} scenes, "
                f"dropout_modules={self.dropout_modules}, sleep={sleep_repr(self.sleep)})")

    # -- state layout -------------------------------------------------------------------------
    def _split(self, states: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(..., S)`` -> positions ``(..., 3, L, 3)``, sleep state ``(..., 2, R)`` (still, asleep)
        and pool index ``(...)`` long."""
        if states.shape[-1] != self.state_dim:
            raise ValueError(f"states must end in {self.state_dim}, got {tuple(states.shape)}")
        positions = 9 * self.num_leaves
        pos = states[..., :positions].reshape(*states.shape[:-1], 3, self.num_leaves, 3)
        sleep = states[..., positions:-1].reshape(*states.shape[:-1], 2, self.num_roots)
        return pos, sleep, states[..., -1].round().long()

    def _join(self, pos: Tensor, index: Tensor, sleep: Tensor | None = None) -> Tensor:
        """``sleep`` ``(..., 2, R)``; None: the state the history implies (a still count of -1)."""
        if sleep is None:
            sleep = pos.new_tensor([[-1.0], [0.0]]).expand(*index.shape, 2, self.num_roots)
        return torch.cat([pos.flatten(-3), sleep.flatten(-2), index.to(pos.dtype).unsqueeze(-1)], dim=-1)

    def leaf_history(self, states: Tensor) -> tuple[Tensor, Tensor]:
        """``(..., S)`` -> leaf positions ``(..., 3, L, 3)`` at ``t-2, t-1, t`` and pool index
        ``(...)`` long."""
        pos, _, index = self._split(states)
        return pos, index

    def state_of(self, leaf_pos: Tensor, index: Tensor) -> Tensor:
        """``(..., 3, L, 3)`` and ``(...)`` -> ``(..., S)``, with the sleep state the history
        implies: the inverse of :meth:`leaf_history` where the sleep state is that one."""
        return self._join(leaf_pos, index)

    def scene_seeds(self, states: Tensor) -> Tensor:
        """The pybullet seed each state's episode started from, ``(...)`` long."""
        return self.pool_seeds[self._split(states)[2]]

    # -- protocol -----------------------------------------------------------------------------
    def reset_states(self, batch: int, generator: torch.Generator) -> Tensor:
        index = torch.randint(len(self._structures), (batch,), generator=generator, device=generator.device)
        index = index.to(self.device)
        return self._join(self.pool[index], index)

    def roots(self, states: Tensor) -> Tensor:
        pos, _, index = self._split(states)  # [..., 3, L, 3], [...]
        mass = self.leaf_mass[index].unsqueeze(-2)  # [..., 1, L]: the same masses at every time
        centres = object_centres(pos[..., 1:, :, :], self.leaf_object, self.num_objects, mass)  # [..., 2, O, 3]
        centre_prev, centre_now = centres.unbind(-3)
        return torch.cat([centre_now, centre_now - centre_prev], dim=-1)

    @torch.no_grad()
    def sample_next(self, states: Tensor, forces: Tensor, k: int, rate: float,
                    generator: torch.Generator) -> Tensor:
        check_count(k, "k")
        check_rate(rate)
        B = states.shape[0]
        if forces.shape != (B, self.num_objects, 3):
            raise ValueError(f"forces must be ({B}, {self.num_objects}, 3), got {tuple(forces.shape)}")
        pos, sleep, index = self._split(states)  # [B, 3, L, 3], [B, 2, R], [B]
        # rate 0: the k samples are one deterministic prediction, made once per environment
        copies_per_env = k if rate > 0 else 1
        n = B * copies_per_env
        masks = None
        if rate > 0:  # one mask per copy on the masked modules only (cube_push: force)
            masks = {name: mask for name, mask in draw_masks(self.model, n, rate, generator).items()
                     if name in self.dropout_modules}
        leaf_pos = pos.repeat_interleave(copies_per_env, dim=0)  # [n, 3, L, 3]
        new_pos, new_sleep = self._advance(leaf_pos, index.repeat_interleave(copies_per_env),
                                           forces.repeat_interleave(copies_per_env, dim=0), masks,
                                           sleep.repeat_interleave(copies_per_env, dim=0))
        new_pos = new_pos.reshape(B, copies_per_env, 3, self.num_leaves, 3).expand(B, k, 3, self.num_leaves, 3)
        new_sleep = new_sleep.reshape(B, copies_per_env, 2, self.num_roots).expand(B, k, 2, self.num_roots)
        return self._join(new_pos, index[:, None].expand(B, k), new_sleep)

    def next_positions(self, leaf_pos: Tensor, index: Tensor, forces: Tensor,
                       masks: dict[str, Tensor] | None = None) -> Tensor:
        """One model step of ``n`` copies as one batched graph, differentiable in the positions
        and the forces (no ``no_grad`` here; :meth:`sample_next` wraps it).

        **Shapes:** leaf positions ``(n, 3, L, 3)`` at ``t-2, t-1, t``, pool indices ``(n,)``
        long, forces ``(n, O, 3)`` Newton, masks ``{module: (rows, hidden)}`` on the masked
        modules (:func:`~hrn_pyg.sampling.sample.draw_masks` of ``n`` copies; None: the
        deterministic model) -> leaf positions at ``t+1``, ``(n, L, 3)``.
        """
        return self.next_history(leaf_pos, index, forces, masks)[:, 2]

    def next_history(self, leaf_pos: Tensor, index: Tensor, forces: Tensor,
                     masks: dict[str, Tensor] | None = None) -> Tensor:
        """:meth:`next_positions` as the next step's history: leaf positions ``(n, 3, L, 3)`` at
        ``t-1, t, t+1``, where ``x_t`` is the one the next step reads its velocity from (moved by
        the ground lift when the model's lift is not a motion, ``HRNConfig.ground_lift_velocity``).
        The sleep state is the one the history implies (the planner's futures take it at every
        step; an episode's step, :meth:`sample_next`, carries its own)."""
        return self._advance(leaf_pos, index, forces, masks)[0]

    def _advance(self, leaf_pos: Tensor, index: Tensor, forces: Tensor, masks: dict[str, Tensor] | None,
                 sleep: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """:meth:`next_history` from the sleep state ``sleep`` ``(n, 2, R)`` (None, or a still
        count of -1: the one the history implies), and the sleep state after the step."""
        n = leaf_pos.shape[0]
        per_leaf = forces[:, self.leaf_object] / self._leaf_count[self.leaf_object, None]  # [n, L, 3]
        graph = self._batched_structure(index)
        graph = set_state(graph, leaf_pos[:, 0].reshape(-1, 3), leaf_pos[:, 1].reshape(-1, 3),
                          leaf_pos[:, 2].reshape(-1, 3), radius=collision_radius_of(self.model.config, graph),
                          force=per_leaf.reshape(-1, 3))
        objs = self._objects_of(graph, n)
        held, after = None, None
        if self.sleep is not None:  # the rule of hrn_pyg.sim.sleeping.sleeping_step
            state = state_from_history(self.sleep, graph, objs)
            if sleep is not None:
                still, asleep = sleep[:, 0].reshape(-1), sleep[:, 1].reshape(-1)
                known = still >= 0
                state = SleepState(asleep=torch.where(known, asleep > 0.5, state.asleep),
                                   still=torch.where(known, still.long(), state.still))
            state = update(self.sleep, state, graph, graph[NODE].force, objs)
            after = torch.stack([state.still.to(leaf_pos.dtype), state.asleep.to(leaf_pos.dtype)])
            after = after.reshape(2, n, self.num_roots).transpose(0, 1)
            held = state.asleep[objs.of_node]
            if not holds_movable(held, graph):
                held = None
        # every copy is pushed by its action: the force module runs (a zero row adds nothing)
        options = StepOptions(force_active=True, objects=(objs.of_node, objs.count))
        prediction = predict_held(self.model, graph, graph[NODE].force, masks, held, options)
        # the rules after the network, as every rollout applies them; a copy that fails is held
        rules = step_rules(self.model, graph, options.objects, hold_failed=True)
        if rules is not None:
            prediction = rules(graph, prediction, graph[NODE].force, None if held is None else ~held)
        leaf = graph[NODE].is_leaf
        since = (leaf_pos[:, 2] if prediction.prev_pos is None
                 else prediction.prev_pos[leaf].reshape(n, self.num_leaves, 3))
        if after is None:
            after = leaf_pos.new_tensor([[-1.0], [0.0]]).expand(n, 2, self.num_roots)
        history = torch.stack([leaf_pos[:, 1], since, prediction.pos[leaf].reshape(n, self.num_leaves, 3)], dim=1)
        return history, after

    def _objects_of(self, graph: HeteroData, n: int) -> Objects:
        """The :class:`~hrn_pyg.sim.sleeping.Objects` of a batched graph of ``n`` copies, found
        once per ``n`` (a host read) and cached."""
        objs = self._objects.get(n)
        if objs is None:
            objs = self._objects.setdefault(n, objects(graph))
        return objs

    def _batched_structure(self, copies: Tensor) -> HeteroData:
        """Pool entries ``copies`` ``[n]`` as one batched static graph (a shallow copy).

        The collated graph of ``n`` copies of entry 0 is cached per ``n``; the attributes that
        differ between entries are overwritten with each copy's own.
        """
        n = int(copies.numel())
        cached = self._batched.get(n)
        if cached is None:
            cached = Batch.from_data_list([self._structures[0]] * n)
            self._batched[n] = cached
            if len(self._batched) > BATCH_CACHE_SIZE:
                self._batched.popitem(last=False)
        else:
            self._batched.move_to_end(n)
        graph = copy.copy(cached)
        store = graph[NODE]
        for name, values in self._varying.items():
            store[name] = values[copies].flatten(0, 1)
        return graph

    def structure_graph(self, index: int = 0) -> HeteroData:
        """The static graph of pool entry ``index`` (for pictures and tests)."""
        return self._structures[index]


def sleep_repr(sleep: SleepConfig | None) -> str:
    """The sleep settings a step of the environment uses, for a run's record.

    Only ``enabled``, ``threshold`` and ``patience``: every episode starts from
    :func:`~hrn_pyg.sim.sleeping.state_from_history`, so ``start_from_history`` (a rollout's option)
    changes nothing here and does not make a run another run when it is resumed.
    """
    if sleep is None:
        return "None"
    return f"SleepConfig(enabled={sleep.enabled}, threshold={sleep.threshold}, patience={sleep.patience})"


def weights_digest(model: torch.nn.Module) -> str:
    """A short SHA-256 of a model's parameters and buffers (names, shapes and values)."""
    digest = hashlib.sha256()
    for name, tensor in sorted(model.state_dict().items()):
        digest.update(name.encode())
        digest.update(str(tuple(tensor.shape)).encode())
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()[:12]


def _varying_node_attributes(structures: Sequence[HeteroData]) -> dict[str, Tensor]:
    """Node tensors that differ between pool structures, stacked ``[P, N, ...]``.

    Raises ValueError when the structures do not share node count and edge sets (the batched
    graph cache relies on one shared hierarchy).
    """
    first = structures[0]
    for other in structures[1:]:
        if other[NODE].num_nodes != first[NODE].num_nodes or any(
                not torch.equal(first[et].edge_index, other[et].edge_index) for et in first.edge_types):
            raise ValueError("pool structures must share one hierarchy (same nodes and edges)")
    varying = {}
    for name, value in first[NODE].items():
        if not isinstance(value, Tensor):
            continue
        stacked = torch.stack([s[NODE][name] for s in structures])
        if not bool((stacked == stacked[:1]).all()):
            varying[name] = stacked
    return varying
