"""Scene-file expressions: each operator and function by hand-computed values, and each limit at
its boundary (just within passes, just past fails), plus hostile expressions from hypothesis
that must end in one line of error or a finite value, quickly."""

from __future__ import annotations

import ast
import math
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hrn_pyg.data.expressions import (
    MAX_DEPTH,
    MAX_ELEMENTS,
    MAX_EXPRESSION_CHARS,
    MAX_INT_BITS,
    MAX_NODES,
    SHOWN_CHARS,
    LimitError,
    broadcast_size,
    check_elements,
    check_power,
    checked,
    count_text,
    evaluate,
    names_in,
    one_line,
    power_log2,
    shown,
    tree_size,
)

#: what an expression, however hostile, may take
SECONDS = 1.0


def ev(text: str, rng_seed: int | None = 0, **names: object) -> object:
    return evaluate(text, names, None if rng_seed is None else np.random.default_rng(rng_seed))


# -- operators and functions ----------------------------------------------------------------


@pytest.mark.parametrize("text, value", [
    ("7 + 5", 12), ("7 - 5", 2), ("7 * 5", 35), ("7 / 2", 3.5), ("2 ** 10", 1024), ("7 % 5", 2),
    ("-3", -3), ("+3", 3), ("2 - 3 - 4", -5), ("2 ** 3 ** 2", 512), ("1 + 2 * 3", 7),
    ("1 < 2", True), ("2 < 2", False), ("2 <= 2", True), ("3 <= 2", False), ("3 > 2", True),
    ("2 > 2", False), ("2 >= 2", True), ("1 >= 2", False), ("1 == 1", True), ("1 == 2", False),
    ("1 != 2", True), ("1 != 1", False), ("1 < 2 < 3", True), ("1 < 3 < 2", False), ("3 < 1 < 2", False),
    ("not 0", True), ("not 1", False), ("1 and 0", False), ("1 and 1", True), ("0 or 0", False), ("0 or 1", True),
    ("5 if 1 else 6", 5), ("5 if 0 else 6", 6), ("[4, 5, 6][1]", 5.0), ("[4, 5, 6][2.0]", 6.0), ("[4, 5, 6][-1]", 6.0),
    ("a * 2", 6), ("pi", math.pi), ("abs(-2)", 2), ("min(3, 1, 2)", 1), ("max(3, 1, 2)", 3),
    ("sqrt(16)", 4.0), ("radians(180)", math.pi), ("degrees(pi)", 180.0), ("sin(0)", 0.0), ("cos(0)", 1.0),
    ("tan(0)", 0.0), ("atan2(1, 1)", math.pi / 4),
])
def test_each_operator_and_function_gives_its_value(text: str, value: object) -> None:
    result = ev(text, a=3)
    assert result == value and type(result) is not complex
    if isinstance(value, bool):
        assert result is value


def test_lists_are_float_arrays_element_wise() -> None:
    value = ev("[1, 2] * [3, 4] + 1")
    assert value.dtype == np.float64 and value.tolist() == [4.0, 9.0]
    assert ev("[[1, 2], [3, 4]]").shape == (2, 2)
    assert ev("[a, a]", a=np.array([1.0, 2.0])).tolist() == [[1.0, 2.0], [1.0, 2.0]]
    assert ev("[1, 2] < [2, 2]") is False and ev("[1, 2] < [2, 3]") is True
    assert ev("zeros(3, 2)").tolist() == [[0.0, 0.0]] * 3 and ev("zeros(2)").tolist() == [0.0, 0.0]
    assert ev("yaw_quaternion(pi)") == pytest.approx([0.0, 0.0, 1.0, 0.0])
    with pytest.raises(ValueError, match="lists of one length"):
        ev("[[1, 2], [3]]")


def test_draws_follow_numpy_call_for_call() -> None:
    rng = np.random.default_rng(5)
    assert ev("uniform(1, 2)", 5) == float(rng.uniform(1.0, 2.0))
    rng = np.random.default_rng(5)
    assert ev("uniform([1, 2])", 5) == float(rng.uniform(1.0, 2.0))
    rng = np.random.default_rng(5)
    assert ev("uniform(0, 1, [2, 3])", 5).tolist() == rng.uniform(0, 1, size=(2, 3)).tolist()
    rng = np.random.default_rng(5)
    assert ev("uniform([0, 1], 4)", 5).tolist() == rng.uniform(0, 1, size=(4,)).tolist()
    rng = np.random.default_rng(5)
    assert ev("integer(1, 6)", 5) == int(rng.integers(1, 7))
    assert ev("integer([3, 3])") == 3 and isinstance(ev("integer(2, 2)"), int)
    assert ev("uniform(2, 2)") == 2.0


@pytest.mark.parametrize("text, message", [
    ("uniform(1)", "uniform\\(low, high"), ("uniform(2, 1)", "low \\[?2"), ("integer(2, 1)", "low 2 > high 1"),
    ("integer(0, 1, 3)", "no shape"), ("integer(0.5, 2)", "whole-number"), ("uniform(0, 1, 0)", "positive integers"),
    ("uniform(0, 1, [2.5])", "positive integers"), ("zeros(0)", "positive integers"),
    ("zeros(2.5)", "positive integers"),
    ("b", "unknown name 'b'"), ("f(1)", "unknown function 'f'"), ("a.real", "Attribute is not allowed"),
    ("min(a=1)", "plain calls"), ("[1, 2][5]", "out of range"), ("[1, 2][0.5]", "whole number"),
    ("[1, 2][0:1]", "Slice is not allowed"), ("'text'", "Constant is not allowed"), ("1 +", "not an expression"),
    ("1 / 0", "division by zero"), ("[1] / [0]", "divide by zero"), ("[1e308] * [10]", "overflow"),
    ("(-8) ** 0.5", "not a real number"), ("1e308 * 10", "not finite"), ("1e999 - 1e999", "not finite"),
    ("sqrt(-1)", "math domain"), ("[1, 2] + [1, 2, 3]", "broadcast"), ("1 if 1 < 2 else", "not an expression"),
])
def test_mistakes_are_one_line_value_errors_naming_the_expression(text: str, message: str) -> None:
    with pytest.raises(ValueError, match=message) as info:
        ev(text, a=1)
    assert "\n" not in str(info.value) and repr(text) in str(info.value)


def test_a_draw_needs_a_random_stream() -> None:
    with pytest.raises(ValueError, match="draws at random"):
        ev("uniform(0, 1)", None)
    assert ev("1 + 1", None) == 2


def test_names_in_leaves_out_functions() -> None:
    assert names_in("uniform(a, b) + sin(c) * pi") == {"a", "b", "c", "pi"}


def test_messages_are_one_line_and_short() -> None:
    assert one_line("a\n  b\tc ") == "a b c"
    assert shown("x" * SHOWN_CHARS) == repr("x" * SHOWN_CHARS)
    assert shown("x" * (SHOWN_CHARS + 1)) == repr("x" * (SHOWN_CHARS - 3) + "...")
    assert shown("a\nb") == "'a\\nb'"
    assert count_text(10**12 - 1) == "999999999999" and count_text(10**12) == "about 10^12"
    with pytest.raises(ValueError) as info:
        ev("1 +\n  unknown")
    assert "\n" not in str(info.value)


# -- limits, each at its boundary ------------------------------------------------------------


def test_length_limit() -> None:
    assert ev("1".ljust(MAX_EXPRESSION_CHARS)) == 1
    with pytest.raises(LimitError, match=f"{MAX_EXPRESSION_CHARS + 1} characters, more than {MAX_EXPRESSION_CHARS}"):
        ev("1".ljust(MAX_EXPRESSION_CHARS + 1))
    with pytest.raises(LimitError, match="characters"):
        names_in("-" * 5000 + "1")  # would exhaust the parser's recursion


def test_tree_size_counts_nodes_and_levels() -> None:
    assert tree_size(ast.parse("1", mode="eval").body) == (1, 1)
    assert tree_size(ast.parse("a + 1", mode="eval").body) == (4, 2)  # BinOp, Name, Add, Constant
    assert tree_size(ast.parse("-(-1)", mode="eval").body) == (5, 3)
    assert tree_size(ast.parse("[1, 2, 3]", mode="eval").body) == (4, 2)


def test_node_limit() -> None:
    within = "[" + ", ".join(["1"] * (MAX_NODES - 1)) + "]"  # a list and its numbers
    assert ev(within).shape == (MAX_NODES - 1,)
    with pytest.raises(LimitError, match=f"{MAX_NODES + 1} parts, more than {MAX_NODES}"):
        ev("[" + ", ".join(["1"] * MAX_NODES) + "]")


def test_depth_limit() -> None:
    assert ev("-" * (MAX_DEPTH - 1) + "1") == (-1) ** (MAX_DEPTH - 1)
    with pytest.raises(LimitError, match=f"nested {MAX_DEPTH + 1} deep, more than {MAX_DEPTH}"):
        ev("-" * MAX_DEPTH + "1")


def test_element_limit_on_shapes_lists_and_results() -> None:
    assert ev(f"zeros({MAX_ELEMENTS})").size == MAX_ELEMENTS
    assert ev("uniform(0, 1, [100, 100])").shape == (100, 100)
    with pytest.raises(LimitError, match=f"shape \\[{MAX_ELEMENTS + 1}\\] of {MAX_ELEMENTS + 1} elements"):
        ev(f"zeros({MAX_ELEMENTS + 1})")
    with pytest.raises(LimitError, match="shape \\[100, 101\\] of 10100 elements"):
        ev("uniform(0, 1, [100, 101])")
    with pytest.raises(LimitError, match="about 10\\^20 elements"):
        ev("uniform(0, 1, [1e10, 1e10])")
    half = np.zeros(MAX_ELEMENTS // 2)
    assert ev("[a, b]", a=half, b=half).size == MAX_ELEMENTS
    with pytest.raises(LimitError, match=f"a list of {MAX_ELEMENTS + 1} elements"):
        ev("[a, b]", a=half, b=np.zeros(MAX_ELEMENTS // 2 + 1))
    column, row, wide = np.zeros((100, 1)), np.zeros((1, 100)), np.zeros((1, 101))
    assert ev("a + b", a=column, b=row).shape == (100, 100)
    with pytest.raises(LimitError, match="the result of 10100 elements"):
        ev("a + b", a=column, b=wide)
    with pytest.raises(LimitError, match="a comparison of 10100 elements"):
        ev("a < b", a=column, b=wide)
    assert ev("uniform(a, b)", a=column, b=row + 1).shape == (100, 100)
    with pytest.raises(LimitError, match="uniform's bounds of 10100 elements"):
        ev("uniform(a, b)", a=column, b=wide + 1)


def test_element_checks() -> None:
    check_elements(MAX_ELEMENTS, "x")
    with pytest.raises(LimitError, match=f"x of {MAX_ELEMENTS + 1} elements, more than {MAX_ELEMENTS}"):
        check_elements(MAX_ELEMENTS + 1, "x")
    assert broadcast_size(np.zeros((3, 1)), np.zeros(4)) == 12 and broadcast_size(2, 3.0) == 1


def test_power_is_bounded_before_it_is_computed() -> None:
    assert power_log2(2, 10) == 10.0 and power_log2(8, 3) == 9.0 and power_log2(-4, 3) == 6.0
    assert power_log2(np.int64(2), 5) == 5.0
    for base, exponent in ((1, 10**9), (-1, 10**9), (0, 10**9), (2, 0), (2, -3), (2.0, 10**9), (2, 10.0)):
        assert power_log2(base, exponent) is None
    check_power(2, MAX_INT_BITS - 1)
    with pytest.raises(LimitError, match=f"about 2\\^{MAX_INT_BITS}, past the limit of {MAX_INT_BITS} bits"):
        check_power(2, MAX_INT_BITS)
    assert ev(f"2 ** {MAX_INT_BITS - 1}") == 2 ** (MAX_INT_BITS - 1)
    assert ev(f"(-2) ** {MAX_INT_BITS - 1}") == (-2) ** (MAX_INT_BITS - 1)
    assert ev("(-2) ** 1021") == -(2**1021)
    assert ev("3 ** 645") == 3**645 and (3**645).bit_length() == MAX_INT_BITS
    for text in (f"2 ** {MAX_INT_BITS}", "3 ** 646", "9 ** 9 ** 9", "2 ** 2 ** 100", "10 ** 10 ** 10"):
        start = time.perf_counter()
        with pytest.raises(LimitError, match="whole number"):
            ev(text)
        assert time.perf_counter() - start < 0.1
    assert ev("1 ** 10 ** 300") == 1 and ev("2 ** -2000") == 0.0


def test_whole_numbers_are_bounded_after_each_operation() -> None:
    assert checked(2**MAX_INT_BITS - 1) == 2**MAX_INT_BITS - 1
    with pytest.raises(LimitError, match=f"{MAX_INT_BITS + 1} bits, more than {MAX_INT_BITS}"):
        checked(2**MAX_INT_BITS)
    assert ev("2 ** 1000 * 2 ** 22") == 2**1022 and float(2**MAX_INT_BITS - 1) == 2.0**MAX_INT_BITS
    with pytest.raises(LimitError, match="1024 bits"):
        ev("2 ** 1000 * 2 ** 23")
    with pytest.raises(LimitError, match="1024 bits"):
        ev("2 ** 1022 + 2 ** 1022")
    with pytest.raises(LimitError, match="1024 bits"):
        ev("-(2 ** 1022) - 2 ** 1022")
    with pytest.raises(LimitError, match="bits"):
        ev("max(2 ** 1022 * 2, 1)")
    assert checked(np.zeros(MAX_ELEMENTS)).size == MAX_ELEMENTS
    with pytest.raises(LimitError):
        checked(np.zeros(MAX_ELEMENTS + 1))
    with pytest.raises(ValueError, match="not a real number"):
        checked(1j)
    with pytest.raises(ValueError, match="not finite"):
        checked(np.array([1.0, np.nan]))
    assert checked(1.5) == 1.5 and checked(True) is True


# -- hostile expressions ----------------------------------------------------------------------

_ATOMS = st.sampled_from(["0", "1", "2", "9", "-1", "0.5", "1e308", "1e-308", "10 ** 300", "99999999999", "1e10",
                          "a", "b", "pi", "[1, 2]", "[[1], [2]]", "zeros(100, 100)", "uniform(0, 1)", "integer(0, 9)"])


def _combine(children: st.SearchStrategy[str]) -> st.SearchStrategy[str]:
    binary = st.tuples(children, st.sampled_from(["+", "-", "*", "/", "**", "%", "<", "=="]), children).map(
        lambda t: f"({t[0]} {t[1]} {t[2]})")
    calls = st.tuples(st.sampled_from(["zeros", "abs", "sqrt", "min", "max", "sin"]), children).map(
        lambda t: f"{t[0]}({t[1]})")
    shapes = st.tuples(children, children).map(lambda t: f"uniform(0, 1, [{t[0]}, {t[1]}])")
    return st.one_of(binary, calls, shapes, children.map(lambda c: f"-{c}"), children.map(lambda c: f"[{c}, {c}]"),
                     st.tuples(children, children).map(lambda t: f"{t[0]}[{t[1]}]"),
                     st.integers(1, 60).map(lambda n: "-" * n + "1"),
                     st.integers(1, 4).map(lambda n: "9 ** " * n + "9"))


HOSTILE = st.recursive(_ATOMS, _combine, max_leaves=12)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(HOSTILE)
def test_hostile_expressions_end_quickly_in_one_line_or_a_finite_value(text: str) -> None:
    names = {"a": np.zeros((100, 1)), "b": np.ones((1, 100)) * 3}
    start = time.perf_counter()
    try:
        value = evaluate(text, names, np.random.default_rng(0))
    except ValueError as exc:
        message = str(exc)
        assert message and "\n" not in message and len(message) < 1000
    else:
        assert np.size(value) <= MAX_ELEMENTS and np.all(np.isfinite(np.asarray(value, dtype=np.float64)))
    assert time.perf_counter() - start < SECONDS


@pytest.mark.parametrize("text, message", [
    ("integer(0, 3, [2])", "integer: draws one number (no shape)"),
    ("integer(0.5, 3)", "integer: whole-number bounds, got 0.5 and 3"),
    ("integer(1)", "integer(low, high[, shape]) or integer(pair[, shape]), got 1 argument(s)"),
    ("uniform(0, 1, [0])", "shape: positive integers, got [0.0]"),
    ("uniform(0, 1, [1.5])", "shape: positive integers, got [1.5]"),
    ("uniform(0, 1, [[2]])", "shape: positive integers, got [[2.0]]"),
    ("uniform(1, [0, 2])", "uniform: low 1 > high [0.0, 2.0]"),
    ("[1e308] * 10", "overflow encountered in multiply"),
    ("[0.0] / 0", "invalid value encountered in divide"),
    ("(-8) ** 0.5", "not a real number (a fractional power of a negative number?)"),
    ("1e308 * 10", "not finite (an infinity or a NaN: an overflow, or inf - inf?)"),
    ("foo(1)", "unknown function 'foo'; the functions are uniform, integer, sin, cos, tan, atan2, sqrt, "
               "radians, degrees, abs, min, max, zeros, yaw_quaternion"),
    ("q", "unknown name 'q'; the names known here are pi"),
    ("[[1, 2], [3]]", "a list of numbers, or of lists of one length"),
    ("[1, 2][5]", "index 5 out of range"),
    ("[1, 2][0.5]", "an index must be a whole number, got 0.5"),
])
def test_a_refused_expression_says_exactly_why(text, message):
    with pytest.raises(ValueError) as info:
        evaluate(text, {}, np.random.default_rng(0))
    assert type(info.value) is ValueError                       # a limit is a LimitError; these are not
    assert str(info.value) == f"{shown(text)}: {message}"


def test_draws_keep_their_kind_and_take_shapes_of_one():
    rng = np.random.default_rng(0)
    assert type(evaluate("uniform(0, 1)", {}, rng)) is float
    assert evaluate("uniform(0, 1, [1])", {}, rng).shape == (1,)
    assert evaluate("uniform([0, 1], 2)", {}, rng).shape == (2,)
    assert evaluate("uniform(0, [1, 2])", {}, rng).shape == (2,)
    assert evaluate("zeros()", {}, rng).shape == ()
    assert power_log2(4, 1) == 2.0 and power_log2(4, 0) is None


def test_brief_shows_numbers_as_written_and_cuts_long_text():
    from hrn_pyg.data.expressions import brief

    assert brief([1, 2.5]) == "[1, 2.5]"
    assert brief(np.array([1.0, 2.0])) == "[1.0, 2.0]"
    assert brief("y" * SHOWN_CHARS) == "y" * SHOWN_CHARS
    assert brief("x" * (SHOWN_CHARS + 1)) == "x" * (SHOWN_CHARS - 3) + "..."


def test_more_refusals_name_what_they_refuse(monkeypatch):
    rng = np.random.default_rng(0)
    assert evaluate("uniform([0, 1, 2], 5)", {}, rng).shape == (3,)   # three lower bounds, one upper
    with pytest.raises(LimitError) as info:
        evaluate("big", {"big": np.zeros(MAX_ELEMENTS + 1)}, rng)
    assert str(info.value) == f"'big': an array of {MAX_ELEMENTS + 1} elements, more than {MAX_ELEMENTS}"
    with pytest.raises(ValueError) as info:
        evaluate("q", {"a": 1.0}, rng)
    assert str(info.value) == "'q': unknown name 'q'; the names known here are a, pi"
    with pytest.raises(ValueError) as info:
        evaluate("[uniform][0](0, 1)", {}, rng)
    assert str(info.value) == "'[uniform][0](0, 1)': only plain calls of the listed functions"

    def too_deep(*args, **kwargs):
        raise RecursionError

    monkeypatch.setattr(ast, "parse", too_deep)                       # what a deeper parser would do
    with pytest.raises(LimitError) as info:
        evaluate("1 + 1", {}, rng)
    assert str(info.value) == "an expression nested too deeply to parse: '1 + 1'"
