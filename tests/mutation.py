"""Mutation testing with mutmut (``make mutation``; the optional ``mutation`` extra, not part of
``make test`` or CI): each module below in turn, mutated in a copy of the package, the
experiments beside it and the tests under ``out/mutation/<name>/`` (the checkout is never
touched), one process, against its own test files only. Prints the survivors and writes them to ``out/mutation/<name>/survivors.txt``;
exits 1 when a survivor is not listed in :data:`EQUIVALENT` (a mutant no test can tell apart).

    python tests/mutation.py [stats stability scene_file expressions]

``cd out/mutation/<name> && ../../../.venv/bin/mutmut show <mutant>`` shows one mutant.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MUTMUT = Path(sys.executable).parent / "mutmut"

#: name -> (the file mutated, its test files, the mutants run: an fnmatch pattern of mutmut's names)
MODULES: dict[str, tuple[str, tuple[str, ...], str]] = {
    "stats": ("experiments/rl/stats.py", ("tests/experiments/rl/test_stats.py",), "experiments.rl.stats.*"),
    "stability": ("hrn_pyg/sim/stability.py", ("tests/sim/test_stability.py",), "hrn_pyg.sim.stability.*"),
    # the scene file's draws: every function or method with "draw" in its name
    "scene_file": ("hrn_pyg/data/scene_file.py",
                   ("tests/data/test_scene_file.py", "tests/data/test_scene_file_bounds.py",
                    "tests/data/test_scene_file_pushes.py", "tests/data/test_scene_file_draws.py"),
                   "hrn_pyg.data.scene_file.*draw*"),
    "expressions": ("hrn_pyg/data/expressions.py", ("tests/data/test_expressions.py",), "hrn_pyg.data.expressions.*"),
}

#: surviving mutants that behave as the original does, each with the reason (mutmut numbers the
#: mutants of a function in order: an edit of the function renumbers them, and a rerun lists them)
EQUIVALENT: dict[str, str] = {
    "experiments.rl.stats.x__as_runs__mutmut_10": "unsqueeze(+1) of a 1-D tensor is unsqueeze(-1): (n, 1)",
    "experiments.rl.stats.x__resampled_medians__mutmut_12": "median's default dim -1 is dim 1 of the [R, n] draws",
    "experiments.rl.stats.x_probability_of_improvement_point__mutmut_23":
        "mean over (-3, +2) then -1 averages the same equally weighted wins over (n, m, T) "
        "(and is (-3, -2) itself for a batch)",
    "experiments.rl.stats.x_reference_levels__mutmut_6": "0.75 and 0.5 of an integer step limit have at most 2 decimals",
    "experiments.rl.stats.x__number__mutmut_11": "only +-inf reach the test: v >= 0 is v > 0 for them",
    "experiments.rl.stats.x__number__mutmut_12": "only +-inf reach the test: v > 1 is v > 0 for them",
    "experiments.rl.stats.x_comparison_markdown__mutmut_63": "a missing versus table read as None or {}: both false",
    "experiments.rl.stats.x_comparison_markdown__mutmut_65": "a missing versus table read as None or {}: both false",
    "hrn_pyg.sim.stability.x_mean_pairwise_distance__mutmut_22":
        "with fewer than two points every distance sum is 0, divided by 1 or 2",
    "hrn_pyg.sim.stability.x_stability_report__mutmut_57":
        "every leaf of an object has its material, and a body has at least two leaves (MIN_LEAVES)",
    "hrn_pyg.sim.stability.x_stability_report__mutmut_76": "norm over dim +1 of [S, 3] centres is dim -1",
    "hrn_pyg.sim.stability.x_stability_report__mutmut_45": 'float("NAN") is float("nan")',
    "hrn_pyg.data.expressions.x_checked__mutmut_4":
        "every value is checked where it first appears, and no literal is complex: a complex value "
        "is a Python complex (a fractional power of a negative number) before it can reach an array",
    "hrn_pyg.data.expressions.x_checked__mutmut_5": "as x_checked__mutmut_4: no complex array can be formed",
    "hrn_pyg.data.expressions.x_tree_size__mutmut_3": "the root sits at depth 1, so the deepest is at least 1 either way",
    "hrn_pyg.data.expressions.x__shape__mutmut_7":
        "a shape is never non-finite: checked refuses an infinity or a NaN where it first appears",
    "hrn_pyg.data.expressions.x__shape__mutmut_12":
        "every array an expression builds is numeric (no string, bool or None literal parses)",
    "hrn_pyg.data.expressions.x__zeros__mutmut_3": "zeros() reads the empty shape as () either way",
    "hrn_pyg.data.scene_file.x__draw__mutmut_17":
        "the message of a TypeError or OverflowError from float64 conversion, which no evaluated "
        "value raises: evaluate returns numbers only, whole numbers of at most 1023 bits (< 2^1024)",
    "hrn_pyg.data.scene_file.x__draw__mutmut_36":
        "the message of a non-finite drawn value, which evaluate has already refused as not finite",
}

CONFIG = """[mutmut]
source_paths = {folder}
only_mutate = {source}
pytest_add_cli_args_test_selection =
{tests}
pytest_add_cli_args =
    -p
    no:cacheprovider
    -p
    no:xdist
    -W
    ignore::DeprecationWarning

[tool:pytest]
pythonpath = tests .
addopts = -q
"""


def run(name: str) -> list[str]:
    """Mutate one module of :data:`MODULES`; its survivors."""
    source, tests, pattern = MODULES[name]
    work = ROOT / "out" / "mutation" / name
    shutil.rmtree(work, ignore_errors=True)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for folder in ("hrn_pyg", "experiments", "tests"):
        shutil.copytree(ROOT / folder, work / folder, ignore=ignore)
    (work / "setup.cfg").write_text(CONFIG.format(folder=source.split("/")[0], source=source,
                                                  tests="\n".join(f"    {t}" for t in tests)))
    print(f"== {name}: {source} against {', '.join(tests)}", flush=True)
    subprocess.run([str(MUTMUT), "run", "--max-children", "1", pattern], cwd=work, check=True,
                   stdout=subprocess.DEVNULL)
    results = subprocess.run([str(MUTMUT), "results"], cwd=work, check=True, capture_output=True, text=True).stdout
    survivors = sorted(line.split(":")[0].strip() for line in results.splitlines() if line.strip().endswith("survived"))
    (work / "survivors.txt").write_text("".join(f"{s}\n" for s in survivors))
    return survivors


def main(names: list[str]) -> int:
    unknown = [n for n in names if n not in MODULES]
    if unknown:
        print(f"unknown module(s) {unknown}; known: {', '.join(MODULES)}", file=sys.stderr)
        return 2
    failed = False
    for name in names or list(MODULES):
        survivors = run(name)
        unexplained = [s for s in survivors if s not in EQUIVALENT]
        print(f"{name}: {len(survivors)} survived, {len(unexplained)} not known to be equivalent", flush=True)
        for s in unexplained:
            print(f"  {s}")
        failed |= bool(unexplained)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
