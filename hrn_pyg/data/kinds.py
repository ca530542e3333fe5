"""A scene's vocabulary without torch: the material names and codes, gravity and the default
model step, and :class:`SceneEffects`.

Reading and checking a scene file (:mod:`hrn_pyg.data.scene_file`) needs these and nothing of
torch, so a bad file is answered before torch is imported; so do the command line's ``--help`` pages
(the history length, the built-in scenes' names). :mod:`hrn_pyg.data.graph` and
:mod:`hrn_pyg.data.effects` use the same names.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

#: Material names in one-hot column order (episode files store the column index).
MATERIALS = ("rigid", "soft", "cloth", "static")
#: Material codes: the value of ``object_material`` and the column of ``graph['particle'].material``
#: (static objects never move).
RIGID, SOFT, CLOTH, STATIC = (MATERIALS.index(name) for name in ("rigid", "soft", "cloth", "static"))
#: The six tetrahedra of the Kuhn (Freudenthal) split of a lattice cell, as indices into its
#: corners numbered ``i + 2 j + 4 k`` for corner offset ``(i, j, k)``. Every one shares the main
#: diagonal 0-7 and neighbouring cells split their common face the same way, so the mesh is
#: conforming without any parity bookkeeping.
KUHN_TETS = ((0, 1, 3, 7), (0, 1, 5, 7), (0, 2, 3, 7), (0, 2, 6, 7), (0, 4, 5, 7), (0, 4, 6, 7))
#: Model states before the current one that a state carries (``x_{t-2}, x_{t-1}`` before ``x_t``).
HISTORY = 2
#: Gravity (m/s^2), along -z in every scene.
GRAVITY = 9.81
#: A scene's default model step: this many physics steps at this rate (1/30 s).
SUBSTEPS, PHYSICS_HZ = 8, 240.0
#: the package's own scenes (``--scene``), one file each under ``hrn_pyg/data/builtin_scenes``
SCENES: tuple[str, ...] = ("soft_bounce", "cube_collision", "wedge", "multi_material", "cube_push", "tower")


@dataclass(frozen=True)
class SceneEffects:
    """The effects a scene can call for; None leaves the choice to the data (the default).

    Attributes:
        forces: True: forces act (the force module runs where nonzero); False: never (a nonzero
            force is an error).
        collisions: True: objects can touch; False: no collision search or module (one object).
    """

    forces: bool | None = None
    collisions: bool | None = None

    def __post_init__(self) -> None:
        for name in ("forces", "collisions"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, bool):
                raise ValueError(f"SceneEffects.{name} must be True, False or None, got {value!r}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)
