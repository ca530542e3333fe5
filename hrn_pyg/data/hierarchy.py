"""Per-object particle hierarchy by recursive k-means (HRN, Mrowca et al. 2018, Sec. 3).

Each object's leaves are clustered with scikit-learn ``KMeans`` into at most ``branching``
groups, each group larger than ``leaf_group_size`` again, recursively; every cluster (singletons
included) is an ancestor node, and each object has exactly one root, even with one leaf. A
node's children are all leaves or all ancestors. A group k-means cannot split (identical states)
is split by index into ``min(branching, n)`` chunks, so the recursion ends.

The parent array over ``N = L + A`` nodes: leaves ``0 .. L-1`` in input order, then ancestors
object by object, breadth-first within an object; roots have parent ``-1``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: k-means restarts per split; a few are enough for groups this small and keep building fast.
KMEANS_N_INIT = 3


@dataclass(frozen=True)
class HierarchyConfig:
    """How the leaves of one object are grouped into a tree.

    Attributes:
        branching: clusters per split (``k`` of k-means), at least 2.
        leaf_group_size: a group with at most this many leaves is not split further.
        velocity_weight: scale of the velocity columns in the clustering state
            ``[x, w_v * v, w_m * m]`` (0 leaves velocity out).
        mass_weight: scale of the mass column in the clustering state (0 leaves mass out).
        seed: ``random_state`` of every k-means call; the same seed gives the same tree.
    """

    branching: int = 8
    leaf_group_size: int = 8
    velocity_weight: float = 0.0
    mass_weight: float = 0.0
    seed: int = 0


def _validate(
    positions: np.ndarray,
    masses: np.ndarray,
    leaf_object: np.ndarray,
    config: HierarchyConfig,
    velocities: np.ndarray | None,
) -> None:
    if positions.ndim != 2 or positions.shape[1] != 3 or positions.shape[0] < 1:
        raise ValueError(f"positions must have shape [L>=1, 3], got {list(positions.shape)}")
    n_leaves = positions.shape[0]
    if not np.all(np.isfinite(positions)):
        raise ValueError("positions contain NaN or infinite values")
    if masses.shape != (n_leaves,):
        raise ValueError(f"masses must have shape [{n_leaves}], got {list(masses.shape)}")
    if not np.all(np.isfinite(masses)) or np.any(masses <= 0):
        raise ValueError("masses must be finite and strictly positive")
    if leaf_object.shape != (n_leaves,):
        raise ValueError(f"leaf_object must have shape [{n_leaves}], got {list(leaf_object.shape)}")
    if not np.issubdtype(leaf_object.dtype, np.integer):
        raise ValueError(f"leaf_object must be an integer array, got dtype {leaf_object.dtype}")
    if np.any(leaf_object < 0):
        raise ValueError("leaf_object must be non-negative")
    if velocities is not None:
        if velocities.shape != (n_leaves, 3):
            raise ValueError(f"velocities must have shape [{n_leaves}, 3], got {list(velocities.shape)}")
        if not np.all(np.isfinite(velocities)):
            raise ValueError("velocities contain NaN or infinite values")
    if config.branching < 2:
        raise ValueError(f"branching must be >= 2, got {config.branching}")
    if config.leaf_group_size < 1:
        raise ValueError(f"leaf_group_size must be >= 1, got {config.leaf_group_size}")
    for name in ("velocity_weight", "mass_weight"):
        w = getattr(config, name)
        if not np.isfinite(w) or w < 0:
            raise ValueError(f"{name} must be finite and >= 0, got {w}")
    if config.velocity_weight > 0 and velocities is None:
        raise ValueError("velocity_weight > 0 needs velocities")


def _clustering_state(
    positions: np.ndarray, masses: np.ndarray, config: HierarchyConfig, velocities: np.ndarray | None
) -> np.ndarray:
    """The per-leaf state k-means sees: ``[x, w_v v, w_m m]`` (zero-weight columns dropped)."""
    cols = [positions.astype(np.float64)]
    if config.velocity_weight > 0 and velocities is not None:
        cols.append(config.velocity_weight * velocities.astype(np.float64))
    if config.mass_weight > 0:
        cols.append(config.mass_weight * masses.astype(np.float64)[:, None])
    return np.concatenate(cols, axis=1)


def _split(state: np.ndarray, members: np.ndarray, config: HierarchyConfig) -> list[np.ndarray]:
    """Split ``members`` (leaf indices) into at most ``branching`` non-empty groups.

    Groups come in increasing label order; members inside a group keep their input order.
    """
    n = members.shape[0]
    k = min(config.branching, n)
    points = state[members]
    n_distinct = np.unique(points, axis=0).shape[0]
    labels = None
    if n_distinct >= 2:
        from sklearn.cluster import KMeans  # here: scikit-learn takes a second to import

        km = KMeans(n_clusters=min(k, n_distinct), n_init=KMEANS_N_INIT, random_state=config.seed)
        labels = km.fit_predict(points)
        if np.unique(labels).shape[0] < 2:
            labels = None
    if labels is None:
        # every point identical: k-means cannot separate them, split by index instead
        labels = np.repeat(np.arange(k), -(-n // k))[:n]
    return [members[labels == lab] for lab in np.unique(labels)]


def build_hierarchy(
    positions: np.ndarray,
    masses: np.ndarray,
    leaf_object: np.ndarray,
    config: HierarchyConfig | None = None,
    velocities: np.ndarray | None = None,
) -> np.ndarray:
    """Parent array of the per-object k-means tree over the leaves (module docstring): ``grow(p, S)``
    makes ``p`` the parent of every ``l in S`` if ``|S| <= leaf_group_size``, else splits ``S``
    with k-means (``k = min(branching, |S|)``) on ``[x, w_v v, w_m m]`` and grows one child per
    cluster.

    Args:
        positions: leaf positions (at rest).
        masses: leaf masses, strictly positive.
        leaf_object: object index of each leaf (need not be contiguous).
        config: clustering settings; ``HierarchyConfig()`` if None.
        velocities: leaf velocities, needed only when ``config.velocity_weight > 0``.

    Returns:
        ``parent`` int64, ``-1`` for roots.

    **Shapes**: positions ``(L, 3)``, masses ``(L,)``, leaf_object ``(L,)``,
    velocities ``(L, 3)``; returns ``(N,)`` with ``N = L + A``.
    """
    config = HierarchyConfig() if config is None else config
    positions = np.asarray(positions)
    masses = np.asarray(masses)
    leaf_object = np.asarray(leaf_object)
    velocities = None if velocities is None else np.asarray(velocities)
    _validate(positions, masses, leaf_object, config, velocities)

    n_leaves = positions.shape[0]
    state = _clustering_state(positions, masses, config, velocities)
    leaf_parent = np.full(n_leaves, -1, dtype=np.int64)
    ancestor_parent: list[int] = []  # parent of ancestor node L + a

    # A Python loop over tree nodes (not particles): each iteration is one k-means call.
    for obj in np.unique(leaf_object):
        root = n_leaves + len(ancestor_parent)
        ancestor_parent.append(-1)
        queue: list[tuple[int, np.ndarray]] = [(root, np.flatnonzero(leaf_object == obj))]
        head = 0
        while head < len(queue):
            node, members = queue[head]
            head += 1
            if members.shape[0] <= config.leaf_group_size:
                leaf_parent[members] = node
                continue
            for group in _split(state, members, config):
                child = n_leaves + len(ancestor_parent)
                ancestor_parent.append(node)
                queue.append((child, group))

    return np.concatenate([leaf_parent, np.asarray(ancestor_parent, dtype=np.int64)])


def start_hierarchy(first_frame: np.ndarray, leaf_mass: np.ndarray, leaf_object: np.ndarray) -> np.ndarray:
    """The hierarchy of a scene's start: :func:`build_hierarchy` of its first frame (float32 as
    stored, clustered in float64); every path that starts a model takes its tree from here.

    **Shapes:** ``(L, 3)``, ``(L,)``, ``(L,)`` -> ``(N,)`` int64.
    """
    positions = np.asarray(first_frame, dtype=np.float32).astype(np.float64)
    masses = np.asarray(leaf_mass, dtype=np.float32).astype(np.float64)
    return np.asarray(build_hierarchy(positions, masses, np.asarray(leaf_object)), dtype=np.int64)
