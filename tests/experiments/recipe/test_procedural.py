"""Procedural shapes (experiments.recipe.procedural): deterministic, unit-sized, filled as the union of
their pieces with the cavities left open, really concave where meant to be, and written to files
that a rerun leaves byte for byte as they were."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh

from hrn_pyg.data.meshes import clean_mesh, load_mesh, solid_points
from experiments.recipe.procedural import (
    KINDS,
    convex_pieces,
    main,
    make_shape,
    obj_text,
    shape_record,
    union_volume,
    write_shapes,
)

CONCAVE = ("l_shape", "t_shape", "cross", "cup", "ring")
SEEDS = (0, 1, 2)


def lattice_in_grown_union(mesh: trimesh.Trimesh, pitch: float, anchor: np.ndarray) -> np.ndarray:
    """The points of the lattice of ``pitch`` through ``anchor`` that lie in the union of the
    mesh's convex pieces grown by half a pitch: the voxels that meet the solid, which is what the
    leaf fill is meant to keep (exact for boxes, a slight excess at a slanted piece's edges)."""
    offset = anchor - pitch * np.round(anchor / pitch)
    lower = np.floor((mesh.bounds[0] - pitch) / pitch)
    upper = np.ceil((mesh.bounds[1] + pitch) / pitch)
    axes = [np.arange(lower[k], upper[k] + 1) * pitch + offset[k] for k in range(3)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    inside = np.zeros(len(points), dtype=bool)
    for eq, _ in convex_pieces(mesh):
        slack = pitch / 2 * np.abs(eq[:, :3]).sum(axis=1) + 1e-9
        inside |= np.all(points @ eq[:, :3].T + eq[:, 3] <= slack, axis=1)
    return points[inside]


def leaves(mesh: trimesh.Trimesh, pitch: float) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a shape that encloses nothing would warn
        points, how = solid_points(clean_mesh(mesh), pitch)
    assert how == "fill"
    return points


@pytest.mark.parametrize("kind", KINDS)
def test_same_seed_same_mesh_other_seed_other_mesh(kind):
    a, b, c = make_shape(kind, 5), make_shape(kind, 5), make_shape(kind, 6)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    assert a.vertices.shape != c.vertices.shape or not np.array_equal(a.vertices, c.vertices)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("seed", SEEDS)
def test_unit_size_centred_and_closed(kind, seed):
    mesh = clean_mesh(make_shape(kind, seed))
    assert mesh.extents.max() == pytest.approx(1.0)
    np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-12)
    assert mesh.is_watertight  # closed pieces that never share an edge
    assert len(convex_pieces(mesh)) >= (1 if kind == "random_hull" else 2)


@pytest.mark.parametrize("kind", CONCAVE)
@pytest.mark.parametrize("seed", SEEDS)
def test_concave_kinds_are_concave_to_the_scene_reader_too(kind, seed):
    mesh = clean_mesh(make_shape(kind, seed))
    hull = mesh.convex_hull.volume
    assert hull > 1.15 * union_volume(mesh)
    # the scene reader collides a mesh as its hull when its volume is within 2 % of the hull's
    assert mesh.volume < 0.96 * hull


def test_a_hull_is_convex():
    mesh = clean_mesh(make_shape("random_hull", 3))
    assert union_volume(mesh) == pytest.approx(mesh.convex_hull.volume, rel=0.02)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("seed", SEEDS)
def test_leaves_at_an_eighth_of_the_size_are_the_voxels_that_meet_the_union(kind, seed):
    """At a pitch of 1/8 the leaves are mostly surface voxels (a unit cube has 9^3 = 729 where its
    volume holds 512), so they are compared with the lattice points of the union grown by half a
    pitch: a hollow fill or a filled cavity would be off by far more than the tolerance."""
    mesh = make_shape(kind, seed)
    pitch = 1 / 8
    points = leaves(mesh, pitch)
    expected = lattice_in_grown_union(mesh, pitch, points[0])
    assert abs(len(points) / len(expected) - 1) < 0.15
    if kind not in ("random_hull", "ring"):  # axis-aligned boxes: the same points exactly
        key = lambda p: set(map(tuple, np.round(p / pitch * 2).astype(np.int64).tolist()))  # noqa: E731
        assert key(points) == key(expected)


@pytest.mark.parametrize("kind", KINDS)
def test_leaves_at_a_fine_pitch_fill_the_volume_of_the_union(kind):
    """Where the surface shell is thin (pitch a quarter of volume / area, as for pybullet_data's
    meshes), leaves x pitch^3 is the union's volume within 30 %."""
    mesh = make_shape(kind, 1)
    volume = union_volume(mesh)
    pitch = volume / mesh.area / 4
    assert abs(len(leaves(mesh, pitch)) * pitch**3 / volume - 1) < 0.3


@pytest.mark.parametrize("seed", SEEDS)
def test_cavities_stay_open(seed):
    cup = make_shape("cup", seed)
    points = leaves(cup, 1 / 16)
    # the cavity is at least 0.12 from the axis to an inner wall; its surface voxels reach 1/32 in
    near_axis = (np.abs(points[:, 0]) < 0.07) & (np.abs(points[:, 1]) < 0.07)
    above_floor = points[:, 2] > cup.bounds[0][2] + 0.25  # floors are at most 0.18 thick
    assert np.any(near_axis) and not np.any(near_axis & above_floor)  # a floor, no leaf in the cup
    ring = make_shape("ring", seed)
    points = leaves(ring, 1 / 16)
    centre = points[:, :2].mean(axis=0)  # the polygon's centre (a pentagon's is off its box's)
    assert not np.any(np.linalg.norm(points[:, :2] - centre, axis=1) < 0.15)  # no leaf in the hole


def test_union_volume_of_two_overlapping_boxes():
    a = trimesh.creation.box((1.0, 1.0, 1.0))
    b = trimesh.creation.box((1.0, 1.0, 1.0))
    b.apply_translation((0.5, 0.0, 0.0))
    union = trimesh.util.concatenate([a, b])
    assert union_volume(union) == pytest.approx(1.5, rel=0.02)
    assert union_volume(union, grow=0.1) == pytest.approx(1.7 * 1.2 * 1.2, rel=0.02)
    with pytest.raises(ValueError, match="not a union of closed convex pieces"):
        union_volume(trimesh.creation.annulus(0.2, 0.5, 0.3))


def test_writes_files_and_index_and_a_rerun_changes_no_byte(tmp_path, capsys):
    assert main(["--out", str(tmp_path), "--per-kind", "2", "--seed", "7"]) == 0
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == sorted([f"{k}_{i:03d}.obj" for k in KINDS for i in range(2)] + ["index.json"])
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    index = json.loads(before["index.json"])
    assert [(r["kind"], r["seed"]) for r in index["shapes"]] == [(k, 7 + i) for k in KINDS for i in range(2)]
    for record in index["shapes"]:
        mesh = clean_mesh(load_mesh(tmp_path / record["file"]))
        assert record["watertight"] is True and mesh.extents.max() == pytest.approx(1.0)
        assert 0.05 < record["volume"] < 1.0
    assert main(["--out", str(tmp_path), "--per-kind", "2", "--seed", "7"]) == 0
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    (tmp_path / "cup_001.obj").unlink()  # made again, the same bytes
    write_shapes(tmp_path, 2, seed=7, kinds=["cup"])
    assert (tmp_path / "cup_001.obj").read_bytes() == before["cup_001.obj"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary file left


def test_a_file_of_another_seed_is_not_overwritten(tmp_path):
    write_shapes(tmp_path, 1, seed=0, kinds=["ring"])
    with pytest.raises(ValueError, match="ring_000.obj exists and is not shape ring of seed 1"):
        write_shapes(tmp_path, 1, seed=1, kinds=["ring"])


@pytest.mark.parametrize("call, message", [
    (lambda out: make_shape("torus", 0), "unknown shape kind 'torus'; choose from random_hull"),
    (lambda out: make_shape("cup", -1), "seed must be an integer >= 0"),
    (lambda out: write_shapes(out, -1), "per_kind must be an integer >= 0, got -1"),
    (lambda out: write_shapes(out, 1, kinds=["cup", "bowl"]), "unknown shape kind 'bowl'"),
])
def test_bad_input_is_a_clear_value_error(tmp_path, call, message):
    with pytest.raises(ValueError, match=message):
        call(tmp_path)
    assert not tmp_path.exists() or not any(tmp_path.iterdir())


def test_cli_bad_input_is_one_line_and_exit_code_2(tmp_path, capsys):
    assert main(["--out", str(tmp_path), "--per-kind", "-2"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "error: per_kind must be an integer >= 0, got -2"


def test_a_cup_that_coarse_v_hacd_fills_is_decomposed_at_a_finer_resolution(tmp_path):
    """Cup seed 3 comes back from V-HACD at the default resolution as one solid part; the finer
    retry keeps its cavity: several parts, none of which holds the cavity's centre."""
    from hrn_pyg.data.meshes import convex_parts, part_count, sized_mesh

    cup = sized_mesh(make_shape("cup", 3), size=0.3)
    parts = convex_parts(cup, tmp_path)
    assert part_count(parts) > 1
    pieces = trimesh.load(parts, force="mesh").split(only_watertight=False)
    cavity = cup.bounds.mean(axis=0) + [0.0, 0.0, 0.25 * cup.extents[2]]  # above the floor, inside the walls
    assert not any(piece.convex_hull.contains([cavity])[0] for piece in pieces)


def test_the_roof_is_a_closed_gable_with_its_ridge_on_the_y_axis():
    from experiments.recipe.procedural import gable_roof

    roof = gable_roof(width=0.4, length=0.3, eaves=0.08, ridge=0.2)
    assert roof.is_watertight and roof.is_convex
    assert np.allclose(roof.bounds, [[-0.2, -0.15, -0.1], [0.2, 0.15, 0.1]])
    assert roof.volume == pytest.approx(0.4 * 0.3 * 0.08 + 0.5 * 0.4 * 0.12 * 0.3)
    top = roof.vertices[np.isclose(roof.vertices[:, 2], 0.1)]
    assert len(top) == 2 and np.allclose(top[:, 0], 0.0)  # the ridge: x = 0, along y
    with pytest.raises(ValueError, match="eaves < ridge"):
        gable_roof(eaves=0.3, ridge=0.2)


SHIPPED = Path(__file__).resolve().parents[3] / "data" / "shapes" / "meshes"


def test_the_shipped_meshes_are_what_the_generator_makes_byte_for_byte():
    """``data/shapes/meshes`` holds exactly the shapes its ``index.json`` lists, each file the
    text :func:`make_shape` gives for its kind and seed (shape ``i`` of a kind: seed ``seed + i``),
    and the index's records are what :func:`shape_record` reads back (one shape per kind)."""
    index = json.loads((SHIPPED / "index.json").read_text())
    records = index["shapes"]
    assert sorted(p.name for p in SHIPPED.iterdir()) == sorted([r["file"] for r in records] + ["index.json"])
    assert len(records) == len(KINDS) * index["per_kind"]
    for record in records:
        kind, i = record["file"].removesuffix(".obj").rsplit("_", 1)
        assert (record["kind"], record["seed"]) == (kind, index["seed"] + int(i))
        assert (SHIPPED / record["file"]).read_bytes() == obj_text(make_shape(kind, record["seed"])).encode()
    for kind in KINDS:
        record = next(r for r in records if r["kind"] == kind and r["seed"] == index["seed"] + index["per_kind"] - 1)
        assert shape_record(SHIPPED / record["file"], kind, record["seed"]) == record
