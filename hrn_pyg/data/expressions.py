r"""Arithmetic in scene files: values derived from settings and from a seed's random draws.

A value may be a string holding one expression in Python's grammar without Python's power:
numbers, lists (``numpy`` arrays, element-wise arithmetic), names bound earlier,
``+ - * / ** %``, comparisons, ``and``/``or``/``not``, ``a if c else b``, constant or named
indexing, and the functions of :data:`FUNCTIONS`. Two draw from the seed's stream in
evaluation order:

* ``uniform(low, high)`` or ``uniform(pair)``: :math:`u \sim U[\text{low}, \text{high})`;
  ``uniform(low, high, shape)`` an array of them;
* ``integer(low, high)`` or ``integer(pair)``: an integer in :math:`\{\text{low}, \dots, \text{high}\}`.

The evaluation mirrors plain ``numpy`` operation for operation, so a file gives bit for bit the
numbers of the same scene in Python. :func:`evaluate` raises ``ValueError`` naming the
expression for anything else, so a file cannot run code; text, syntax tree, array elements and
integer bits are bounded (:class:`LimitError`, a ``ValueError``); numpy overflow and invalid
operations are errors.
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

#: the longest expression (characters). The package's longest is under 150; the limit keeps
#: parsing cheap and below Python's own recursion limit (a chain of 5,000 ``-`` exhausts it).
MAX_EXPRESSION_CHARS = 1_000
#: the most nodes of an expression's syntax tree (operators, names, numbers, calls; the package's
#: largest has 42). Each node is evaluated once at a cost bounded by :data:`MAX_ELEMENTS`, so
#: this bounds an expression's time.
MAX_NODES = 300
#: the deepest nesting of an expression's syntax tree (the package's deepest is 7): evaluation
#: recurses once per level, and this keeps it far from Python's recursion limit.
MAX_DEPTH = 32
#: the most elements of an array (a list, a drawn or ``zeros`` shape, the result of an operation
#: on two arrays), checked before it is made: a scene reads a few numbers per object, and 10,000
#: float64 take 80 kB, so no expression allocates more than a few MB.
MAX_ELEMENTS = 10_000
#: the most bits of a whole number: every integer below 2^1023 converts to a float64 (whose
#: largest is just under 2^1024), so a field can take it; the time of ``**`` and ``*`` on
#: integers grows with their size (``9 ** 9 ** 9`` has 1.2e9 bits), so a power is checked
#: before it is computed.
MAX_INT_BITS = 1_023
#: an expression longer than this (characters) is shortened in error messages
SHOWN_CHARS = 80


class LimitError(ValueError):
    """An expression past one of the limits (:data:`MAX_EXPRESSION_CHARS`, :data:`MAX_NODES`,
    :data:`MAX_DEPTH`, :data:`MAX_ELEMENTS`, :data:`MAX_INT_BITS`) or a scene file past one of
    its own."""


def tree_size(tree: ast.AST) -> tuple[int, int]:
    """``(nodes, depth)`` of a syntax tree: its nodes (load/store markers excluded) and its
    deepest level (a lone number: 1), counted without recursion."""
    nodes, depth, stack = 0, 0, [(tree, 1)]
    while stack:
        node, level = stack.pop()
        nodes, depth = nodes + 1, max(depth, level)
        stack.extend((child, level + 1) for child in ast.iter_child_nodes(node)
                     if not isinstance(child, ast.expr_context))
    return nodes, depth


def count_text(count: int) -> str:
    """A count as messages write it: its digits, or ``about 10^k`` past twelve of them."""
    digits = str(count)
    return digits if len(digits) <= 12 else f"about 10^{len(digits) - 1}"


def check_elements(count: int, what: str) -> None:
    """LimitError when an array of ``count`` elements (``what`` names it) is more than
    :data:`MAX_ELEMENTS`."""
    if count > MAX_ELEMENTS:
        raise LimitError(f"{what} of {count_text(count)} elements, more than {MAX_ELEMENTS}")


def broadcast_size(*values: Any) -> int:
    """The number of elements of an operation's result on ``values`` (numbers or arrays), from
    their shapes alone; ValueError when they do not broadcast."""
    return math.prod(np.broadcast_shapes(*(np.shape(v) for v in values)))


def power_log2(base: Any, exponent: Any) -> float | None:
    """``log2 |base ** exponent|`` when both are whole numbers and the power grows (``|base| > 1``,
    ``exponent > 0``), computed without the power; None otherwise (a float power overflows at
    once, and one that does not grow stays small)."""
    whole = (int, np.integer)
    if not (isinstance(base, whole) and isinstance(exponent, whole)) or exponent <= 0 or abs(base) <= 1:
        return None
    return float(exponent) * math.log2(abs(int(base)))


def check_power(base: Any, exponent: Any) -> None:
    """LimitError when ``base ** exponent`` is a whole number of more than :data:`MAX_INT_BITS`
    bits (``log2`` of it at least that many), before it is computed."""
    log2 = power_log2(base, exponent)
    if log2 is not None and log2 >= MAX_INT_BITS:
        raise LimitError(f"** gives a whole number of about 2^{log2:.4g}, past the limit of {MAX_INT_BITS} bits")


def checked(value: Any) -> Any:
    """``value`` when it is within the limits, real and finite; LimitError for a whole number of
    more than :data:`MAX_INT_BITS` bits or an array of more than :data:`MAX_ELEMENTS` elements,
    ValueError for a complex number (a fractional power of a negative number) or an infinity or
    NaN (a float overflow, which Python's own floats do not raise)."""
    if isinstance(value, int) and value.bit_length() > MAX_INT_BITS:
        raise LimitError(f"a whole number of {value.bit_length()} bits, more than {MAX_INT_BITS}")
    if isinstance(value, complex) or np.iscomplexobj(value):
        raise ValueError("not a real number (a fractional power of a negative number?)")
    if isinstance(value, np.ndarray):
        check_elements(value.size, "an array")
    if isinstance(value, (float, np.floating, np.ndarray)) and not np.all(np.isfinite(value)):
        raise ValueError("not finite (an infinity or a NaN: an overflow, or inf - inf?)")
    return value


def _pair(args: tuple, name: str) -> tuple[Any, Any, Any]:
    """``(low, high, shape)`` of ``f(low, high[, shape])`` or ``f(pair[, shape])``."""
    if len(args) in (1, 2) and np.ndim(args[0]) == 1 and len(args[0]) == 2:
        low, high = args[0]
        return low, high, args[1] if len(args) == 2 else None
    if len(args) in (2, 3):
        return args[0], args[1], args[2] if len(args) == 3 else None
    raise ValueError(f"{name}(low, high[, shape]) or {name}(pair[, shape]), got {len(args)} argument(s)")


def _shape(shape: Any) -> tuple[int, ...] | None:
    """An array's shape from a number or a list of them (positive whole numbers), at most
    :data:`MAX_ELEMENTS` elements in all."""
    if shape is None:
        return None
    dims = np.atleast_1d(np.asarray(shape))
    if (dims.ndim != 1 or not np.issubdtype(dims.dtype, np.number) or not np.all(np.isfinite(dims))
            or not np.all(dims == np.round(dims)) or np.any(dims < 1)):
        raise ValueError(f"shape: positive integers, got {brief(np.asarray(shape))}")
    dims = tuple(int(d) for d in dims)
    check_elements(math.prod(dims), f"shape [{', '.join(count_text(d) for d in dims)}]")
    return dims


def _zeros(*shape: Any) -> np.ndarray:
    """``zeros(n, m, ...)``: an array of zeros of that shape (within :data:`MAX_ELEMENTS`)."""
    return np.zeros(_shape(list(shape)) if shape else ())


def _uniform(rng: np.random.Generator, *args: Any) -> Number:
    low, high, shape = _pair(args, "uniform")
    if np.any(np.asarray(low) > np.asarray(high)):
        raise ValueError(f"uniform: low {brief(np.asarray(low))} > high {brief(np.asarray(high))}")
    if shape is None and np.ndim(low) == 0 and np.ndim(high) == 0:
        return float(rng.uniform(float(low), float(high)))
    size = _shape(shape)
    check_elements(broadcast_size(low, high), "uniform's bounds")
    return np.asarray(rng.uniform(low, high, size=size))


def _integer(rng: np.random.Generator, *args: Any) -> int:
    low, high, shape = _pair(args, "integer")
    if shape is not None:
        raise ValueError("integer: draws one number (no shape)")
    if not (float(low) == round(float(low)) and float(high) == round(float(high))):
        raise ValueError(f"integer: whole-number bounds, got {brief(low)} and {brief(high)}")
    if low > high:
        raise ValueError(f"integer: low {brief(low)} > high {brief(high)}")
    return int(rng.integers(int(low), int(high) + 1))


def _yaw_quaternion(yaw: float) -> np.ndarray:
    return np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])


#: the functions an expression may call (besides ``uniform`` and ``integer``)
FUNCTIONS: dict[str, Callable[..., Any]] = {
    "sin": math.sin, "cos": math.cos, "tan": math.tan, "atan2": math.atan2, "sqrt": math.sqrt,
    "radians": math.radians, "degrees": math.degrees, "abs": abs, "min": min, "max": max,
    "zeros": _zeros,
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


def shown(text: str) -> str:
    """An expression as error messages quote it: its ``repr`` (one line), shortened past
    :data:`SHOWN_CHARS` characters."""
    return repr(text if len(text) <= SHOWN_CHARS else text[:SHOWN_CHARS - 3] + "...")


def one_line(message: Any) -> str:
    """A message with its runs of white space (new lines included) as single spaces."""
    return " ".join(str(message).split())


def brief(value: Any) -> str:
    """A value as error messages show it: a list for an array, on one line, shortened past
    :data:`SHOWN_CHARS` characters."""
    text = one_line(np.asarray(value).tolist() if isinstance(value, np.ndarray) else value)
    return text if len(text) <= SHOWN_CHARS else text[:SHOWN_CHARS - 3] + "..."


def _parse(text: str) -> ast.Expression:
    """The syntax tree of an expression within :data:`MAX_EXPRESSION_CHARS`, :data:`MAX_NODES`
    and :data:`MAX_DEPTH` (the length checked before parsing)."""
    if len(text) > MAX_EXPRESSION_CHARS:
        raise LimitError(f"an expression of {len(text)} characters, more than {MAX_EXPRESSION_CHARS}: {shown(text)}")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError as exc:
        raise ValueError(f"not an expression: {shown(text)} ({exc.msg})") from None
    except (RecursionError, MemoryError):
        raise LimitError(f"an expression nested too deeply to parse: {shown(text)}") from None
    nodes, depth = tree_size(tree.body)
    if nodes > MAX_NODES:
        raise LimitError(f"an expression of {nodes} parts, more than {MAX_NODES}: {shown(text)}")
    if depth > MAX_DEPTH:
        raise LimitError(f"an expression nested {depth} deep, more than {MAX_DEPTH}: {shown(text)}")
    return tree


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

    def binary(node: ast.BinOp) -> Any:
        left, right = walk(node.left), walk(node.right)
        check_elements(broadcast_size(left, right), "the result")
        if isinstance(node.op, ast.Pow):
            check_power(left, right)
        return _BINARY[type(node.op)](left, right)

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
            check_elements(sum(int(np.size(i)) for i in items), "a list")
            try:
                return np.array(items, dtype=np.float64)
            except ValueError:
                raise ValueError("a list of numbers, or of lists of one length") from None
        if isinstance(node, ast.BinOp) and type(node.op) in _BINARY:
            return checked(binary(node))
        if isinstance(node, ast.UnaryOp) and type(node.op) in _UNARY:
            return checked(_UNARY[type(node.op)](walk(node.operand)))
        if isinstance(node, ast.BoolOp):
            values = [bool(np.all(walk(v))) for v in node.values]
            return all(values) if isinstance(node.op, ast.And) else any(values)
        if isinstance(node, ast.Compare) and all(type(op) in _COMPARE for op in node.ops):
            left = walk(node.left)
            for op, right_node in zip(node.ops, node.comparators):
                right = walk(right_node)
                check_elements(broadcast_size(left, right), "a comparison")
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
                raise ValueError(f"an index must be a whole number, got {brief(index)}")
            try:
                return value[index]
            except (IndexError, TypeError):
                raise ValueError(f"index {brief(index)} out of range") from None
        if isinstance(node, ast.Call):
            return checked(call(node))
        raise ValueError(f"{type(node).__name__} is not allowed in a scene file's expression")

    try:
        with np.errstate(over="raise", divide="raise", invalid="raise"):
            value = checked(walk(tree.body))
    except ValueError as exc:
        raise (LimitError if isinstance(exc, LimitError) else ValueError)(f"{shown(text)}: {one_line(exc)}") from None
    except (TypeError, ZeroDivisionError, OverflowError, ArithmeticError) as exc:
        raise ValueError(f"{shown(text)}: {one_line(exc)}") from None
    return value
