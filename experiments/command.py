"""The command line of an experiment script: a parser from a module's ``add_arguments`` and its
``run``, with the package's conventions (:class:`~hrn_pyg.utils.options.HelpFormatter` shows
every default; bad input is one line on stderr and exit code 2, as ``hrn-pyg`` answers it)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from hrn_pyg.utils.options import HelpFormatter, run_reporting_errors


def build_parser(prog: str, description: str,
                 add_arguments: Callable[[argparse.ArgumentParser], None]) -> argparse.ArgumentParser:
    """The parser of a script: ``prog`` as its name, ``add_arguments`` filling it in."""
    parser = argparse.ArgumentParser(prog=prog, description=description, formatter_class=HelpFormatter)
    add_arguments(parser)
    return parser


def script_main(prog: str, description: str, add_arguments: Callable[[argparse.ArgumentParser], None],
                run: Callable[[argparse.Namespace], int], argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (None: ``sys.argv[1:]``) and call ``run``; ``ValueError`` and
    ``FileNotFoundError`` become one line ``<prog>: error: ...`` and exit code 2, an interrupt
    exit code 130."""
    args = build_parser(prog, description, add_arguments).parse_args(sys.argv[1:] if argv is None else list(argv))
    return run_reporting_errors(prog, run, args)
