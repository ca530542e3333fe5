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


def test_progress_off_a_terminal_is_one_line_per_stage_and_tenth(capsys):
    """stderr captured (no terminal): no bar, a line per stage, per tenth of a long loop and at
    the end; --no-progress: nothing."""
    from hrn_pyg.utils.options import LineProgress, progress_bar

    bar = progress_bar(3, "sample", "stage")
    assert isinstance(bar, LineProgress)
    for stage in ("16 futures of 30 steps", "figure", "animation"):
        bar.set_postfix_str(stage)
        bar.update()
    bar.close()
    lines = capsys.readouterr().err.splitlines()
    assert lines == ["sample: 0/3 stage (16 futures of 30 steps)", "sample: 1/3 stage (figure)",
                     "sample: 2/3 stage (animation)", "sample: 3/3 stage (animation)"]
    long = progress_bar(200, "train ours", "step", initial=100)
    for _ in range(100):
        long.update()
        long.set_postfix(loss=0.5)
    long.close()
    lines = capsys.readouterr().err.splitlines()
    assert lines == [f"train ours: {n}/200 step (loss=0.5)" for n in range(120, 201, 20)]
    assert "\r" not in "".join(lines)
    quiet = progress_bar(3, "sample", "stage", enabled=False)
    quiet.set_postfix_str("figure")
    quiet.update()
    quiet.close()
    assert capsys.readouterr().err == ""
