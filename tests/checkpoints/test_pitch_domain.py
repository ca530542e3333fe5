"""The domain of a pitch-aware model: the span of its datasets' pitches, any pitch within it
inside, a pitch beyond it reported as the one line ``sample``/``evaluate``/``rl`` print.

The end-to-end case trains a tiny pitch-aware model with ``hrn-pyg train --model-pitch-aware
true`` on two tiny ``cube_collision`` datasets generated at pitches 0.05 and 0.08, resumes it,
and reads its checkpoint's domain."""

from __future__ import annotations

import pytest
import torch
from torch_geometric.data import Batch

from hrn_pyg.checkpoints import load_model, training_domain
from hrn_pyg.checkpoints.domain import Domain, check_scene, dataset_domain, outside, report_outside, with_pitch_range
from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.data.graph import graph_pitch

PITCH_AWARE = Domain(pitches=(0.05, 0.08), pitch_range=(0.05, 0.08), materials=("rigid",))
ONE_PITCH = Domain(pitches=(0.05,), materials=("rigid",))


@pytest.mark.parametrize("pitch", [0.05, 0.065, 0.08, 0.0796, 0.0805])
def test_a_pitch_within_the_range_is_inside(pitch):
    assert outside(PITCH_AWARE, Domain(pitches=(pitch,))) == []
    assert check_scene("m.pt", PITCH_AWARE, Domain(pitches=(pitch,))) is None


@pytest.mark.parametrize("pitch, says", [(0.025, "0.025 m (0.5x the finest)"), (0.1, "0.1 m (1.2x the coarsest)")])
def test_a_pitch_beyond_the_range_is_one_line(pitch, says):
    line = check_scene("m.pt", PITCH_AWARE, Domain(pitches=(pitch,)))
    assert line == f"m.pt was trained at pitches 0.05-0.08 m; this scene's pitch is {says}"


def test_a_model_of_one_pitch_still_warns_between_its_pitches():
    assert check_scene("m.pt", ONE_PITCH, Domain(pitches=(0.065,))) is not None
    two = Domain(pitches=(0.05, 0.08))  # two pitches, no range: a plain model trained on both
    assert check_scene("m.pt", two, Domain(pitches=(0.065,))) is not None
    assert check_scene("m.pt", two, Domain(pitches=(0.08,))) is None


def test_the_range_round_trips_merges_and_stays_out_of_plain_records():
    assert Domain.from_dict(PITCH_AWARE.to_dict()) == PITCH_AWARE
    assert "pitch_range" not in ONE_PITCH.to_dict()  # the manifest's records keep their shape
    assert Domain.from_dict(ONE_PITCH.to_dict()).pitch_range is None
    merged = PITCH_AWARE.merge(Domain(pitches=(0.03,), pitch_range=(0.03, 0.03)))
    assert merged.pitch_range == (0.03, 0.08)
    assert with_pitch_range(Domain(pitches=(0.08, 0.025, 0.05))).pitch_range == (0.025, 0.08)
    assert with_pitch_range(Domain()).pitch_range is None


def _generate(folder, pitch: float, first_seed: int) -> None:
    from hrn_pyg.cli import main

    assert main(["generate", "--scene", "cube_collision", "--episodes", "2", "--episode-steps", "12",
                 "--pitch", str(pitch), "--first-seed", str(first_seed), "--out", str(folder),
                 "--no-progress"]) == 0


def test_train_a_pitch_aware_model_on_two_pitches_resume_and_read_its_domain(tmp_path, capsys):
    """``hrn-pyg train --model-pitch-aware true --extra-data``: windows of both pitches in one
    run, a resumed run, and the checkpoint's domain the span 0.05..0.08."""
    import argparse

    from hrn_pyg.cli import main
    from hrn_pyg.train import add_arguments, config_from_args, train, window_loss

    fine, coarse, out = tmp_path / "p005", tmp_path / "p008", tmp_path / "run"
    _generate(fine, 0.05, 0)
    _generate(coarse, 0.08, 10)
    args = ["--preset", "hrn", "--data", str(fine), "--extra-data", str(coarse), "--out", str(out),
            "--model-pitch-aware", "true", "--model-hidden", "8", "--model-depth", "1", "--model-effect-dim", "8",
            "--model-ground-contact", "true", "--train-steps", "3", "--batch-size", "4", "--checkpoint-every", "1",
            "--warmup", "1", "--seed", "1", "--no-progress"]
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    config, model_config = config_from_args(parser.parse_args(args))
    assert model_config.pitch_aware
    train(config, model_config, progress=False, stop_after=2)  # interrupted after two steps
    assert not (out / "model.pt").exists()
    assert main(["train", *args, "--resume"]) == 0
    assert "model at" in capsys.readouterr().out

    model = load_model(out / "model.pt")
    assert model.config.pitch_aware and model.config.reference_pitch == 0.05
    assert model.domain.pitch_range == (0.05, 0.08) and model.domain.pitches == (0.05, 0.08)
    assert training_domain((str(fine), str(coarse)), "", pitch_range=True).pitch_range == (0.05, 0.08)
    assert training_domain((str(fine), str(coarse))).pitch_range is None  # a plain model's: the pitches alone

    # one batch holds windows of both pitches, and its loss is finite
    windows = EpisodeWindows([fine, coarse], "train", horizon=1)
    batch = Batch.from_data_list([windows[0], windows[len(windows) - 1]])
    assert graph_pitch(batch).tolist() == [0.05, 0.08]
    loss, _ = window_loss(model, batch, 1, config)
    assert torch.isfinite(loss)

    # the warning of sample / evaluate / rl: none inside the range, one line beyond it
    assert report_outside(model, dataset_domain(coarse)) is None
    assert report_outside(model, Domain(pitches=(0.065,))) is None
    line = report_outside(model, Domain(pitches=(0.025,)))
    assert line is not None and "pitches 0.05-0.08 m" in line and "0.025 m" in line
    assert "pitches 0.05-0.08 m" in capsys.readouterr().err


def test_the_checkpoints_table_shows_a_pitch_range():
    from hrn_pyg.checkpoints import ShippedModel
    from hrn_pyg.checkpoints.cli import COLUMNS, model_row

    def pitch_cell(domain):
        model = ShippedModel(name="m", path=None, domain=domain)
        return model_row(model)[COLUMNS.index("pitch (m)")]

    assert pitch_cell(PITCH_AWARE) == "0.05-0.08"
    assert pitch_cell(Domain(pitches=(0.05, 0.08))) == "0.05, 0.08"
