"""A step of a pile against pybullet's: time per model step as the object count grows.

For each object count ``N`` in ``--counts`` a scene of ``N`` meshes the generalist never trained
on (``--meshes``, default pybullet_data's duck and torus, the validation meshes of
docs/generalist.md) is written as a scene file: the objects stand on a square grid 0.4 m apart
in layers 0.4 m apart, each turned by a random yaw and scaled to a drawn size, and fall into a
pile. pybullet runs one episode of it (``--steps`` model steps); its time per model step is the
median over those steps of one ``Scene.step`` (``substeps`` physics steps, the leaves read
back). The model rolls out the same episode from step 2 for ``--steps - 2`` steps, sleeping off
(every object awake, the network alone), one torch thread; its time per step is the rollout's
seconds per step. Both are timed ``--repeats`` times, paired: each repeat runs pybullet's episode
again and then every model's rollout, so a machine whose speed drifts slows both sides of a pair
alike (the rounds run model by model, each with pybullet's episode beside it). The table gives
pybullet's median over all rounds, each model's median and the median of its paired ratios (model
over pybullet); the JSON keeps every round and the paired ratios' range. Each model of ``--model`` is timed as
it is loaded and, when it averages over the lattice's symmetries (``mirror_average``), also as
one pass (the same weights, ``mirror_average`` off), so the cost of the average is read off one
run. The position MSE of the one-pass rollout against the averaged one at the last step says
how far apart they are on this scene. With ``--compile`` each model is also timed in one pass
as fixed-shape steps compiled by ``torch.compile``
(:class:`hrn_pyg.sim.fixed_shape.FixedShapeSimulator`, ``compile=True``): the seconds of its
first rollout (the compilation) are reported beside its median time per step, and its largest
difference from the eager one-pass rollout says it computes the same positions.

``--sizes W:C:L,...`` also times fresh networks of other sizes in the same rounds: the model's
config with MLP width and effect size ``W``, ``C`` vector channels (an equivariant network) and
``L`` hidden layers, one pass, the trained normaliser and the next-state module's weights zeroed
(the pile then falls freely and stays finite; a network's time does not depend on its weights'
values). Each is timed as the model is (eagerly, and compiled with ``--compile``), so a size's
cost against pybullet is read off before anything is trained at it. Their compiled rollouts'
difference from the eager ones is recorded too, but says little: with the readout zeroed, every
position is the free fall's.

Run: ``python -m benchmarks.pile_step [--counts 2,5,10,20,40] [--material rigid] [--model shapes]
[--compile] [--sizes 48:4:2] [--out benchmarks/results/pile_step_rigid.json]``. Prints a markdown table and writes JSON
atomically. Time only on a quiet machine.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from collections.abc import Callable
from pathlib import Path

import torch

from hrn_pyg.checkpoints import load_model, with_applied_options
from hrn_pyg.data.scene_file import read_scene_file
from hrn_pyg.nn.networks import network_from_dict
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.utils.files import atomic_write_json

from benchmarks.common import DEFAULT_MESHES, compiled_rollout, pile_scene_text, rollout_seconds, time_pybullet


def parse_sizes(text: str) -> list[tuple[int, int, int]]:
    """``"W:C:L,..."`` as (width, vector channels, hidden layers) triples of positive integers."""
    sizes = []
    for item in (t for t in text.split(",") if t):
        parts = item.split(":")
        if len(parts) != 3 or not all(p.isdigit() and int(p) > 0 for p in parts):
            raise SystemExit(f"--sizes: {item!r} is not WIDTH:CHANNELS:LAYERS of positive integers")
        sizes.append((int(parts[0]), int(parts[1]), int(parts[2])))
    return sizes


def sized_network(model, width: int, channels: int, layers: int):
    """A fresh one-pass network of ``model``'s config at another size, for timing: MLP width and
    effect size ``width``, ``channels`` vector channels (used by an equivariant network),
    ``layers`` hidden layers; ``model``'s normaliser, and the next-state module's weights zeroed
    so that a rollout stays finite."""
    config = {**model.config.to_dict(), "hidden": width, "effect_dim": width, "depth": layers,
              "vector_channels": channels, "mirror_average": False}
    if not hasattr(model, "state"):
        raise SystemExit(f"--sizes: {type(model).__name__} is not an HRN; sizes are timed for HRNs only")
    network = network_from_dict(config)
    network.normalizer.load_state_dict(model.normalizer.state_dict())
    with torch.no_grad():
        for parameter in network.state.parameters():
            parameter.zero_()
    return network.eval()


def paired_times(bullet: Callable[[], float], runs: dict[str, Callable[[], tuple[float, torch.Tensor]]],
                 repeats: int) -> tuple[list[float], dict[str, list[float]], dict[str, torch.Tensor]]:
    """``repeats`` rounds of pybullet's seconds per step and then each run's: the lists in
    round order and each run's last positions."""
    bullet_s: list[float] = []
    seconds: dict[str, list[float]] = {label: [] for label in runs}
    positions: dict[str, torch.Tensor] = {}
    for _ in range(repeats):
        bullet_s.append(bullet())
        for label, run in runs.items():
            s, positions[label] = run()
            seconds[label].append(s)
    return bullet_s, seconds, positions


def paired_summary(bullet_s: list[float], seconds: list[float]) -> dict:
    """Median milliseconds, the median of the paired ratios to pybullet and their range."""
    ratios = [m / b for m, b in zip(seconds, bullet_s)]
    return {"ms": 1e3 * statistics.median(seconds), "x_pybullet": statistics.median(ratios),
            "x_pybullet_range": [min(ratios), max(ratios)], "ms_runs": [1e3 * v for v in seconds]}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", default="2,5,10,20,40", help="object counts, comma-separated")
    parser.add_argument("--material", choices=("rigid", "soft"), default="rigid")
    parser.add_argument("--model", action="append", default=None, help="shipped name or path (repeatable; default shapes)")
    parser.add_argument("--meshes", default=",".join(DEFAULT_MESHES), help="meshes drawn per object, comma-separated")
    parser.add_argument("--pitch", type=float, default=0.05)
    parser.add_argument("--steps", type=int, default=40, help="model steps of the episode")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--compile", action="store_true",
                        help="also time one pass as compiled fixed-shape steps (a minute or so to compile per count)")
    parser.add_argument("--sizes", default="",
                        help="also time fresh one-pass networks of these sizes, WIDTH:CHANNELS:LAYERS comma-separated")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    if args.repeats < 1 or args.steps < 4:
        raise SystemExit("--repeats must be >= 1 and --steps >= 4")
    sizes = parse_sizes(args.sizes)
    torch.set_num_threads(args.threads)
    counts = [int(c) for c in args.counts.split(",") if c]
    meshes = tuple(m for m in args.meshes.split(",") if m)
    models = {name: load_model(name) for name in (args.model or ["shapes"])}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for count in counts:
            path = Path(tmp) / f"pile_{count}.toml"
            path.write_text(pile_scene_text(count, args.material, meshes, args.pitch, args.steps))
            spec = read_scene_file(path)
            episode, _ = time_pybullet(spec, args.seed)  # the episode, and pybullet warmed up
            leaves = int(episode["positions"].shape[1])
            state = episode_state(episode, start=2, steps=args.steps - 2)
            steps = args.steps - 2
            row = {"objects": count, "leaves": leaves, "pybullet_ms_runs": [], "models": {}}
            for name, model in models.items():
                # a model's variants share its rounds; a compiled model is timed before the next
                # compiles (the compiled steps hold no guards on the model)
                variants = {"as loaded": model.eval()}
                if getattr(model.config, "mirror_average", False):
                    variants["one pass"] = with_applied_options(model, mirror_average=False).eval()
                one_pass = "one pass" if "one pass" in variants else "as loaded"
                for w, c, layers in sizes:
                    variants[f"fresh {w}:{c}:{layers}"] = sized_network(model, w, c, layers)
                runs = {}
                for label, variant in variants.items():
                    rollout_seconds(variant, state, 2)  # warm-up
                    runs[label] = (lambda v=variant: rollout_seconds(v, state, steps))
                compile_seconds = {}
                if args.compile:
                    compiled = [("compiled", one_pass)] + [(f"compiled {lab}", lab) for lab in variants if lab.startswith("fresh")]
                    for k, (label, source) in enumerate(compiled):
                        try:
                            compile_seconds[label], runs[label] = compiled_rollout(variants[source], state, steps,
                                                                                   reset=k == 0)
                        except ValueError as exc:  # a model the fixed-shape steps cannot run (a GNS)
                            row["compiled_skipped"] = str(exc).splitlines()[0]
                            print(f"{label}: not timed ({row['compiled_skipped']})", flush=True)
                bullet_s, seconds, positions = paired_times(
                    lambda: time_pybullet(spec, args.seed)[1], runs, args.repeats)
                row["pybullet_ms_runs"] += [1e3 * b for b in bullet_s]
                results = {label: paired_summary(bullet_s, s) for label, s in seconds.items()}
                if one_pass == "one pass":
                    results["one pass"]["mse_to_averaged_last_step"] = float(
                        ((positions["one pass"][-1] - positions["as loaded"][-1]) ** 2).sum(-1).mean())
                for label, seconds_to_compile in compile_seconds.items():
                    eager = one_pass if label == "compiled" else label.removeprefix("compiled ")
                    results[label]["compile_s"] = seconds_to_compile
                    results[label]["max_abs_diff_to_eager_m"] = float((positions[label] - positions[eager]).abs().max())
                row["models"][name] = results
            row["pybullet_ms"] = statistics.median(row["pybullet_ms_runs"])
            rows.append(row)
            print(f"{count} objects, {leaves} leaves: pybullet {row['pybullet_ms']:.2f} ms; "
                  + "; ".join(f"{n} {lab} {r['ms']:.2f} ms" for n, res in row["models"].items() for lab, r in res.items()),
                  flush=True)
    header = "| objects | leaves | pybullet (ms) | " + " | ".join(
        f"{n} {lab} (ms, x pybullet)" for n, res in rows[0]["models"].items() for lab in res) + " |"
    print()
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for row in rows:
        cells = [f"{r['ms']:.2f} ({r['x_pybullet']:.2f}x)" for res in row["models"].values() for r in res.values()]
        print(f"| {row['objects']} | {row['leaves']} | {row['pybullet_ms']:.2f} | " + " | ".join(cells) + " |")
    result = {"material": args.material, "pitch": args.pitch, "steps": args.steps, "repeats": args.repeats,
              "threads": args.threads, "seed": args.seed, "meshes": list(meshes), "sizes": [list(z) for z in sizes],
              "torch": torch.__version__,
              "rows": rows}
    if args.out:
        atomic_write_json(args.out, result)
    return result


if __name__ == "__main__":
    main()
