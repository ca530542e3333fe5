r"""The rules after the network, in one place: what every path applies to a step's prediction.

:func:`~hrn_pyg.sim.step.decode` ends with the rules of the decoder (the rigid fit, the ground
projection); the rules here need the scene or the step's force, so they are made once per scene
(:func:`step_rules`) and applied by every step that path takes, the same way in each: the rollout
loop (:func:`~hrn_pyg.sim.rollout.iterate`), the sleeping step, the fixed-shape simulator, the
sampler and the RL dynamics (environment and planner). In order:

1. **Failed copies held** (``hold_failed``): a copy of a batch whose prediction holds NaN or inf
   (checked before the other rules and after them) stays where it is, with zero velocity, and is
   recorded in :attr:`StepRules.failed`; the other copies go on. Without it a non-finite
   prediction is an error of the step.
2. **Energy limit** (``HRNConfig.energy_limit``, :mod:`hrn_pyg.sim.energy`): no copy ends the step
   with more energy than it started with plus the work of its pushes, judged on the network's
   prediction.
3. **Static friction** (``HRNConfig.rest_friction``, :mod:`hrn_pyg.sim.rest_friction`): a
   supported object, not pushed in the step, whose last step and predicted step are both shorter
   than a small part of a pitch is held where it is. Before the clearance, so that a push out of
   another body is never taken back.
4. **Clearance** (``HRNConfig.cloth_clearance``, ``HRNConfig.solid_clearance``,
   :mod:`hrn_pyg.sim.cloth_contact`): a leaf of a cloth (or of a soft body or a rigid object) is
   stopped where it enters another object, or moved back out; a soft body gives way to what is
   inside it and is stretched no further than a limit. It comes last because moving a body out
   of another raises it: an energy limit after it would take part of that move back and leave
   the body inside. Its stops only shorten steps; a push is about as long as the overlap
   it removes plus the clearance and gives no speed (the body's :math:`x_t` moves with it).

**Shapes.** A :class:`StepRules` maps a :class:`~hrn_pyg.sim.step.Prediction` of a graph of
``N`` nodes (each tensor ``(N, 3)``) to another; ``failed`` is ``(R,)`` bool over the graph's
``R`` objects, indexed by batch copy (the first ``B`` rows: one per copy).
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.sim.cloth_contact import ClothContact, cloth_contact
from hrn_pyg.sim.energy import copy_of_objects, limit_energy
from hrn_pyg.sim.rest_friction import hold_resting
from hrn_pyg.sim.step import Prediction, held_at_current, non_finite_copies, object_of


class StepRules:
    """The rules of one model on one scene (module docstring), made by :func:`step_rules`.

    Call it as ``rules(graph, prediction, force, movable)``: ``graph`` the step's graph at
    :math:`t` (the whole scene, with the structure the rules were made for), ``force`` ``[N, 3]``
    the step's external force (N) or None, ``movable`` ``[N]`` bool the rows that may move (a
    step with sleeping objects) or None.

    Attributes:
        cloth: the cloth rule's constants, or None (no moving cloth near a solid, or off).
        energy: whether the energy limit applies.
        objects: ``([N] long, R)``, every node's object (:func:`~hrn_pyg.sim.step.object_of`).
        rigid_from_rest: the energy limit's rigid refit reads the rest shape.
        hold_failed: a copy whose prediction is not finite is held rather than an error.
        rest_friction: pitches under which a supported object's steps hold it still (0: off).
        host_reads: the rules may read the device to skip work (False: a fixed-shape step, which
            then has only the energy limit).
        failed: ``[R]`` bool, row ``b``: copy ``b`` has failed at some step (``hold_failed``).
    """

    def __init__(self, cloth: ClothContact | None, energy: bool, objects: tuple[Tensor, int],
                 rigid_from_rest: bool = False, hold_failed: bool = False, host_reads: bool = True,
                 rest_friction: float = 0.0) -> None:
        if not host_reads and (cloth is not None or hold_failed):
            raise ValueError("StepRules: cloth clearance and failed copies held need host reads")
        if not 0.0 <= rest_friction < 1.0:
            raise ValueError(f"StepRules: rest_friction must be in [0, 1) pitches, got {rest_friction}")
        self.cloth, self.energy, self.objects = cloth, energy, objects
        self.rigid_from_rest, self.hold_failed, self.host_reads = rigid_from_rest, hold_failed, host_reads
        self.rest_friction = float(rest_friction)
        self.failed = torch.zeros(objects[1], dtype=torch.bool, device=objects[0].device)

    @property
    def active(self) -> bool:
        """Whether any rule can change a prediction."""
        return self.cloth is not None or self.energy or self.hold_failed or self.rest_friction > 0

    def __repr__(self) -> str:
        return (f"StepRules(cloth={self.cloth is not None}, energy={self.energy}, "
                f"hold_failed={self.hold_failed}, rest_friction={self.rest_friction:g})")

    def __call__(self, graph: HeteroData, prediction: Prediction, force: Tensor | None = None,
                 movable: Tensor | None = None) -> Prediction:
        if self.hold_failed:
            prediction = self.hold_non_finite(graph, prediction)
        if self.energy:
            prediction = limit_energy(graph, prediction, self.objects, force, movable, self.rigid_from_rest,
                                      self.host_reads)
        if self.rest_friction > 0:
            prediction = hold_resting(graph, prediction, self.objects, self.rest_friction, force)
        if self.cloth is not None:
            prediction = self.cloth(graph, prediction, movable)
        if self.hold_failed and (self.cloth is not None or self.energy):  # what the rules made, too
            prediction = self.hold_non_finite(graph, prediction)
        return prediction

    def hold_non_finite(self, graph: HeteroData, prediction: Prediction) -> Prediction:
        """``prediction`` with every copy that has a non-finite row held at :math:`x_t` (zero
        velocity); such copies are added to :attr:`failed`. One host read."""
        group, count = self.objects
        copy = copy_of_objects(graph, self.objects)[group]  # [N]
        bad = non_finite_copies(prediction.pos, copy, count)
        self.failed = self.failed | bad
        if not bool(bad.any()):
            return prediction
        return held_at_current(graph, prediction, bad[copy])

    def failed_copies(self, copies: int) -> Tensor:
        """``[copies]`` bool: which of the first ``copies`` copies have failed."""
        return self.failed[:copies]


def step_rules(model: torch.nn.Module, graph: HeteroData, objects: tuple[Tensor, int] | None = None,
               hold_failed: bool = False, collisions: bool = True) -> StepRules | None:
    """The :class:`StepRules` of ``model`` on the scene ``graph`` (a one-scene graph or a batch
    of copies), or None when no rule has anything to do. ``objects``: :func:`object_of` of
    ``graph`` if the caller has it; ``collisions=False``: nothing in the scene touches, so the
    cloth rule has nothing to do. One host pass over the objects when the model keeps cloth out."""
    config = model.config
    clearance = float(getattr(config, "cloth_clearance", 0.0))
    solid_clearance = float(getattr(config, "solid_clearance", 0.0))
    clear = (clearance > 0 or solid_clearance > 0) and collisions
    energy = bool(getattr(config, "energy_limit", False))
    friction = float(getattr(config, "rest_friction", 0.0))
    if not clear and not energy and not hold_failed and not friction > 0:
        return None
    objects = object_of(graph) if objects is None else objects
    cloth = (cloth_contact(graph, clearance, objects=objects, solid_clearance=solid_clearance,
                           project_cloth=clearance > 0) if clear else None)
    rules = StepRules(cloth, energy, objects, bool(getattr(config, "rigid_fit_rest", False)), hold_failed,
                      rest_friction=friction)
    return rules if rules.active else None
