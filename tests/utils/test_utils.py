import random

import numpy as np
import pytest
import torch

from hrn_pyg.utils.checkpoint import (
    load_checkpoint,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from hrn_pyg.utils.files import atomic_path, atomic_write_text
from hrn_pyg.utils.metrics import CSVLog
from hrn_pyg.utils.schedules import (
    LinearSchedule,
    SequenceLengthSchedule,
    cosine_lr_factor,
)


def test_atomic_path_leaves_nothing_on_error(tmp_path):
    target = tmp_path / "x.txt"
    atomic_write_text(target, "old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.txt"]


def test_checkpoint_round_trip_and_rng(tmp_path):
    random.seed(1); np.random.seed(2); torch.manual_seed(3)
    state = rng_state()
    expected = (random.random(), np.random.rand(), torch.rand(1).item())
    save_checkpoint(tmp_path / "c.pt", {"model": {"w": torch.ones(2)}, "config": "{}", "rng": state})
    ckpt = load_checkpoint(tmp_path / "c.pt")
    set_rng_state(ckpt["rng"])
    assert (random.random(), np.random.rand(), torch.rand(1).item()) == expected
    assert torch.equal(ckpt["model"]["w"], torch.ones(2))


def test_linear_schedule_values():
    s = LinearSchedule(0.1, 0.0, 1200)
    assert s(0) == pytest.approx(0.1)
    assert s(600) == pytest.approx(0.05)
    assert s(1200) == 0.0 and s(5000) == 0.0


def test_sequence_length_schedule_grows_monotonically_to_end():
    s = SequenceLengthSchedule(1, 6, total_steps=600, grow_until=0.5)
    values = [s(i) for i in range(600)]
    assert values[0] == 1 and values[-1] == 6 and values[299] == 6
    assert all(b >= a for a, b in zip(values, values[1:]))
    assert sorted(set(values)) == [1, 2, 3, 4, 5, 6]
    with pytest.raises(ValueError):
        SequenceLengthSchedule(3, 2)


def test_cosine_lr_factor_bounds():
    assert cosine_lr_factor(0, 100) == pytest.approx(1.0)
    assert cosine_lr_factor(100, 100) == pytest.approx(0.05)
    assert cosine_lr_factor(0, 100, warmup=10) == pytest.approx(0.1)


def test_csv_log_truncate_after(tmp_path):
    log = CSVLog(tmp_path / "m.csv", ["step", "loss"])
    for s in range(5):
        log.append({"step": s, "loss": 1.0 / (s + 1)})
    log.truncate_after(2)
    assert [int(r["step"]) for r in log.read()] == [0, 1, 2]
