r"""Arithmetic in scene files: values derived from settings and from a seed's random draws.

A scene file's value may be a string holding one expression, evaluated with Python's grammar
but nothing of Python's power: numbers, lists (read as ``numpy`` arrays, so arithmetic is
element-wise), names bound earlier, ``+ - * / ** %``, comparisons, ``and``/``or``/``not``,
``a if c else b``, indexing by a constant or a name, and the functions of :data:`FUNCTIONS`.
Two functions draw from the seed's random stream, in the order they are evaluated:

* ``uniform(low, high)`` or ``uniform(pair)``: :math:`u \sim U[\text{low}, \text{high})`;
  ``uniform(low, high, shape)`` an array of them (element after element from the stream);
* ``integer(low, high)`` or ``integer(pair)``: an integer in :math:`\{\text{low}, \dots, \text{high}\}`.

The evaluation mirrors plain ``numpy`` code operation for operation (the same association and
the same calls), so a scene written as a file gives bit for bit the numbers the same scene
written in Python gives.

:func:`evaluate` raises ``ValueError`` naming the expression for anything else (an unknown
name, an attribute, a call of anything not listed), so a file can never run code.
"""

from __future__ import annotations

import ast
import math
import operator
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

#: a value of an expression: a float, an int (from ``integer``) or an array
Number = float | int | np.ndarray


def _pair(args: tuple, name: str) -> tuple[Any, Any, Any]:
    """``(low, high, shape)`` of ``f(low, high[, shape])`` or ``f(pair[, shape])``."""
    if len(args) in (1, 2) and np.ndim(args[0]) == 1 and len(args[0]) == 2:
        low, high = args[0]
        return low, high, args[1] if len(args) == 2 else None
    if len(args) in (2, 3):
        return args[0], args[1], args[2] if len(args) == 3 else None
    raise ValueError(f"{name}(low, high[, shape]) or {name}(pair[, shape]), got {len(args)} argument(s)")


def _shape(shape: Any) -> tuple[int, ...] | None:
    if shape is None:
        return None
    dims = np.atleast_1d(np.asarray(shape))
    if dims.ndim != 1 or not np.all(dims == np.round(dims)) or np.any(dims < 1):
        raise ValueError(f"shape: positive integers, got {np.asarray(shape).tolist()}")
    return tuple(int(d) for d in dims)


def _uniform(rng: np.random.Generator, *args: Any) -> Number:
    low, high, shape = _pair(args, "uniform")
    if np.any(np.asarray(low) > np.asarray(high)):
        raise ValueError(f"uniform: low {np.asarray(low).tolist()} > high {np.asarray(high).tolist()}")
    if shape is None and np.ndim(low) == 0 and np.ndim(high) == 0:
        return float(rng.uniform(float(low), float(high)))
    return np.asarray(rng.uniform(low, high, size=_shape(shape)))


def _integer(rng: np.random.Generator, *args: Any) -> int:
    low, high, shape = _pair(args, "integer")
    if shape is not None:
        raise ValueError("integer: draws one number (no shape)")
    if not (float(low) == round(float(low)) and float(high) == round(float(high))):
        raise ValueError(f"integer: whole-number bounds, got {low} and {high}")
    if low > high:
        raise ValueError(f"integer: low {low} > high {high}")
    return int(rng.integers(int(low), int(high) + 1))


def _yaw_quaternion(yaw: float) -> np.ndarray:
    return np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])


#: the functions an expression may call (besides ``uniform`` and ``integer``)
FUNCTIONS: dict[str, Callable[..., Any]] = {
    "sin": math.sin, "cos": math.cos, "tan": math.tan, "atan2": math.atan2, "sqrt": math.sqrt,
    "radians": math.radians, "degrees": math.degrees, "abs": abs, "min": min, "max": max,
    "zeros": lambda *shape: np.zeros(tuple(int(s) for s in shape)),
    #: ``[x, y, z, w]`` of a turn by ``yaw`` rad about the vertical axis
    "yaw_quaternion": _yaw_quaternion,
}
#: the functions that draw from the random stream
DRAWS = ("uniform", "integer")
#: constants every expression knows
CONSTANTS: dict[str, float] = {"pi": math.pi}

_BINARY = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul, ast.Div: operator.truediv,
           ast.Pow: operator.pow, ast.Mod: operator.mod}
_UNARY = {ast.USub: operator.neg, ast.UAdd: operator.pos, ast.Not: operator.not_}
_COMPARE = {ast.Eq: operator.eq, ast.NotEq: operator.ne, ast.Lt: operator.lt, ast.LtE: operator.le,
            ast.Gt: operator.gt, ast.GtE: operator.ge}


def names_in(text: str) -> set[str]:
    """The names an expression reads (functions excluded)."""
    tree = _parse(text)
    called = {n.func.id for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}
    return {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)} - called


def _parse(text: str) -> ast.Expression:
    try:
        return ast.parse(text.strip(), mode="eval")
    except SyntaxError as exc:
        raise ValueError(f"not an expression: {text!r} ({exc.msg})") from None


def evaluate(text: str, names: Mapping[str, Any], rng: np.random.Generator | None = None) -> Any:
    """The value of the expression ``text`` with ``names`` bound; ``uniform``/``integer`` draw
    from ``rng`` (an expression that draws without one is an error).

    Lists become float arrays; a list of arrays of one length becomes a 2-D array.
    """
    tree = _parse(text)

    def call(node: ast.Call) -> Any:
        if not isinstance(node.func, ast.Name) or node.keywords:
            raise ValueError("only plain calls of the listed functions")
        name, args = node.func.id, tuple(walk(a) for a in node.args)
        if name in DRAWS:
            if rng is None:
                raise ValueError(f"{name}() draws at random: only values drawn per seed may use it")
            return (_uniform if name == "uniform" else _integer)(rng, *args)
        if name not in FUNCTIONS:
            raise ValueError(f"unknown function {name!r}; the functions are "
                             f"{', '.join([*DRAWS, *FUNCTIONS])}")
        return FUNCTIONS[name](*args)

    def walk(node: ast.AST) -> Any:
        if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) and not isinstance(node.value, bool):
            return node.value
        if isinstance(node, ast.Name):
            if node.id in names:
                return names[node.id]
            if node.id in CONSTANTS:
                return CONSTANTS[node.id]
            raise ValueError(f"unknown name {node.id!r}; the names known here are "
                             f"{', '.join(sorted([*names, *CONSTANTS]))}")
        if isinstance(node, ast.List):
            items = [walk(e) for e in node.elts]
            try:
                return np.array(items, dtype=np.float64)
            except ValueError:
                raise ValueError("a list of numbers, or of lists of one length") from None
        if isinstance(node, ast.BinOp) and type(node.op) in _BINARY:
            return _BINARY[type(node.op)](walk(node.left), walk(node.right))
        if isinstance(node, ast.UnaryOp) and type(node.op) in _UNARY:
            return _UNARY[type(node.op)](walk(node.operand))
        if isinstance(node, ast.BoolOp):
            values = [bool(np.all(walk(v))) for v in node.values]
            return all(values) if isinstance(node.op, ast.And) else any(values)
        if isinstance(node, ast.Compare) and all(type(op) in _COMPARE for op in node.ops):
            left = walk(node.left)
            for op, right_node in zip(node.ops, node.comparators):
                right = walk(right_node)
                if not bool(np.all(_COMPARE[type(op)](left, right))):
                    return False
                left = right
            return True
        if isinstance(node, ast.IfExp):
            return walk(node.body) if bool(np.all(walk(node.test))) else walk(node.orelse)
        if isinstance(node, ast.Subscript):
            value, index = walk(node.value), walk(node.slice)
            if isinstance(index, float) and index == round(index):
                index = int(index)
            if not isinstance(index, int):
                raise ValueError(f"an index must be a whole number, got {index!r}")
            try:
                return value[index]
            except (IndexError, TypeError):
                raise ValueError(f"index {index} out of range") from None
        if isinstance(node, ast.Call):
            return call(node)
        raise ValueError(f"{type(node).__name__} is not allowed in a scene file's expression")

    try:
        value = walk(tree.body)
    except ValueError as exc:
        raise ValueError(f"{text!r}: {exc}") from None
    except (TypeError, ZeroDivisionError, OverflowError, ArithmeticError) as exc:
        raise ValueError(f"{text!r}: {exc}") from None
    return value
