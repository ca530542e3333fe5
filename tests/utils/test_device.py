"""``--device`` takes only the kinds of device the package runs on."""

import pytest
import torch

from hrn_pyg.cli import main
from hrn_pyg.utils.device import resolve_device


@pytest.mark.parametrize("name", ["meta", "mps", "xpu", "hpu"])
def test_devices_the_package_does_not_run_on_are_refused(name):
    with pytest.raises(ValueError, match=rf"^device '{name}': the package runs on cpu or cuda devices only$"):
        resolve_device(name)
    assert resolve_device("cpu") == torch.device("cpu")


def test_sample_on_the_meta_device_is_one_line(capsys, tmp_path):
    assert main(["sample", "--scene", "cube_collision", "--k", "2", "--horizon", "2", "--device", "meta",
                 "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "runs on cpu or cuda" in err and not (tmp_path / "out").exists()
