"""What the command lines of the package share: a help formatter that shows every default, old
spellings of renamed options that still work with a one-line warning, the ``--no-progress``
switch and its progress bar, and help texts read from a config's ``Attributes:`` docstring.

Imports nothing heavy (argparse only; tqdm when a bar is made), so a command can check its
input before torch is loaded.
"""

from __future__ import annotations

import argparse
import inspect
import re
import sys
from collections.abc import Sequence
from typing import Any


def shows_default(default: Any) -> bool:
    """Whether a default is worth showing: not None, False, an empty string or list, or suppressed."""
    if default is None or default is False or default is argparse.SUPPRESS:
        return False
    return not (isinstance(default, (str, list, tuple)) and len(default) == 0)


def shown_default(default: Any) -> str:
    """A default as ``--help`` shows it: a list as its items separated by spaces, else ``str``."""
    if isinstance(default, (list, tuple)):
        return " ".join(map(str, default))
    return str(default)


class HelpFormatter(argparse.HelpFormatter):
    """argparse's formatter with ``(default: X)`` after the help of every option whose default
    :func:`shows_default` (what ``ArgumentDefaultsHelpFormatter`` does, without ``None`` and
    ``False``). An option without a help text shows nothing, its default included: give each one."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if shows_default(action.default) and action.option_strings:
            suffix = f"(default: {shown_default(action.default)})".replace("%", "%%")
            text = f"{text} {suffix}" if text else suffix
        return text


class Renamed(argparse.Action):
    """The old spelling of a renamed option: hidden from ``--help``, stores into the new
    option's destination and warns in one line on stderr."""

    def __init__(self, option_strings: Sequence[str], dest: str, new: str = "", **kwargs: Any) -> None:
        kwargs["help"] = argparse.SUPPRESS
        kwargs["default"] = argparse.SUPPRESS
        super().__init__(option_strings, dest, **kwargs)
        self.new = new

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        print(f"{parser.prog}: warning: {option_string} is deprecated and goes in the next release; "
              f"use {self.new}", file=sys.stderr)
        setattr(namespace, self.dest, values)


class Moved(argparse.Action):
    """An option that went to another command: hidden from ``--help``; using it ends the command
    with one line naming where the option lives now (exit 2)."""

    def __init__(self, option_strings: Sequence[str], dest: str, where: str = "", **kwargs: Any) -> None:
        kwargs.update(help=argparse.SUPPRESS, default=argparse.SUPPRESS, nargs="?")
        super().__init__(option_strings, dest, **kwargs)
        self.where = where

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        parser.exit(2, f"{parser.prog}: error: {option_string} belongs to {self.where}\n")


def add_moved(parser: argparse.ArgumentParser, options: Sequence[str], where: str) -> None:
    """Let ``options``, which moved to another command, say so in one line (:class:`Moved`)."""
    for option in options:
        parser.add_argument(option, action=Moved, where=where, dest=f"moved_{option.strip('-').replace('-', '_')}")


class Removed(argparse.Action):
    """An option that was removed: hidden from ``--help``; given (with or without a value), it
    warns in one line on stderr that it is ignored and goes in the next release."""

    def __init__(self, option_strings: Sequence[str], dest: str, why: str = "", **kwargs: Any) -> None:
        kwargs.update(help=argparse.SUPPRESS, default=argparse.SUPPRESS, nargs="?")
        super().__init__(option_strings, dest, **kwargs)
        self.why = why

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        print(f"{parser.prog}: warning: {option_string} was removed ({self.why}) and is ignored; "
              "it is refused from the next release", file=sys.stderr)


def add_removed(parser: argparse.ArgumentParser, options: Sequence[str], why: str) -> None:
    """Let ``options``, which were removed, warn and be ignored for one release (:class:`Removed`)."""
    for option in options:
        parser.add_argument(option, action=Removed, why=why, dest=f"removed_{option.strip('-').replace('-', '_')}")


def add_renamed(parser: argparse.ArgumentParser, old: str, new: str) -> None:
    """Let ``old`` spell the option ``new`` that ``parser`` already has (same destination, type,
    count and choices; in the same mutually exclusive group), with :class:`Renamed`'s warning."""
    action = next(a for a in parser._actions if new in a.option_strings)
    container: Any = next((g for g in parser._mutually_exclusive_groups if action in g._group_actions), parser)
    kwargs: dict[str, Any] = {"nargs": 0} if action.nargs == 0 else {
        "nargs": action.nargs, "type": action.type, "choices": action.choices, "metavar": action.metavar}
    container.add_argument(old, action=Renamed, new=new, dest=action.dest, **kwargs)


def renamed_options(parser: argparse.ArgumentParser) -> dict[str, str]:
    """``{old spelling: new}`` of the :class:`Renamed` options of ``parser``."""
    return {s: a.new for a in parser._actions if isinstance(a, Renamed) for s in a.option_strings}


def run_reporting_errors(prog: str, run: Any, args: argparse.Namespace) -> int:
    """``run(args)`` as a command runs it: bad input (``ValueError``, ``FileNotFoundError``)
    becomes one line ``<prog>: error: ...`` on stderr and exit code 2, an interrupt exit code 130."""
    try:
        return int(run(args) or 0)
    except (ValueError, FileNotFoundError) as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; finished work is kept", file=sys.stderr)
        return 130


def add_no_progress(parser: argparse.ArgumentParser) -> None:
    """``--no-progress``: the command draws no progress bar (``args.no_progress``)."""
    parser.add_argument("--no-progress", action="store_true", help="draw no progress bar on stderr")


def add_strict(parser: argparse.ArgumentParser, what: str = "a scene") -> None:
    """``--strict``: ``what`` outside a model's training domain is an error (exit 2), not a
    one-line warning (``args.strict``)."""
    parser.add_argument("--strict", action="store_true",
                        help=f"{what} outside what the model was trained on is an error (exit 2), "
                             "not a one-line warning")


class LineProgress:
    """A progress bar's interface written as lines on stderr, for a log rather than a terminal:
    ``<desc>: <n>/<total> <unit> (<postfix>)`` when a stage begins (:meth:`set_postfix_str` with
    a new text), at each tenth of a ``total`` over 10 (a long loop) and at the end."""

    def __init__(self, total: int, desc: str, unit: str, initial: int = 0, stream: Any = None) -> None:
        self.total, self.desc, self.unit, self.n = int(total), desc, unit, int(initial)
        self.postfix, self.stream, self._said = "", stream, ""
        self._tenth = self._tenths()

    def _tenths(self) -> int:
        return 10 * self.n // self.total if self.total > 0 else 0

    def _say(self) -> None:
        text = f"{self.desc}: {self.n}/{self.total} {self.unit}" + (f" ({self.postfix})" if self.postfix else "")
        if text != self._said:
            print(text, file=self.stream or sys.stderr, flush=True)
            self._said = text

    def update(self, n: int = 1) -> None:
        self.n += int(n)
        if self.total > 10 and self._tenths() != self._tenth:
            self._tenth = self._tenths()
            self._say()

    def set_postfix_str(self, text: str, refresh: bool = True) -> None:
        if text != self.postfix:
            self.postfix = text
            self._say()

    def set_postfix(self, **values: Any) -> None:
        self.postfix = ", ".join(f"{k}={v}" for k, v in values.items())

    def close(self) -> None:
        self._say()


class _NoProgress:
    """A progress bar that draws nothing (``--no-progress``)."""

    def update(self, n: int = 1) -> None:
        pass

    def set_postfix_str(self, text: str, refresh: bool = True) -> None:
        pass

    def set_postfix(self, **values: Any) -> None:
        pass

    def close(self) -> None:
        pass


def progress_bar(total: int, desc: str, unit: str, enabled: bool = True, initial: int = 0) -> Any:
    """A command's progress on stderr: a tqdm bar where stderr is a terminal, else
    :class:`LineProgress` (one line per stage and per tenth, never a bar drawn into a log file);
    nothing when ``enabled`` is False."""
    if not enabled:
        return _NoProgress()
    if not sys.stderr.isatty():
        return LineProgress(total, desc, unit, initial)
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, initial=initial, leave=False, dynamic_ncols=True)


def attribute_help(cls: type) -> dict[str, str]:
    """``{field: first sentence}`` from the ``Attributes:`` section of ``cls``'s docstring (one
    entry per name of a ``a, b: text`` line; continuation lines joined)."""
    doc = inspect.getdoc(cls) or ""
    _, found, section = doc.partition("Attributes:\n")
    if not found:
        return {}
    entries: dict[str, str] = {}
    names: list[str] = []
    for line in section.splitlines():
        if not line.strip():
            continue
        match = re.match(r"^ {4}(\w[\w, ]*):\s*(.*)$", line)  # a name at the indent of 4, not deeper
        if match:
            names = [n.strip() for n in match.group(1).split(",")]
            for name in names:
                entries[name] = match.group(2)
        elif line.startswith("        ") and names:
            for name in names:
                entries[name] += " " + line.strip()
        elif not line.startswith(" "):
            break
    return {name: first_sentence(text) for name, text in entries.items()}


def first_sentence(text: str) -> str:
    """The text up to its first full stop followed by a space (or all of it), without the stop;
    reST roles (``:class:`X```) and double backquotes shown plain."""
    text = re.sub(r":\w+:`~?([^`]+)`", r"\1", text).replace("``", "")
    head = re.split(r"\.\s", text + " ", maxsplit=1)[0].rstrip(". ")
    return head.replace("%", "%%")
