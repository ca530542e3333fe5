"""The command line as a whole: every sub-command's parser and the experiment scripts', walked.

One meaning per option name (the same type, count and kind wherever a name appears, and
:data:`hrn_pyg.cli.MEANINGS` saying what each shared name means), every default shown in
``--help``, ``--no-progress`` wherever a progress bar is drawn, ``--scene`` checked against the
built-in scenes, and the old spellings of renamed options still working with one warning line.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import sys
from collections import defaultdict
from pathlib import Path

import pytest

import hrn_pyg
from experiments.command import build_parser as build_script_parser
from hrn_pyg.cli import COMMANDS, MEANINGS, RENAMED, build_parser, main
from hrn_pyg.data.scene_file import SCENES
from hrn_pyg.utils.options import HelpFormatter, Moved, Renamed, renamed_options, shown_default, shows_default

ROOT = Path(hrn_pyg.__file__).resolve().parent
#: commands whose module draws a progress bar (tqdm or progress_bar) somewhere
PROGRESS = ("generate", "train", "evaluate", "sample", "calibrate", "rl", "demo")
#: the experiment scripts beside the package (``python -m <module>``), walked with the commands
SCRIPTS = ("experiments.rl.sweep", "experiments.rl.clone", "experiments.rl.summary",
           "experiments.planning.sweep", "experiments.planning.summary")
#: old spelling -> new of the experiment scripts' options
SCRIPT_RENAMED = {"experiments.rl.sweep": {"--mode": "--modes", "--seeds": "--num-seeds", "--seed-start": "--first-seed"},
                  "experiments.rl.clone": {"--steps": "--train-steps"}}


def sub_parser(command: str) -> argparse.ArgumentParser:
    parser = build_parser(command)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[command]


def script_parser(name: str) -> argparse.ArgumentParser:
    module = importlib.import_module(name)
    return build_script_parser(f"python -m {name}", module.DESCRIPTION, module.add_arguments)


def all_parsers() -> dict[str, argparse.ArgumentParser]:
    """``{"generate": parser, ..., "experiments.rl.sweep": parser}``: every sub-command and
    experiment script."""
    return {name: sub_parser(name) for name in COMMANDS} | {name: script_parser(name) for name in SCRIPTS}


@pytest.fixture(scope="module")
def parsers() -> dict[str, argparse.ArgumentParser]:
    return all_parsers()


def live_options(parser: argparse.ArgumentParser) -> list[tuple[str, argparse.Action]]:
    """``(option string, action)`` of every long option but help, the renamed spellings and the
    options that moved to another command (they take nothing and only say where they went)."""
    return [(s, a) for a in parser._actions if not isinstance(a, (Renamed, Moved, argparse._HelpAction))
            for s in a.option_strings if s.startswith("--")]


def kind(action: argparse.Action) -> tuple[str, str]:
    """What an option takes: a switch, or values of a type and a count (``append`` is one value,
    repeatable: the same meaning as one value)."""
    if action.nargs == 0:
        return ("switch", "")
    count = "one" if action.nargs in (None, "?") else "several"
    return (getattr(action.type, "__name__", "str") if action.type else "str", count)


def test_every_command_and_script_is_walked(parsers):
    assert set(parsers) == set(COMMANDS) | set(SCRIPTS)
    assert all(isinstance(p.formatter_class, type) and issubclass(p.formatter_class, HelpFormatter)
               for p in parsers.values())


def test_no_option_name_has_two_meanings(parsers):
    """The same kind of value wherever a name appears, in the commands and the scripts; what a
    name shared by two commands means is in :data:`hrn_pyg.cli.MEANINGS`."""
    kinds: dict[str, dict[tuple[str, str], list[str]]] = defaultdict(lambda: defaultdict(list))
    for command, parser in parsers.items():
        for option, action in live_options(parser):
            kinds[option][kind(action)].append(command)
    two = {option: dict(by_kind) for option, by_kind in kinds.items() if len(by_kind) > 1}
    assert not two, f"one name, two kinds of value: {two}"
    used = defaultdict(set)
    for option, by_kind in kinds.items():
        used[option] = {c for commands in by_kind.values() for c in commands if c in COMMANDS}
    shared = sorted(option for option, commands in used.items() if len(commands) > 1)
    missing = [option for option in shared if option not in MEANINGS]
    assert not missing, f"shared by two commands, without a meaning in hrn_pyg.cli.MEANINGS: {missing}"
    stale = sorted(option for option in MEANINGS if not used[option])
    assert not stale, f"MEANINGS names options no command has: {stale}"


def test_the_retired_names_are_gone(parsers):
    """``--steps`` and ``--seeds`` meant different things in different commands: no command
    has them but as a renamed spelling; ``--seed-offset`` and ``--seed-start`` became ``--first-seed``."""
    for command, parser in parsers.items():
        options = {option for option, _ in live_options(parser)}
        assert not options & {"--steps", "--seeds", "--seed-offset", "--seed-start"}, command


def test_renamed_spellings_are_the_table(parsers):
    found = {command: renamed_options(parser) for command, parser in parsers.items()}
    assert {c: r for c, r in found.items() if r} == RENAMED | SCRIPT_RENAMED


@pytest.mark.parametrize("command", sorted(RENAMED | SCRIPT_RENAMED))
def test_an_old_spelling_sets_the_new_option_and_warns_once(parsers, command, capsys):
    parser = parsers[command]
    for old, new in (RENAMED | SCRIPT_RENAMED)[command].items():
        action = next(a for a in parser._actions if new in a.option_strings)
        value = "8" if action.type is int or new == "--episode-seeds" else "stochastic" if new == "--modes" else "force"
        required = {"generate": ["--scene", "wedge", "--episodes", "1", "--out", "o"],
                    "train": ["--preset", "ours", "--data", "d", "--out", "o"],
                    "experiments.rl.clone": ["--task", "cube_push_stop", "--out", "o.pt"],
                    "sample": ["--scene", "wedge"]}.get(command, [])
        args = parser.parse_args([*required, old, value])
        expected = parser.parse_args([*required, new, value])
        assert getattr(args, action.dest) == getattr(expected, action.dest)
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"{old} is deprecated" in err and f"use {new}" in err, err


def test_every_default_is_shown_in_help(parsers):
    hidden = []
    for command, parser in parsers.items():
        text = " ".join(parser.format_help().split())
        for option, action in live_options(parser):
            if not action.help:
                hidden.append(f"{command} {option}: no help text")
            elif shows_default(action.default) and f"(default: {shown_default(action.default)})" not in text:
                hidden.append(f"{command} {option}: default {action.default!r} not shown")
    assert not hidden, "\n".join(hidden)


def test_the_formatter_shows_defaults_but_not_none_or_false():
    parser = argparse.ArgumentParser(prog="p", formatter_class=HelpFormatter)
    parser.add_argument("--a", type=int, default=3, help="a count")
    parser.add_argument("--b", default=None, help="b (default: the model's)")
    parser.add_argument("--c", action="store_true", help="a switch")
    parser.add_argument("--d", nargs="+", default=["x", "y"], help="100%% of it")
    text = " ".join(parser.format_help().split())
    assert "a count (default: 3)" in text and "100% of it (default: x y)" in text
    assert "b (default: the model's)" in text and "(default: None)" not in text and "(default: False)" not in text


def _draws_progress(module: str) -> bool:
    """Whether a module's source makes a tqdm bar (directly or through progress_bar)."""
    path = ROOT.joinpath(*module.split(".")[1:]).with_suffix(".py")
    paths = [path] if path.exists() else sorted(path.with_suffix("").glob("*.py"))  # a package: its modules
    names = {n.id if isinstance(n, ast.Name) else n.attr for p in paths for n in ast.walk(ast.parse(p.read_text()))
             if isinstance(n, (ast.Name, ast.Attribute))}
    return bool(names & {"tqdm", "progress_bar"})


def test_no_progress_wherever_a_bar_is_drawn(parsers):
    drawing = {c for c, (module, _) in COMMANDS.items() if _draws_progress(module)}
    assert set(PROGRESS) <= drawing | {"demo"}  # demo's bars are its steps'
    for command in drawing | set(PROGRESS):
        assert "--no-progress" in dict(live_options(parsers[command])), command


@pytest.mark.parametrize("argv", [
    ["generate", "--scene", "nowhere", "--episodes", "1", "--out", "o"],
    ["sample", "--scene", "nowhere"],
    ["calibrate", "--scene", "nowhere"],
])
def test_an_unknown_scene_lists_the_known_ones(argv, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown 'nowhere'" in err, err
    assert all(name in err for name in SCENES), err


def test_every_help_runs(parsers, capsys):
    for command in parsers:
        script = command in SCRIPTS
        with pytest.raises(SystemExit) as exit_info:
            importlib.import_module(command).main(["--help"]) if script else main([command, "--help"])
        assert exit_info.value.code == 0
        usage = f"usage: python -m {command}" if script else f"usage: hrn-pyg {command}"
        assert capsys.readouterr().out.startswith(usage)


def test_the_cli_module_imports_no_torch():
    """``hrn-pyg --help`` and the checks of cheap commands do not wait for torch."""
    import subprocess

    script = "import sys, hrn_pyg, hrn_pyg.cli; print(sorted(m for m in ('torch', 'torch_geometric') if m in sys.modules))"
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert done.stdout.strip() == "[]", done.stdout + done.stderr
