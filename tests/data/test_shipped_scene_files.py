"""Every scene file the repository ships (the built-in scenes, the generalist's training scenes
and its unseen-shape scenes) reads and passes the checks an episode makes before it simulates:
at the seeds its generate command draws, and with every mesh it lists."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import pytest

from hrn_pyg.data.meshes import MeshWarning
from hrn_pyg.data.scene_file import SCENES, SHEET, posed_mesh, read_scene_file

ROOT = Path(__file__).resolve().parents[2]
FILES = sorted([*(ROOT / "hrn_pyg" / "data" / "builtin_scenes").glob("*.toml"),
                *(ROOT / "data" / "shapes").glob("*.toml"), *(ROOT / "data" / "shapes" / "unseen").glob("*.toml")])
#: meshes that enclose no voxel centre at the files' pitch (pybullet_data's open mug, and its
#: lego brick, hollow with walls thinner than 5 cm): their leaves are the voxels the surface
#: passes through, with a warning
OPEN = ("mug.obj", "lego.obj")


def test_the_shipped_scene_files_are_all_found():
    assert {p.stem for p in FILES if p.parent.name == "builtin_scenes"} == set(SCENES)
    assert len([p for p in FILES if p.parent.name == "unseen"]) >= 6 and len(FILES) >= 17


def _seeds(path: Path) -> list[int]:
    """The first seeds of the dataset the file's comment says to generate (0: none given)."""
    found = re.search(r"--(?:first-seed|seed-offset) (\d+)", path.read_text())
    start = int(found.group(1)) if found else 0
    return list(range(start, start + 3))


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_a_shipped_scene_file_reads_and_checks(path):
    spec = read_scene_file(path)
    assert spec.objects and spec.config.steps > 0
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=MeshWarning, message=".*encloses no volume")
        for seed in _seeds(path):
            spec.check(seed)                                      # overlaps redrawn, leaves counted
            scene = spec.make_scene(seed)
            assert len(scene.params["objects"]) == len(spec.objects)


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_listed_mesh_makes_leaves_at_the_file_pitch(path):
    """A seed draws one mesh of a list; the others are posed here one by one."""
    import numpy as np

    from hrn_pyg.data.scene_file import leaves_of

    spec = read_scene_file(path)
    drawn = spec.draw(np.random.default_rng(_seeds(path)[0]))["objects"]
    for index, (obj, values) in enumerate(zip(spec.objects, drawn)):
        if obj.material in ("soft", "cloth") or len(obj.meshes) < 2:
            continue                                              # checked through spec.check
        for m, mesh in enumerate(obj.meshes):
            posed = posed_mesh(obj, {**values, "mesh": m})
            assert posed is not None and mesh != SHEET
            with warnings.catch_warnings():
                if not mesh.endswith(OPEN):
                    warnings.simplefilter("error", MeshWarning)   # a closed mesh encloses its leaves
                points = leaves_of(posed, spec.config.pitch, f"{path.name}: objects[{index}] {mesh}")
            assert len(points) >= 2
