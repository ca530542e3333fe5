"""``hrn-pyg sample``: K futures of one scene by Monte Carlo dropout, drawn like Fig. 6.

The start comes from a test episode of ``--data`` or a fresh pybullet episode
(``--episode-seed``); the K futures are drawn light, the ground truth dark, in a PNG and a GIF.
Also ``samples.npz`` (``samples [K, T, L, 3]``, ``truth [T+1, L, 3]``, and the scene:
``leaf_object``, ``object_material``, ``pitch``, ``dt``, its meshes at rest,
:meth:`hrn_pyg.export.SceneMeshes.to_arrays`); ``--export glb,ply,obj,vtk`` writes the futures as
the scene's meshes (:mod:`hrn_pyg.export`), which ``hrn-pyg view`` shows. Without ``--rate``:
the calibrated ``dropout_rate``, or :data:`UNCALIBRATED_RATE` (``samples.json`` says which).
"""

from __future__ import annotations

import argparse
import io
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch_geometric.data import HeteroData

from hrn_pyg.checkpoints import checkpoint_path, load_model, resolve_model
from hrn_pyg.checkpoints.domain import Domain, episode_domain, report_outside
from hrn_pyg.commands.sample import UNCALIBRATED_RATE, add_arguments  # noqa: F401  the command's arguments, here too
from hrn_pyg.data.io import load_episode
from hrn_pyg.data.graph import HISTORY, NODE
from hrn_pyg.data.scene_file import MAX_STEPS, check_scene_name, scene_effects
from hrn_pyg.nn.hrn import HRN
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sampling.sample import sample
from hrn_pyg.sim.fixed_shape import FixedShapeConfig
from hrn_pyg.sim.plausibility import state_plausibility, summary_line
from hrn_pyg.sim.sleeping import DEFAULT_SLEEP
from hrn_pyg.utils.device import resolve_device
from hrn_pyg.utils.files import atomic_write, atomic_write_json
from hrn_pyg.utils.options import progress_bar

if TYPE_CHECKING:
    from hrn_pyg.data.scene_file import SceneSpec

#: the most futures one command samples (the package's docs use at most 32)
MAX_K = 1024
#: the most memory the futures of one command may need (:func:`check_memory`)
MAX_SAMPLE_BYTES = 4 * 2**30
#: columns of the PNG, as fractions of the horizon (t = 0 is the start state)
FIGURE_COLUMNS = (0.0, 0.25, 0.5, 0.75, 1.0)


def default_rate(model: HRN, calibrated: bool = False) -> tuple[float, str]:
    """The rate to sample ``model`` at when the user names none, and where it comes from:
    ``"calibrated"`` (``hrn-pyg calibrate`` chose it), ``"model config"`` (a ``dropout_rate``
    set otherwise) or ``"uncalibrated default"`` (:data:`UNCALIBRATED_RATE`)."""
    rate = float(model.config.dropout_rate)
    if rate > 0:
        return rate, "calibrated" if calibrated else "model config"
    return UNCALIBRATED_RATE, "uncalibrated default"


def initial_state(args: argparse.Namespace, steps: int | None,
                  source: str | SceneSpec | None = None) -> tuple[HeteroData, dict]:
    """The start graph (carrying ``pos_seq``/``force_seq``) and a description of its origin,
    with the :class:`~hrn_pyg.checkpoints.domain.Domain` of its episode (``domain``);
    ``source`` is :func:`scene_source` of ``args`` when the caller has it."""
    if args.data:
        from hrn_pyg.data.dataset import EpisodeWindows

        dataset = EpisodeWindows(args.data, split=args.split, horizon=steps or 1)
        index = int(args.window)
        if not 0 <= index < len(dataset):
            raise ValueError(f"--window must be in [0, {len(dataset) - 1}], got {index}")
        window = dataset[index]
        episode = load_episode(Path(args.data) / f"episode_{int(window.episode_seed):06d}.npz")
        return window, {"data": str(args.data), "window": index,
                        "episode_seed": int(window.episode_seed), "start_step": int(window.start_step),
                        "domain": episode_domain(episode).to_dict()}
    from hrn_pyg.data.episodes import simulate_episode

    total = args.start + (steps or 30)
    episode = simulate_episode(scene_source(args) if source is None else source, int(args.seed), steps=total)
    graph = episode_state(episode, start=args.start, steps=total - args.start)
    where = {"scene_file": str(args.scene_file)} if args.scene_file else {"scene": args.scene}
    return graph, {**where, "seed": int(args.seed), "start_step": int(args.start),
                   "domain": episode_domain(episode).to_dict()}


def scene_source(args: argparse.Namespace) -> str | SceneSpec:
    """The built-in scene's name, or the :class:`~hrn_pyg.data.scene_file.SceneSpec` of ``--scene-file``."""
    if not args.scene_file:
        return args.scene
    from hrn_pyg.data.scene_file import read_scene_file

    return read_scene_file(args.scene_file)


def check_sizes(k: int, last_step: int) -> None:
    """ValueError for more than :data:`MAX_K` futures or an episode past the scene files'
    ``MAX_STEPS`` (``last_step``: ``--start`` plus ``--horizon``), before anything is simulated."""
    if k > MAX_K:
        raise ValueError(f"--k {k}: at most {MAX_K} futures (each is simulated and drawn)")
    if last_step > MAX_STEPS:
        raise ValueError(f"--start plus --horizon is {last_step} steps, more than {MAX_STEPS}")


def check_memory(k: int, steps: int, graph: HeteroData, width: int) -> None:
    r"""ValueError when ``k`` futures of ``steps`` steps of ``graph`` would need more than
    :data:`MAX_SAMPLE_BYTES`, estimated as

    .. math:: k \bigl(3 \cdot 12\,(T + 1) L + 32\, w\, (N + E)\bigr)

    bytes: three float32 copies of the futures and eight activations of width :math:`w` per node
    and edge of each copy.
    """
    leaves = int(graph[NODE].is_leaf.sum())
    size = k * (36 * (steps + 1) * leaves + 32 * width * (graph[NODE].num_nodes + graph.num_edges))
    if size > MAX_SAMPLE_BYTES:
        raise ValueError(f"--k {k} futures of {steps} steps of {leaves} leaves need about {size / 2**30:.1f} GB, "
                         f"more than {MAX_SAMPLE_BYTES / 2**30:.0f} GB; ask for fewer futures or steps")


def run(args: argparse.Namespace) -> int:
    check_scene_name(args.scene)
    if args.k < 1:
        raise ValueError(f"--k must be >= 1, got {args.k}")
    if args.rate is not None and not 0.0 <= args.rate < 1.0:
        raise ValueError(f"--rate must be in [0, 1), got {args.rate}")
    if args.steps is not None and args.steps < 1:
        raise ValueError(f"--horizon must be >= 1, got {args.steps}")
    check_sizes(args.k, args.start + (args.steps or 0))
    if args.cuda_graph and not args.fixed_shape:
        raise ValueError("--cuda-graph needs --fixed-shape")
    device = resolve_device(args.device)
    if args.cuda_graph and device.type != "cuda":
        raise ValueError(f"--cuda-graph needs a CUDA device, got {device}")
    if args.scene_file and not args.model:
        raise ValueError("--scene-file needs --model (the shipped checkpoints each know one built-in scene)")
    from hrn_pyg.export.options import check_picture_options

    pictures = check_picture_options(args)
    source = scene_source(args)
    name = args.scene or source.name
    model_path = resolve_model(name, args.model)
    model = load_model(model_path, device)
    if args.compile and not args.fixed_shape:
        model.compile()  # same numbers; shapes that change (new contacts) compile once more
    if args.rate is None:
        from hrn_pyg.sampling.calibrate import calibration_record

        rate, rate_source = default_rate(model, calibration_record(model_path) is not None)
    else:
        rate, rate_source = float(args.rate), "--rate"
    graph, origin = initial_state(args, args.steps, source)
    report_outside(model, Domain.from_dict(origin["domain"]), strict=args.strict, prefix="hrn-pyg sample: warning: ")
    store = graph[NODE]
    steps = int(store.force_seq.shape[1]) if args.steps is None else int(args.steps)
    from hrn_pyg.export.options import result_meshes

    meshes = result_meshes(args, source, np.asarray(store.object[store.is_leaf]), steps, origin)  # before any sampling
    check_memory(args.k, steps, graph, model.config.hidden)
    forces = store.force_seq.transpose(0, 1)[:steps]  # [steps, N, 3]
    modules = tuple(m for m in args.modules.split(",") if m) if args.modules else None
    generator = torch.Generator(device=device).manual_seed(int(args.sample_seed))  # draws on the device
    sleep = None if (args.no_sleep or args.fixed_shape) else DEFAULT_SLEEP
    fixed = FixedShapeConfig(cuda_graph=args.cuda_graph, compile=args.compile) if args.fixed_shape else None
    bar = progress_bar(3, "sample", "stage", enabled=not getattr(args, "no_progress", False))
    bar.set_postfix_str(f"{args.k} futures of {steps} steps")
    samples = sample(model, graph, args.k, steps, rate, forces=forces, generator=generator,
                     modules=modules, sleep=sleep, fixed_shape=fixed,
                     effects=scene_effects(source) if isinstance(source, str) else source.effects
                     ).cpu().numpy()  # [K, steps, L, 3]

    leaf = store.is_leaf
    truth = store.pos_seq[leaf][:, HISTORY:].transpose(0, 1).numpy()  # [steps+1, L, 3], t = 0..steps
    start = np.broadcast_to(truth[:1], (args.k, 1) + truth.shape[1:])
    paths = np.concatenate([start, samples], axis=1)  # [K, steps+1, L, 3]
    leaf_object = store.object[leaf]

    from hrn_pyg.viz import object_colors, samples_figure, write_gif

    out = Path(args.out) if args.out else Path("runs") / "sample" / name
    out.mkdir(parents=True, exist_ok=True)
    colors = object_colors(np.asarray(leaf_object), static=np.asarray(store.is_static[leaf]))  # static light grey
    times = pictures.times(steps, FIGURE_COLUMNS)
    title = f"{name}: {args.k} samples, dropout {rate:g}"
    bar.update()
    bar.set_postfix_str("figure")
    samples_figure(truth, paths, times, colors, out / "samples.png", title=title, size=pictures.size,
                   view=pictures.camera)
    bar.update()
    bar.set_postfix_str("animation")
    for suffix in ("gif", "mp4") if args.mp4 else ("gif",):
        write_gif({"truth (dark) + samples": truth}, colors, out / f"samples.{suffix}", samples=paths,
                  fps=pictures.fps, size=pictures.size, view=pictures.camera)

    def write_npz(f) -> None:
        buffer = io.BytesIO()
        np.savez_compressed(buffer, samples=samples, truth=truth, **meshes.to_arrays())
        f.write(buffer.getvalue())

    atomic_write(out / "samples.npz", write_npz)
    plausible = plausibility_record(graph, samples, forces)
    atomic_write_json(out / "samples.json", {
        "plausibility": plausible,
        "k": args.k, "rate": rate, "rate_source": rate_source, "steps": steps, "modules": list(modules or model.config.dropout_modules),
        "sample_seed": args.sample_seed, "sleep": None if sleep is None else sleep.to_dict(), "model": str(args.model or checkpoint_path(name)),
        "device": str(device), "compiled": bool(args.compile),
        "fixed_shape": None if fixed is None else asdict(fixed), **origin,
    })
    if pictures.export:
        from hrn_pyg.export import export_trajectories, sample_trajectories

        written = export_trajectories(meshes, sample_trajectories(truth, paths), out, pictures.export)
        print(f"exported {', '.join(pictures.export)}: {', '.join(str(p) for p in written[:3])}"
              + (f" and {len(written) - 3} more" if len(written) > 3 else ""))
    bar.update()
    bar.close()
    print(f"wrote {out / 'samples.png'}, {out / 'samples.gif'} and samples.npz ({args.k} x {steps} steps, "
          f"rate {rate:g}: {rate_source})")
    print(plausible["line"])
    return 0


def plausibility_record(graph, samples: np.ndarray, forces: torch.Tensor) -> dict:
    """The plausibility report (:mod:`hrn_pyg.sim.plausibility`) of the futures ``samples``
    ``[K, steps, L, 3]`` and of the graph's ground truth (the reference row), with its summary line."""
    reports, reference, scene = state_plausibility(graph, torch.as_tensor(samples), forces)
    return {"futures": [r.to_dict() for r in reports], "truth": reference.to_dict(),
            "line": summary_line(reports, scene.pitch, reference)}
