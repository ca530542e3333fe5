"""The command options read from the config dataclasses' source are those dataclasses: the same
fields, defaults and help, the parsers' defaults are the configs' defaults, and every command's
``--help`` answers without importing torch."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import MISSING, fields

import pytest

from hrn_pyg.cli import COMMANDS, build_parser
from hrn_pyg.commands.configs import config_fields, config_help, source_constant
from hrn_pyg.commands.rl import TASK_NAMES
from hrn_pyg.utils.options import attribute_help


def configs():
    from hrn_pyg.nn.gns import GNSConfig
    from hrn_pyg.nn.hrn import HRNConfig
    from hrn_pyg.rl.planning import PlannerConfig
    from hrn_pyg.rl.ppo import PPOConfig
    from hrn_pyg.train.config import TrainConfig

    return [TrainConfig, HRNConfig, GNSConfig, PPOConfig, PlannerConfig]


@pytest.mark.parametrize("cls", configs(), ids=lambda c: c.__name__)
def test_the_source_gives_the_dataclass(cls):
    read = config_fields(cls.__module__, cls.__name__)
    assert [f.name for f in read] == [f.name for f in fields(cls)]
    for got, f in zip(read, fields(cls)):
        default = f.default if f.default is not MISSING else f.default_factory()
        assert got.default == default and type(got.default) is type(default), f.name
    assert config_help(cls.__module__, cls.__name__) == attribute_help(cls)


def test_the_constants_read_from_source_are_the_modules():
    from hrn_pyg.losses import DEFAULT_CHUNK_SIZE
    from hrn_pyg.rl.planning import SCORES
    from hrn_pyg.rl.tasks import MODES, TASKS
    from hrn_pyg.train.config import PRESET_OVERRIDES, PRESETS

    assert source_constant("hrn_pyg.train.config", "PRESET_OVERRIDES") == PRESET_OVERRIDES
    assert source_constant("hrn_pyg.train.config", "PRESETS") == PRESETS == tuple(PRESET_OVERRIDES)
    assert source_constant("hrn_pyg.train.config", "DEFAULT_CHUNK_SIZE") == DEFAULT_CHUNK_SIZE  # imported there
    assert source_constant("hrn_pyg.rl.tasks", "MODES") == MODES
    assert source_constant("hrn_pyg.rl.planning", "SCORES") == SCORES
    assert TASK_NAMES == tuple(TASKS)
    with pytest.raises(ValueError, match="no module-level constant 'NOPE'"):
        source_constant("hrn_pyg.rl.tasks", "NOPE")
    with pytest.raises(ValueError, match="not a module of hrn_pyg"):
        config_fields("torch.nn", "Linear")


@pytest.mark.parametrize("preset", ["hrn", "ours", "gns"])
def test_train_parser_defaults_are_the_presets(preset):
    from hrn_pyg.nn.gns import GNSConfig
    from hrn_pyg.nn.hrn import HRNConfig
    from hrn_pyg.train.cli import config_from_args
    from hrn_pyg.train.config import TrainConfig

    args = build_parser("train").parse_args(["train", "--preset", preset, "--data", "d", "--out", "o"])
    config, model = config_from_args(args)
    assert config == TrainConfig.for_preset(preset, data="d", out="o")
    assert model == (GNSConfig() if preset == "gns" else HRNConfig())
    text = " ".join(build_parser("train")._subparsers._group_actions[0].choices["train"].format_help().split())
    assert "(default: hrn 1, ours 6, gns 1)" in text  # --seq-end, the presets' own values


def test_rl_and_plan_parser_defaults_are_the_configs():
    from hrn_pyg.rl.planning import PlannerConfig
    from hrn_pyg.rl.ppo import PPOConfig

    rl = vars(build_parser("rl").parse_args(["rl"]))
    ppo = PPOConfig()
    for f in fields(PPOConfig):
        if f.name in rl:
            assert rl[f.name] == getattr(ppo, f.name), f.name
    assert len(set(rl) & {f.name for f in fields(PPOConfig)}) == 12
    plan = vars(build_parser("plan").parse_args(["plan", "--task", "tower_aside", "--model", "tower"]))
    planner = PlannerConfig()
    named = {"k": "futures"}
    shared = [o for o in plan if named.get(o, o) in {f.name for f in fields(PlannerConfig)}]
    assert len(shared) == 13
    for option in shared:
        if option != "refine_steps":  # with --refine only: the command's own 3, not the config's 0
            assert plan[option] == getattr(planner, named.get(option, option)), option


def test_every_help_imports_no_torch():
    """Each command's ``--help`` in a fresh interpreter, then whether torch was imported."""
    script = ("import contextlib, io, sys\nfrom hrn_pyg.cli import COMMANDS, main\n"
              "for command in COMMANDS:\n"
              "    with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n"
              "        main([command, '--help'])\n"
              "    print(command, sorted(m for m in ('torch', 'torch_geometric') if m in sys.modules))\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == [f"{command} []" for command in COMMANDS], done.stdout
