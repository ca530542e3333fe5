"""Shipped models by name from any folder, their list, their domains and the warnings they give."""

from __future__ import annotations

import json

import pytest

from hrn_pyg.checkpoints import (
    CHECKPOINT_DIR,
    POLICY_NAMES,
    checkpoint_domain,
    load_model,
    model_path,
    read_manifest,
    shipped_models,
    shipped_names,
)
from hrn_pyg.checkpoints.domain import DomainError
from hrn_pyg.cli import main
from hrn_pyg.data.scene_file import BUILTIN_DIR


def test_load_model_by_name_from_another_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    model = load_model("shapes")
    assert model.checkpoint_name == "shapes.pt" and model.domain.pitch_range == (0.025, 0.08)
    assert model_path("shapes.pt") == CHECKPOINT_DIR / "shapes.pt"
    assert model_path(str(CHECKPOINT_DIR / "wedge.pt")) == CHECKPOINT_DIR / "wedge.pt"  # a path still works


def test_an_unknown_name_lists_the_shipped_ones(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(FileNotFoundError, match="neither a file nor a shipped model.*shapes.*wedge"):
        load_model("shape")
    with pytest.raises(FileNotFoundError):
        model_path("cube_push_policy")  # a policy is not a model


def test_every_shipped_model_is_listed_with_its_domain():
    models = shipped_models()
    listed = {n for m in models for n in (m.name, *m.aliases)}
    assert listed == set(shipped_names()) == {p.stem for p in CHECKPOINT_DIR.glob("*.pt")} - set(POLICY_NAMES)
    for m in models:
        assert m.domain is not None and m.domain.pitches and m.domain.materials and m.datasets, m.name
        assert m.sha256 and m.path.is_file()
    shapes = next(m for m in models if m.name == "shapes")
    assert set(shapes.domain.materials) == {"rigid", "soft", "cloth"} and shapes.rate == 0.2
    assert {"shapes_drop", "cube_collision", "shapes_soft", "shapes_cloth", "urdf_drop"} <= set(shapes.datasets)
    eight_pass = next(m for m in models if m.name == "shapes_d4")
    assert "cloth" not in eight_pass.domain.materials and eight_pass.rate == 0.02


def test_shipped_domains_come_from_the_manifest_by_the_files_bytes():
    manifest = read_manifest()
    for name, entry in manifest.items():
        assert checkpoint_domain(CHECKPOINT_DIR / f"{name}.pt").to_dict() == entry["domain"], name


def test_models_command_prints_every_model_and_json(capsys):
    assert main(["models"]) == 0
    out = capsys.readouterr().out
    assert all(name in out for name in read_manifest()) and "pitch (m)" in out
    assert max(len(line) for line in out.splitlines()) <= 100  # one terminal's width
    assert main(["models", "--json"]) == 0
    records = json.loads(capsys.readouterr().out)
    assert {r["name"] for r in records} == set(read_manifest())


def test_models_name_prints_every_dataset_of_one_model(capsys):
    shapes = next(m for m in shipped_models() if m.name == "shapes")
    assert main(["models", "shapes"]) == 0
    out = capsys.readouterr().out
    assert f"trained on:         {', '.join(shapes.datasets)}" in out and str(shapes.path) in out
    assert main(["models", "soft_bounce"]) == 0  # an alias
    assert "model:              soft_bounce_ours" in capsys.readouterr().out
    assert main(["models", "no_such_model"]) == 2
    assert "no shipped model 'no_such_model'" in capsys.readouterr().err


def test_version_comes_from_the_metadata(capsys):
    from hrn_pyg import __version__

    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0 and capsys.readouterr().out.strip() == f"hrn-pyg {__version__}"


def _cube_collision_at(pitch: float, folder) -> str:
    path = folder / "cube_collision_fine.toml"
    text = (BUILTIN_DIR / "cube_collision.toml").read_text()
    assert "pitch = 0.05" in text
    path.write_text(text.replace("pitch = 0.05", f"pitch = {pitch}"))
    return str(path)


@pytest.mark.parametrize("model, pitch, warning", [
    ("shapes_d4", 0.025, "shapes_d4.pt was trained at pitch 0.05 m; this scene's pitch is 0.025 m (0.5x)"),
    ("shapes", 0.0125, "shapes.pt was trained at pitches 0.025-0.08 m; this scene's pitch is 0.0125 m "
                       "(0.5x the finest)"),
])
def test_sample_outside_the_pitch_warns_in_one_line_and_strict_exits_2(model, pitch, warning, tmp_path, capsys):
    scene = _cube_collision_at(pitch, tmp_path)
    args = ["sample", "--scene-file", scene, "--model", model, "--k", "1", "--horizon", "1", "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "warned")]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"hrn-pyg sample: warning: {warning}"]
    assert main([*args, "--out", str(tmp_path / "strict"), "--strict"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"pitch is {pitch:g} m" in err[0] and not (tmp_path / "strict").exists()


def test_sample_inside_the_domain_says_nothing(tmp_path, capsys):
    assert main(["sample", "--scene", "cube_collision", "--model", "shapes", "--k", "1", "--horizon", "1",
                 "--strict", "--out", str(tmp_path / "s")]) == 0
    assert "warning" not in capsys.readouterr().err


def test_multi_material_names_cloth_to_the_eight_pass_model_and_not_to_shapes(tmp_path, capsys):
    assert main(["sample", "--scene", "multi_material", "--model", "shapes_d4", "--k", "1", "--horizon", "1",
                 "--strict", "--out", str(tmp_path / "d4")]) == 2
    err = capsys.readouterr().err
    assert "this scene has cloth" in err and len(err.strip().splitlines()) == 1
    assert main(["sample", "--scene", "multi_material", "--model", "shapes", "--k", "1", "--horizon", "1",
                 "--strict", "--out", str(tmp_path / "s")]) == 0
    assert "warning" not in capsys.readouterr().err


def test_evaluate_takes_a_name_and_warns(tiny_episodes, tmp_path, capsys):
    from hrn_pyg.evaluate import _parse_models

    assert _parse_models(["shapes", "ours=cube_collision"]) == {"shapes": "shapes", "ours": "cube_collision"}
    assert main(["evaluate", "--data", str(tiny_episodes), "--model", "soft_bounce", "--horizons", "2",
                 "--long-horizons", "", "--no-figure", "--out", str(tmp_path / "e"), "--strict"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "soft_bounce.pt was trained on soft objects, on 1 moving object" in err
    assert "this scene has rigid" in err and "this scene has 2" in err


def test_rl_dynamics_outside_the_domain(capsys):
    from hrn_pyg.rl.hrn_dynamics import HRNDynamics

    with pytest.raises(DomainError, match="this scene has 4"):
        HRNDynamics(load_model("shapes"), "tower", pool_seeds=(10_000,), strict=True)
    HRNDynamics(load_model("cube_push"), "cube_push", pool_seeds=(10_000,), strict=True)
    HRNDynamics(load_model("shapes"), "tower", pool_seeds=(10_000,))
    assert capsys.readouterr().err.count("this scene has 4") == 1
