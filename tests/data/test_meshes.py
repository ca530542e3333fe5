"""Meshes as they come (hrn_pyg.data.meshes): pybullet_data's untidy meshes fill their volume,
open meshes are filled by the winding number, bad files are one clear error, and a concave
rigid body collides as its convex parts."""

from __future__ import annotations

import os
import warnings

import numpy as np
import pybullet
import pybullet_data
import pytest
import trimesh

from hrn_pyg.data import meshes
from hrn_pyg.data.meshes import (
    PRIMITIVES,
    MeshWarning,
    clean_mesh,
    convex_parts,
    load_mesh,
    primitive_mesh,
    sized_mesh,
    solid_points,
    winding_numbers,
)
from hrn_pyg.data.voxelise import grid_sheet

DATA = pybullet_data.getDataPath()
#: pybullet_data meshes that are closed once their seams are merged: (file, duplicated seams?)
CLOSED = ["duck.obj", "torus/torus_textured.obj", "cube.obj", "bunny.obj"]


def unshared(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """A copy in which every triangle has vertices of its own: every edge is a seam, so the copy
    is open (not watertight) although it bounds the same solid."""
    vertices = np.asarray(mesh.triangles).reshape(-1, 3)
    return trimesh.Trimesh(vertices=vertices, faces=np.arange(len(vertices)).reshape(-1, 3), process=False)


def volume_pitch(mesh: trimesh.Trimesh) -> float:
    """A quarter of volume / area: fine enough that the half-voxel shell of surface leaves adds
    about an eighth to the count."""
    return float(mesh.volume / mesh.area) / 4


@pytest.mark.parametrize("name", CLOSED)
def test_leaves_fill_the_volume_of_a_mesh_and_of_its_copy_with_seams(name):
    raw = load_mesh(os.path.join(DATA, name))
    solid = sized_mesh(clean_mesh(raw, name), size=0.3)
    assert solid.is_watertight
    pitch = volume_pitch(solid)
    expected = solid.volume / pitch**3
    points, how = solid_points(solid, pitch, name)
    assert how == "fill" and abs(len(points) / expected - 1) < 0.25
    seams = unshared(solid)
    assert not seams.is_watertight
    again, _ = solid_points(clean_mesh(seams, name), pitch, name)
    assert abs(len(again) / expected - 1) < 0.25
    some = points[np.random.default_rng(0).choice(len(points), 200, replace=False)]
    inside = np.abs(winding_numbers(solid, some)) >= 0.5
    assert inside.mean() > 0.6  # most leaves lie inside; the rest in the half-voxel shell


@pytest.mark.parametrize("name", ["cube.obj", "torus/torus_textured.obj"])
def test_the_winding_number_fills_an_open_mesh_as_the_closed_one_is_filled(name):
    """Without merging its seams the mesh is open; the winding-number lattice is the fill's."""
    raw = sized_mesh(load_mesh(os.path.join(DATA, name)), size=0.2)
    assert not raw.is_watertight
    closed = clean_mesh(raw)
    pitch = 0.2 / 12
    open_points, how = solid_points(raw, pitch)
    closed_points, closed_how = solid_points(closed, pitch)
    assert (how, closed_how) == ("winding", "fill")
    key = lambda p: np.round(p / pitch).astype(np.int64).tolist()  # noqa: E731
    assert sorted(key(open_points)) == sorted(key(closed_points))


def test_winding_numbers_are_one_inside_zero_outside_and_a_hole_is_bridged():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    w = winding_numbers(sphere, np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 0.5], [2.0, 0.0, 0.0], [0.0, 0.0, -1.5]]))
    np.testing.assert_allclose(w, [1.0, 1.0, 0.0, 0.0], atol=1e-9)
    holed = sphere.copy()
    holed.update_faces(np.arange(len(holed.faces)) != 0)  # one face missing
    assert not holed.is_watertight
    assert abs(winding_numbers(holed, np.zeros((1, 3)))[0] - 1.0) < 0.05


def test_an_open_sheet_keeps_its_surface_voxels_with_a_warning():
    vertices, faces = grid_sheet(0.2, 0.02)
    vertices[:, 2] = 0.05 * np.sin(vertices[:, 0] * 20)  # a wavy sheet: it bounds nothing
    sheet = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    with pytest.warns(MeshWarning, match="encloses no volume"):
        points, how = solid_points(sheet, 0.01, "sheet")
    assert how == "surface" and len(points) == len(sheet.voxelized(0.01).points)
    assert np.abs(points[:, 2] - 0.05 * np.sin(points[:, 0] * 20)).max() < 0.01 * np.sqrt(3)  # on the sheet


@pytest.mark.parametrize("name", PRIMITIVES)
def test_primitives_are_closed_centred_and_one_metre_long(name):
    mesh = primitive_mesh(name)
    assert mesh.is_watertight
    np.testing.assert_allclose(mesh.extents.max(), 1.0, rtol=0.01)  # an icosphere's vertices miss the axes
    centre = [0.0, 0.0, 0.25] if name == "wedge" else [0.0, 0.0, 0.0]  # a wedge stands on its base
    np.testing.assert_allclose(mesh.bounds.mean(axis=0), centre, atol=1e-12)


@pytest.mark.parametrize("name, extents", [("box", (0.3, 0.2, 0.1)), ("cylinder", (0.1, 0.1, 0.3)),
                                           ("capsule", (0.1, 0.1, 0.3)), ("cone", (0.2, 0.2, 0.1)),
                                           ("wedge", (0.4, 0.3, 0.2))])
def test_primitives_take_their_extents(name, extents):
    mesh = primitive_mesh(name, np.array(extents))
    assert mesh.is_watertight
    np.testing.assert_allclose(mesh.extents, extents, rtol=1e-3)
    with pytest.raises(ValueError, match="extents must be finite and > 0"):
        primitive_mesh(name, np.array([0.1, 0.0, 0.1]))


def test_sized_mesh_scales_the_longest_extent_and_centres_the_box():
    mesh = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
    mesh.apply_translation([5.0, -3.0, 1.0])
    out = sized_mesh(mesh, size=0.4)
    np.testing.assert_allclose(out.extents, [0.4, 0.2, 0.1])
    np.testing.assert_allclose(out.bounds.mean(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(sized_mesh(mesh, scale=0.5).extents, [1.0, 0.5, 0.25])
    with pytest.raises(ValueError, match="one of size and scale"):
        sized_mesh(mesh)


def test_bad_meshes_are_one_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="mesh file not found"):
        load_mesh(tmp_path / "nope.obj")
    text = tmp_path / "notes.obj"
    text.write_text("this is not a mesh\n")
    with pytest.raises(ValueError, match="notes.obj"):
        load_mesh(text)
    empty = trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64))
    with pytest.raises(ValueError, match="empty mesh"):
        clean_mesh(empty, "empty")
    bad = trimesh.creation.box()
    bad.vertices[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        clean_mesh(bad, "bad")
    flat = trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [2, 0, 0]], faces=[[0, 1, 2]], process=False)
    with pytest.raises(ValueError, match="no face with an area"):
        clean_mesh(flat, "flat")
    with pytest.raises(ValueError, match="make it at least 10 m long, or use a pitch of at most 0.5 m"):
        solid_points(primitive_mesh("sphere"), 5.0, "ball")


def _cup() -> trimesh.Trimesh:
    """A cup 10 cm wide and 9 cm tall: a wall 1 cm thick on a 1 cm base (concave)."""
    wall = trimesh.creation.annulus(r_min=0.04, r_max=0.05, height=0.08, sections=32)
    wall.apply_translation([0.0, 0.0, 0.05])
    base = trimesh.creation.cylinder(radius=0.05, height=0.01, sections=32)
    base.apply_translation([0.0, 0.0, 0.005])
    cup = trimesh.util.concatenate([wall, base])
    cup.apply_translation(-cup.bounds.mean(axis=0))
    return cup


def _ball_height_in(collision_file) -> float:
    """Drop a 1.5 cm ball from 20 cm onto a cup (0.5 kg, on the ground) whose collision shape is
    ``collision_file``; the ball's height after two seconds."""
    client = pybullet.connect(pybullet.DIRECT)
    try:
        pybullet.setGravity(0, 0, -9.81, physicsClientId=client)
        plane = pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=client)
        pybullet.createMultiBody(0, plane, physicsClientId=client)
        shape = pybullet.createCollisionShape(pybullet.GEOM_MESH, fileName=str(collision_file), physicsClientId=client)
        pybullet.createMultiBody(0.5, shape, basePosition=[0, 0, 0.046], physicsClientId=client)
        sphere = pybullet.createCollisionShape(pybullet.GEOM_SPHERE, radius=0.015, physicsClientId=client)
        ball = pybullet.createMultiBody(0.01, sphere, basePosition=[0, 0, 0.2], physicsClientId=client)
        for _ in range(480):
            pybullet.stepSimulation(physicsClientId=client)
        return pybullet.getBasePositionAndOrientation(ball, physicsClientId=client)[0][2]
    finally:
        pybullet.disconnect(client)


def test_a_concave_cup_holds_a_ball_in_its_cavity_as_its_convex_parts(tmp_path, monkeypatch):
    cup = _cup()
    parts = convex_parts(cup, tmp_path / "cache")
    assert _ball_height_in(parts) < 0.05  # in the cavity: on the base, below the rim at 9 cm
    cup.export(tmp_path / "cup.obj")
    assert _ball_height_in(tmp_path / "cup.obj") > 0.09  # as one convex hull the cavity is solid

    def no_second_decomposition(*args, **kwargs):
        raise AssertionError("the cached decomposition was made again")

    monkeypatch.setattr(pybullet, "vhacd", no_second_decomposition)
    assert convex_parts(cup.copy(), tmp_path / "cache") == parts
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == [parts.name]  # nothing left over


def _channel(width: float, height: float) -> trimesh.Trimesh:
    """A U-shaped channel ``width`` wide and ``height`` tall, 4 cm deep, walls 1 cm thick
    (concave, and quick to decompose)."""
    floor = trimesh.creation.box([width, 0.04, 0.01])
    floor.apply_translation([0.0, 0.0, -(height - 0.01) / 2])
    walls = [trimesh.creation.box([0.01, 0.04, height]) for _ in range(2)]
    walls[0].apply_translation([-(width - 0.01) / 2, 0.0, 0.0])
    walls[1].apply_translation([(width - 0.01) / 2, 0.0, 0.0])
    return trimesh.util.concatenate([floor, *walls])


def test_the_decomposition_cache_keeps_one_entry_per_mesh(tmp_path, monkeypatch):
    wide, tall = _channel(0.12, 0.06), _channel(0.06, 0.12)
    cache = tmp_path / "cache"
    parts = {name: convex_parts(mesh, cache, resolution=20_000) for name, mesh in (("wide", wide), ("tall", tall))}
    assert parts["wide"] != parts["tall"]
    assert sorted(p.name for p in cache.iterdir()) == sorted(p.name for p in parts.values())
    for name, mesh in (("wide", wide), ("tall", tall)):
        got = trimesh.load(parts[name], force="mesh")
        assert np.abs(got.bounds - mesh.bounds).max() < 0.003, name  # each entry is its own mesh's parts

    def no_second_decomposition(*args, **kwargs):
        raise AssertionError("the cached decomposition was made again")

    monkeypatch.setattr(pybullet, "vhacd", no_second_decomposition)
    assert convex_parts(tall.copy(), cache, resolution=20_000) == parts["tall"]
    assert convex_parts(wide.copy(), cache, resolution=20_000) == parts["wide"]


def test_the_mesh_digest_follows_vertices_and_faces():
    wide = _channel(0.12, 0.06)
    digests = {meshes.mesh_digest(wide), meshes.mesh_digest(_channel(0.06, 0.12))}
    moved = wide.copy()
    moved.vertices[3, 2] += 1e-9
    digests.add(meshes.mesh_digest(moved))
    flipped = wide.copy()
    flipped.faces = flipped.faces[:, ::-1]
    digests.add(meshes.mesh_digest(flipped))
    assert len(digests) == 4
    assert meshes.mesh_digest(wide) == meshes.mesh_digest(wide.copy())


def test_a_mesh_with_seams_warns_of_nothing_and_loads_as_one_mesh():
    with warnings.catch_warnings():
        warnings.simplefilter("error", MeshWarning)
        mesh = load_mesh(os.path.join(DATA, "duck.obj"))
        points, how = solid_points(sized_mesh(clean_mesh(mesh), size=0.2), 0.02)
    assert how == "fill" and len(points) > 100
    assert meshes.mesh_digest(mesh) == meshes.mesh_digest(mesh.copy())


def test_a_mesh_file_changed_on_disk_is_read_again(tmp_path):
    """Scene files keep the meshes they read in memory; a file written again is not served stale."""
    from hrn_pyg.data.meshes import MAX_FACES
    from hrn_pyg.data.scene_file import base_mesh

    path = tmp_path / "changing.obj"
    trimesh.creation.box().export(path)
    assert len(base_mesh(str(path)).faces) == 12
    rng = np.random.default_rng(0)
    faces = rng.integers(1, 9, size=(MAX_FACES + 1, 3))
    path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in rng.random((8, 3)))
                    + "".join(f"f {a} {b} {c}\n" for a, b, c in faces))
    os.utime(path, ns=(1, 1))  # a different time of change, whatever the clock's resolution
    with pytest.raises(ValueError, match=f"more than {MAX_FACES}"):
        base_mesh(str(path))
