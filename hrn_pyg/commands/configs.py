"""Config dataclasses read from their source, without importing their modules.

A command's options mirror a config dataclass (``TrainConfig``, ``HRNConfig``, ``PPOConfig``,
``PlannerConfig``) whose module imports torch. :func:`config_fields` parses that module's file
with :mod:`ast` instead, so ``--help`` shows the dataclass's own defaults and field help and the
defaults are written once, in the dataclass. A default must be a literal, a tuple, list or dict
of them, ``field(default=...)``, or a module-level constant (of that module, or imported into
it from another module of the package) of the same kind; ``tests/commands/test_configs.py``
holds every config read here to the imported dataclass.
"""

from __future__ import annotations

import ast
import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hrn_pyg.utils.options import attribute_help

PACKAGE = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class SourceField:
    """One dataclass field as written: ``name``, ``default``, the annotation's text ``kind``."""

    name: str
    default: Any
    kind: str


@functools.lru_cache(maxsize=None)
def _module(module: str) -> ast.Module:
    """The parsed source of ``hrn_pyg.<...>`` (a package's ``__init__.py`` where it is one)."""
    parts = module.split(".")
    if parts[0] != "hrn_pyg":
        raise ValueError(f"not a module of hrn_pyg: {module!r}")
    path = PACKAGE.joinpath(*parts[1:])
    path = path / "__init__.py" if path.is_dir() else path.with_suffix(".py")
    return ast.parse(path.read_text(encoding="utf-8"), filename=str(path))


def _value(node: ast.expr, module: str) -> Any:
    """The value of a default or constant expression of ``module``."""
    if isinstance(node, ast.Name):
        return source_constant(module, node.id)
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "field":
        given = {k.arg: k.value for k in node.keywords}
        if "default" not in given:
            raise ValueError(f"{module}: a field without a default= is not read from source")
        return _value(given["default"], module)
    if isinstance(node, (ast.Tuple, ast.List)):
        items = [_value(e, module) for e in node.elts]
        return tuple(items) if isinstance(node, ast.Tuple) else items
    if isinstance(node, ast.Dict):
        return {_value(k, module): _value(v, module) for k, v in zip(node.keys, node.values)}
    return ast.literal_eval(node)


def source_constant(module: str, name: str) -> Any:
    """The value of module-level constant ``name`` of ``module`` (followed through a
    ``from hrn_pyg... import name``)."""
    for node in _module(module).body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == name for t in node.targets):
            return _value(node.value, module)
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and node.target.id == name:
            return _value(node.value, module)
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("hrn_pyg"):
            if any((a.asname or a.name) == name for a in node.names):
                original = next(a.name for a in node.names if (a.asname or a.name) == name)
                return source_constant(node.module, original)
    raise ValueError(f"{module} has no module-level constant {name!r}")


def _class(module: str, name: str) -> ast.ClassDef:
    for node in _module(module).body:
        if isinstance(node, ast.ClassDef) and node.name == name:
            return node
    raise ValueError(f"{module} has no class {name!r}")


def config_fields(module: str, name: str) -> list[SourceField]:
    """The fields of dataclass ``name`` of ``module``, in order, as its source writes them
    (class variables, ``ClassVar`` annotations, left out)."""
    out = []
    for node in _class(module, name).body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            kind = ast.unparse(node.annotation)
            if kind.startswith("ClassVar"):
                continue
            if node.value is None:
                raise ValueError(f"{module}.{name}.{node.target.id} has no default")
            out.append(SourceField(node.target.id, _value(node.value, module), kind))
    return out


def config_help(module: str, name: str) -> dict[str, str]:
    """:func:`~hrn_pyg.utils.options.attribute_help` of dataclass ``name`` of ``module``."""
    doc = ast.get_docstring(_class(module, name)) or ""
    return attribute_help(type(name, (), {"__doc__": doc}))
