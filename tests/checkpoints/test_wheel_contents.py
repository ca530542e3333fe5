"""The wheel carries every file the package reads at run time: setup.cfg's package_data covers
every file under hrn_pyg/ that is not Python, and the wheel setuptools would build lists them."""

from __future__ import annotations

import configparser
import subprocess
from pathlib import Path

from hrn_pyg.checkpoints import CHECKPOINT_DIR, MANIFEST_PATH
from hrn_pyg.data.scene_file import BUILTIN_DIR, SCENES

REPO = Path(__file__).resolve().parents[2]
PACKAGE = REPO / "hrn_pyg"
#: files under hrn_pyg/ that are read by people, not by the package
NOT_READ = {"checkpoints/README.md"}


def package_data() -> set[Path]:
    """The files setup.cfg's ``[options.package_data] hrn_pyg`` globs match."""
    config = configparser.ConfigParser()
    config.read(REPO / "setup.cfg")
    globs = [g.strip() for g in config["options.package_data"]["hrn_pyg"].replace("\n", ",").split(",") if g.strip()]
    return {p for g in globs for p in PACKAGE.glob(g)}


def tracked_data_files() -> set[Path]:
    """The files git tracks under hrn_pyg/ that are not Python sources."""
    listed = subprocess.run(["git", "ls-files", "hrn_pyg"], cwd=REPO, capture_output=True, text=True, check=True)
    paths = {REPO / line for line in listed.stdout.splitlines()}
    return {p for p in paths if p.suffix != ".py" and str(p.relative_to(PACKAGE)) not in NOT_READ and p.is_file()}


def test_package_data_covers_what_the_code_reads():
    data = package_data()
    assert {BUILTIN_DIR / f"{name}.toml" for name in SCENES} <= data
    assert MANIFEST_PATH in data and set(CHECKPOINT_DIR.glob("*.pt")) <= data
    assert tracked_data_files() <= data, sorted(str(p) for p in tracked_data_files() - data)


def test_the_wheel_setuptools_builds_lists_them(tmp_path, monkeypatch):
    from setuptools.dist import Distribution

    monkeypatch.chdir(REPO)
    dist = Distribution({"script_name": "setup.py"})
    dist.parse_config_files(["setup.cfg"])
    build = dist.get_command_obj("build_py")
    build.build_lib = str(tmp_path)
    build.ensure_finalized()
    files = {Path(p).relative_to(tmp_path) for p in build.get_outputs(include_bytecode=0)}  # nothing is written
    wanted = {p.relative_to(REPO) for p in package_data()}
    assert {Path("hrn_pyg/data/builtin_scenes") / f"{n}.toml" for n in SCENES} <= files
    assert wanted <= files and Path("hrn_pyg/checkpoints/manifest.json") in files
