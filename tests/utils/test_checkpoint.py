"""Bad checkpoint files give one short line naming the file, in the library and on the CLI."""

from __future__ import annotations

import fractions
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from hrn_pyg.cli import main
from hrn_pyg.utils.checkpoint import CheckpointError, load_checkpoint, save_checkpoint


def _good(path: Path) -> Path:
    save_checkpoint(path, {"model": {"w": torch.arange(1000, dtype=torch.float32)}, "config": '{"model": {}}'})
    return path


def _truncated(tmp_path: Path) -> Path:
    data = _good(tmp_path / "whole.pt").read_bytes()
    path = tmp_path / "truncated.pt"
    path.write_bytes(data[: len(data) // 2])
    return path


def _random_bytes(tmp_path: Path) -> Path:
    path = tmp_path / "noise.pt"
    path.write_bytes(np.random.default_rng(0).bytes(512))
    return path


def _raises_one_line(path: Path, pattern: str) -> CheckpointError:
    """Load ``path``, expect a CheckpointError matching ``pattern``, and check its form."""
    with pytest.raises(CheckpointError, match=pattern) as info:
        load_checkpoint(path)
    message = str(info.value)
    assert message.startswith(str(path)), message
    assert "\n" not in message and len(message) < len(str(path)) + 120, message
    assert "weights_only" not in message  # torch's advice to load unsafely is not passed on
    assert info.value.__suppress_context__ or info.value.__context__ is None  # no chained paragraph
    assert isinstance(info.value, ValueError)  # what the CLI turns into exit code 2
    return info.value


def test_a_good_checkpoint_loads(tmp_path):
    ckpt = load_checkpoint(_good(tmp_path / "ok.pt"))
    assert torch.equal(ckpt["model"]["w"], torch.arange(1000, dtype=torch.float32))


def test_truncated_file(tmp_path):
    _raises_one_line(_truncated(tmp_path), r"is not a readable checkpoint \(truncated or damaged zip archive\)$")


def test_random_bytes(tmp_path):
    _raises_one_line(_random_bytes(tmp_path), r"is not a readable checkpoint \(not a file written by torch\.save\)$")


def test_empty_file(tmp_path):
    (tmp_path / "empty.pt").write_bytes(b"")
    _raises_one_line(tmp_path / "empty.pt", r"is not a readable checkpoint \(the file is empty or cut short\)$")


def test_pickled_object_refused_by_weights_only(tmp_path):
    torch.save({"model": fractions.Fraction(1, 3)}, tmp_path / "pickled.pt")
    _raises_one_line(tmp_path / "pickled.pt",
                     r"is not a readable checkpoint \(it holds a pickled fractions\.Fraction, "
                     r"which a weights-only load refuses\)$")


def test_plain_tensor_is_foreign(tmp_path):
    torch.save(torch.ones(3), tmp_path / "tensor.pt")
    _raises_one_line(tmp_path / "tensor.pt", r"is not an hrn_pyg checkpoint \(it holds a Tensor, not a dict\)$")


def test_dict_without_our_keys_is_foreign(tmp_path):
    torch.save({"model": {}}, tmp_path / "other.pt")
    _raises_one_line(tmp_path / "other.pt", r"is not an hrn_pyg checkpoint \(missing keys 'format', 'config'\)$")


def test_wrong_format_tag_and_bad_config(tmp_path):
    torch.save({"format": "someone.else.v3", "model": {}, "config": "{}"}, tmp_path / "tag.pt")
    _raises_one_line(tmp_path / "tag.pt", r"\(format 'someone\.else\.v3', expected 'hrn_pyg\.checkpoint\.v1'\)$")
    save_checkpoint(tmp_path / "config.pt", {"model": {}, "config": "not json"})
    _raises_one_line(tmp_path / "config.pt", r"\('config' is not JSON text of an object\)$")
    save_checkpoint(tmp_path / "model.pt", {"model": torch.ones(2), "config": "{}"})
    _raises_one_line(tmp_path / "model.pt", r"\('model' is a Tensor, not a state dict\)$")


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        load_checkpoint(tmp_path / "missing.pt")


@pytest.mark.parametrize("make", [_truncated, _random_bytes], ids=["truncated", "random-bytes"])
def test_cli_prints_one_line_and_exits_2(make, tiny_episodes, tmp_path, capsys):
    bad = make(tmp_path)
    code = main(["evaluate", "--data", str(tiny_episodes), "--model", f"x={bad}", "--out", str(tmp_path / "e")])
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert code == 2
    assert len(lines) == 1, captured.err
    assert re.fullmatch(rf"hrn-pyg evaluate: error: {re.escape(str(bad))} is not a readable checkpoint \(.+\)",
                        lines[0]), lines[0]


def test_json_depth_counts_brackets_outside_strings():
    from hrn_pyg.utils.checkpoint import json_depth

    assert json_depth('{"a": [1, {"b": "[[[[\\"[["}]}') == 3
    assert json_depth("") == 0
    assert json_depth("[" * 100_000 + "]" * 100_000) == 100_000
    assert json_depth('"\\' * 200_000) == 0  # an unclosed string runs to the end, read once


def test_deeply_nested_config_and_domain_are_refused_before_parsing(tmp_path):
    deep = "[" * 200_000 + "]" * 200_000
    save_checkpoint(tmp_path / "config.pt", {"model": {}, "config": deep})
    _raises_one_line(tmp_path / "config.pt", r"\('config' is JSON nested 200000 deep, more than 32\)$")
    save_checkpoint(tmp_path / "domain.pt", {"model": {}, "config": "{}", "domain": '{"a": ' + deep + "}"})
    _raises_one_line(tmp_path / "domain.pt", r"\('domain' is JSON nested 200001 deep, more than 32\)$")


def test_pickles_refused_in_any_wording_name_what_was_refused(tmp_path):
    # a protocol-0 pickle of os.system: torch words this refusal apart from "Unsupported global"
    path = tmp_path / "system.pt"
    path.write_bytes(b"cos\nsystem\n(S'echo hi'\ntR.")
    _raises_one_line(path, r"\(it holds a pickled os\.system, which a weights-only load refuses\)$")
