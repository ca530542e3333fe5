"""The package's imports point down a fixed order of layers and form no cycle, and the package
never imports the experiments beside it.

Read from the source with ``ast`` (imports inside functions included, so a lazy import cannot
hide a cycle; ``importlib.import_module("hrn_pyg....")`` counts as an import, and a module that
imports a computed name imports every package module it names in a string, as ``cli.py``'s
command table does). The order, bottom first; a module may import from its own layer or below
(the package root is a layer entry for itself only, not for its submodules):

    utils, version -> data, viz, commands (a command's arguments, no torch) -> nn -> checkpoints -> sim -> train, losses, evaluate,
    sampling -> rl -> demo, cli, the package root
"""

from __future__ import annotations

import ast
import functools
from collections import defaultdict
from pathlib import Path

import pytest

import hrn_pyg

ROOT = Path(hrn_pyg.__file__).resolve().parent
LAYERS = (
    ("hrn_pyg.utils", "hrn_pyg.version"),
    ("hrn_pyg.data", "hrn_pyg.viz", "hrn_pyg.commands"),
    ("hrn_pyg.nn",),
    ("hrn_pyg.checkpoints",),
    ("hrn_pyg.sim",),
    ("hrn_pyg.train", "hrn_pyg.losses", "hrn_pyg.evaluate", "hrn_pyg.sampling", "hrn_pyg.export"),
    ("hrn_pyg.rl",),
    ("hrn_pyg.demo", "hrn_pyg.cli", "hrn_pyg"),
)


def module_files() -> dict[str, Path]:
    """``{dotted module name: file}`` of every module of the package."""
    out = {}
    for path in ROOT.rglob("*.py"):
        parts = ("hrn_pyg",) + path.relative_to(ROOT).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _dynamic_import(node: ast.AST) -> ast.expr | None:
    """The argument of ``importlib.import_module(x)``, ``import_module(x)`` or ``__import__(x)``."""
    if not isinstance(node, ast.Call) or not node.args:
        return None
    callee = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
    return node.args[0] if callee in ("import_module", "__import__") else None


def imports_of(name: str, path: Path, modules: set[str]) -> list[tuple[str, str, int]]:
    """``(target module, imported name, line)`` of every package import in one module.

    Besides ``import`` statements: ``import_module("hrn_pyg.x")`` with a literal name imports
    ``hrn_pyg.x``; where a module imports a computed name (``import_module(name)``), every string
    in it that names a package module is taken as imported (``cli.py``'s command table).
    """
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    tree = ast.parse(path.read_text(), str(path))
    found = []
    arguments = [a for a in map(_dynamic_import, ast.walk(tree)) if a is not None]
    computed = any(not (isinstance(a, ast.Constant) and isinstance(a.value, str)) for a in arguments)
    for node in ast.walk(tree):
        argument = _dynamic_import(node)
        if isinstance(argument, ast.Constant) and isinstance(argument.value, str):
            if argument.value.split(".")[0] == "hrn_pyg":
                found.append((argument.value, "", node.lineno))
        elif computed and isinstance(node, ast.Constant) and node.value in modules:
            found.append((node.value, "", node.lineno))
        if isinstance(node, ast.Import):
            found += [(a.name, "", node.lineno) for a in node.names if a.name.split(".")[0] == "hrn_pyg"]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            if source.split(".")[0] != "hrn_pyg":
                continue
            for alias in node.names:
                sub = f"{source}.{alias.name}"
                found.append((sub, "", node.lineno) if sub in modules else (source, alias.name, node.lineno))
    return found


def layer_of(module: str) -> int:
    """The layer of a module: that of the longest entry of :data:`LAYERS` it is or sits under
    (the package root holds only itself, so a module in no subpackage's layer has none)."""
    best, level = -1, None
    for i, layer in enumerate(LAYERS):
        for prefix in layer:
            inside = module.startswith(prefix + ".") and prefix != "hrn_pyg"
            if (module == prefix or inside) and len(prefix) > best:
                best, level = len(prefix), i
    assert level is not None, f"{module} is in no layer: add it to LAYERS"
    return level


def unit_of(module: str) -> str:
    """The subpackage or top-level module a module belongs to (``hrn_pyg.sim.step`` -> ``hrn_pyg.sim``)."""
    return ".".join(module.split(".")[:2])


@functools.lru_cache(maxsize=None)
def graph() -> dict[str, list[tuple[str, str, int]]]:
    files = module_files()
    return {name: imports_of(name, path, set(files)) for name, path in files.items()}


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one node (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def test_every_module_is_in_a_layer():
    for name in module_files():
        layer_of(name)


def test_every_import_points_down_the_layers():
    upward = [f"{name}:{line} imports {target} (layer {layer_of(target)} above {layer_of(name)})"
              for name, found in graph().items() for target, _, line in found
              if layer_of(target) > layer_of(name)]
    assert not upward, "\n".join(upward)


def test_no_module_imports_the_package_root():
    offenders = [f"{name}:{line} imports from hrn_pyg itself" for name, found in graph().items()
                 for target, _, line in found if target == "hrn_pyg" and name != "hrn_pyg"]
    assert not offenders, "\n".join(offenders)


def test_no_cycle_between_modules():
    """The command table included: ``cli`` dispatches to every command by name, and no command
    calls back into ``cli``."""
    edges = {name: {t for t, _, _ in found if t != name} for name, found in graph().items()}
    assert cycles(edges) == []


def test_no_cycle_between_subpackages():
    edges: dict[str, set[str]] = defaultdict(set)
    for name, found in graph().items():
        for target, _, _ in found:
            if unit_of(target) != unit_of(name):
                edges[unit_of(name)].add(unit_of(target))
    assert cycles(edges) == []


def test_no_private_name_is_imported_from_another_module():
    private = [f"{name}:{line} imports {target}.{imported}" for name, found in graph().items()
               for target, imported, line in found if imported.startswith("_") and not imported.endswith("__") and target != name]
    assert not private, "\n".join(private)


def test_the_checker_finds_a_cycle_and_an_upward_import():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert layer_of("hrn_pyg.sim.step") > layer_of("hrn_pyg.nn.hrn") > layer_of("hrn_pyg.data.graph")
    assert layer_of("hrn_pyg.rl.ppo") > layer_of("hrn_pyg.sampling.sample")
    assert layer_of("hrn_pyg") == layer_of("hrn_pyg.cli") == len(LAYERS) - 1


def test_a_module_in_no_layer_is_reported():
    for name in ("hrn_pyg.newmodule", "hrn_pyg.newpackage.part", "hrn_pyg.simulator"):
        with pytest.raises(AssertionError, match="in no layer"):
            layer_of(name)


def test_imports_by_name_are_seen(tmp_path):
    modules = {"hrn_pyg.cli", "hrn_pyg.rl.ppo", "hrn_pyg.data.io"}
    literal = tmp_path / "literal.py"
    literal.write_text("import importlib\n"
                       "from importlib import import_module\n"
                       "def f():\n"
                       "    importlib.import_module('hrn_pyg.cli')\n"
                       "    import_module('hrn_pyg.rl.ppo')\n"
                       "    __import__('hrn_pyg.data.io')\n"
                       "    importlib.import_module('numpy')\n"
                       "    return 'hrn_pyg.rl.ppo'\n")
    assert sorted(imports_of("hrn_pyg.data.probe", literal, modules)) == [
        ("hrn_pyg.cli", "", 4), ("hrn_pyg.data.io", "", 6), ("hrn_pyg.rl.ppo", "", 5)]
    computed = tmp_path / "computed.py"
    computed.write_text("import importlib\n"
                        "TABLE = {'a': 'hrn_pyg.cli', 'b': 'hrn_pyg.rl.ppo', 'c': 'not.a.module'}\n"
                        "def f(key):\n"
                        "    return importlib.import_module(TABLE[key])\n")
    assert sorted(imports_of("hrn_pyg.data.probe", computed, modules)) == [
        ("hrn_pyg.cli", "", 2), ("hrn_pyg.rl.ppo", "", 2)]


def test_the_command_table_of_cli_counts_as_its_imports():
    found = {target for target, _, _ in graph()["hrn_pyg.cli"]}
    assert {"hrn_pyg.rl.ppo", "hrn_pyg.sampling.cli", "hrn_pyg.checkpoints.cli", "hrn_pyg.demo"} <= found


def experiments_imported(path: Path) -> list[tuple[str, int]]:
    """``(module, line)`` of every import of the ``experiments`` folder in one file: statements
    (inside functions too), ``import_module`` / ``__import__`` of a literal name, and any string
    naming an ``experiments.`` module where the file imports a computed name."""
    tree = ast.parse(path.read_text(), str(path))
    arguments = [a for a in map(_dynamic_import, ast.walk(tree)) if a is not None]
    computed = any(not (isinstance(a, ast.Constant) and isinstance(a.value, str)) for a in arguments)
    found = []
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level:
            names = [node.module or ""]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            argument = node in arguments
            if argument or computed:
                names = [node.value] if argument or node.value.startswith("experiments.") else []
        found += [(n, node.lineno) for n in names if n.split(".")[0] == "experiments"]
    return found


def test_the_package_never_imports_the_experiments():
    """``experiments/`` sits beside the package and is not in the wheel: a library module that
    imported it would fail once installed."""
    offenders = [f"{name}:{line} imports {target}" for name, path in module_files().items()
                 for target, line in experiments_imported(path)]
    assert not offenders, "\n".join(offenders)


def test_the_experiments_checker_sees_each_kind_of_import(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("import importlib\n"
                     "import experiments.rl.stats\n"
                     "from experiments.rl import sweep\n"
                     "def f(name):\n"
                     "    from experiments.rl.summary import task_summary\n"
                     "    importlib.import_module('experiments.rl.clone')\n"
                     "    return importlib.import_module(name), 'experiments.rl.planners', 'hrn_pyg.rl.env'\n")
    assert sorted(experiments_imported(probe)) == [
        ("experiments.rl", 3), ("experiments.rl.clone", 6), ("experiments.rl.planners", 7),
        ("experiments.rl.stats", 2), ("experiments.rl.summary", 5)]


def test_the_three_stages_of_a_step_are_chained_in_one_place():
    """``build_inputs``, ``run_network`` and ``decode`` are called only by
    :func:`hrn_pyg.sim.step.predict`; every other caller goes through it (and
    :func:`hrn_pyg.sim.step.hierarchy_constants` reads the first stage's inputs once a rollout
    for the constants it keeps)."""
    calls = []
    for name, path in module_files().items():
        tree = ast.parse(path.read_text(), str(path))
        for function in ast.walk(tree):
            if not isinstance(function, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(function):
                if isinstance(node, ast.Call):
                    callee = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
                    if callee in ("build_inputs", "run_network", "decode"):
                        calls.append((name, function.name, callee))
    assert sorted(set(calls)) == [("hrn_pyg.sim.step", "hierarchy_constants", "build_inputs")] + [
        ("hrn_pyg.sim.step", "predict", c) for c in ("build_inputs", "decode", "run_network")]
