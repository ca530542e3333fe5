"""``attribute_help``: one entry per documented attribute, its first sentence, continuation lines
joined, even where a continuation line holds a colon."""

from dataclasses import dataclass

from hrn_pyg.utils.options import attribute_help, first_sentence


@dataclass
class _Documented:
    """A config.

    Attributes:
        alpha, beta: two numbers that share a line
            of help. More.
        gamma: a long entry whose continuation
            line has words then a colon: which is not a new name. After.
    """

    alpha: int = 0
    beta: int = 0
    gamma: int = 0


def test_attribute_help_keeps_a_continuation_line_with_a_colon():
    found = attribute_help(_Documented)
    assert set(found) == {"alpha", "beta", "gamma"}
    assert found["alpha"] == found["beta"] == "two numbers that share a line of help"
    assert found["gamma"] == "a long entry whose continuation line has words then a colon: which is not a new name"


def test_first_sentence_shows_roles_plain():
    assert first_sentence("see :func:`~a.b.c` and ``x``. Then more.") == "see a.b.c and x"
