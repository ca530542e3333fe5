"""experiments/plausibility/table.py: where a model's cells are kept."""

from pathlib import Path

from experiments.plausibility.table import cells_tag


def test_a_model_path_names_one_folder_under_the_work_folder():
    work = Path("/tmp/work")
    for model in ("/abs/runs/x.pt", "runs/s27/x.pt", "shapes"):
        tag = cells_tag(model, {"rest_friction": 0.01}, 0.2)
        assert "/" not in tag and (work / "cells" / tag).parent == work / "cells"
    assert cells_tag("/abs/runs/x.pt", {}, 0.2) == "abs_runs_x.pt_rate0.2"
    assert cells_tag("shapes", {"rest_friction": 0.01}, 0.3) == "shapes_rest_friction=0.01_rate0.3"
