"""Voxelisation: counts against analytic volumes, lattice tetrahedra, bad meshes."""

import numpy as np
import pytest
import trimesh

from hrn_pyg.data.voxelise import (
    LatticeWarning,
    box_mesh,
    grid_sheet,
    largest_piece,
    lattice_tetrahedra,
    sphere_mesh,
    voxelise,
    wedge_mesh,
    write_tetrahedral_vtk,
)


def test_box_count_matches_volume():
    # every voxel meeting the box is kept, so the voxels cover the box and lie within the box
    # grown by one pitch on every side
    pitch = 0.02
    extents = np.array([0.3, 0.2, 0.1])
    points = voxelise(box_mesh(extents), pitch)
    volume = len(points) * pitch**3
    assert np.prod(extents) < volume < np.prod(extents + 2 * pitch)
    assert points.shape[1] == 3


def test_box_count_exact_when_sides_are_even_multiples():
    # side 0.2 = 4 pitches: centres at -0.1, -0.05, 0, 0.05, 0.1 per axis (faces included)
    points = voxelise(box_mesh(0.2), 0.05)
    assert len(points) == 125
    assert np.allclose(np.abs(points).max(axis=0), 0.1)


def test_sphere_count_close_to_volume():
    radius, pitch = 0.1, 0.01
    points = voxelise(sphere_mesh(radius), pitch)
    volume = len(points) * pitch**3
    # between the sphere's volume and that of the sphere grown by half a voxel diagonal
    assert 4 / 3 * np.pi * radius**3 < volume < 4 / 3 * np.pi * (radius + pitch * np.sqrt(3) / 2) ** 3
    assert np.all(np.linalg.norm(points, axis=1) < radius + pitch)


def test_wedge_is_watertight_prism():
    mesh = wedge_mesh(0.4, 0.2, 0.3)
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(0.5 * 0.4 * 0.2 * 0.3)
    points = voxelise(mesh, 0.05)
    assert points[:, 2].min() >= -0.025 - 1e-9


@pytest.mark.parametrize("pitch", [0.0, -0.1, float("nan")])
def test_bad_pitch(pitch):
    with pytest.raises(ValueError, match="pitch"):
        voxelise(box_mesh(0.1), pitch)


def test_empty_mesh():
    with pytest.raises(ValueError, match="empty"):
        voxelise(trimesh.Trimesh(), 0.1)


def test_non_watertight_mesh():
    mesh = box_mesh(0.2)
    open_mesh = trimesh.Trimesh(mesh.vertices, mesh.faces[:-2], process=False)
    with pytest.raises(ValueError, match="watertight"):
        voxelise(open_mesh, 0.05)


def test_nan_vertices():
    mesh = box_mesh(0.2)
    vertices = mesh.vertices.copy()
    vertices[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        voxelise(trimesh.Trimesh(vertices, mesh.faces, process=False), 0.05)


def test_lattice_tetrahedra_box():
    points = voxelise(box_mesh(0.2), 0.05)  # 5 x 5 x 5 centres
    nodes, tets = lattice_tetrahedra(points, 0.05)
    assert len(nodes) == 125 and tets.shape == (6 * 4**3, 4)
    x = nodes[tets]
    volume = np.linalg.det(x[:, 1:] - x[:, :1]) / 6
    assert np.all(volume > 0)
    # the tets tile the box spanned by the centres exactly
    assert volume.sum() == pytest.approx(0.2**3)


def _block(corner, n: int, pitch: float = 0.05) -> np.ndarray:
    """``n^3`` voxel centres from ``corner`` (lattice units) up."""
    grid = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    return (grid + np.asarray(corner)) * pitch


def test_cells_apart_from_the_largest_face_joined_piece_are_dropped():
    """A 3^3 block (8 cells), a 2^3 block touching it only along an edge and another only at a
    corner: one piece by shared nodes, three by shared faces; the two small blocks go."""
    big = _block((0, 0, 0), 3)
    edge = _block((2, 2, 0), 2)  # shares big's edge from (2, 2, 0) to (2, 2, 1)
    corner = _block((-1, -1, -1), 2)  # shares big's corner (0, 0, 0)
    points = np.concatenate([big, edge, corner])
    points = np.unique(np.round(points, 6), axis=0)
    with pytest.warns(LatticeWarning, match="2 of 10 cells"):
        nodes, tets = lattice_tetrahedra(points, 0.05)
    assert len(nodes) == 27 and len(tets) == 6 * 8
    assert largest_piece(np.array([[0, 0, 0], [1, 0, 0], [5, 5, 5]])).tolist() == [True, True, False]


def test_lattice_tetrahedra_needs_a_cell():
    with pytest.raises(ValueError, match="cell"):
        lattice_tetrahedra(np.zeros((1, 3)), 0.05)


def test_vtk_writer(tmp_path):
    nodes, tets = lattice_tetrahedra(voxelise(box_mesh(0.1), 0.05), 0.05)
    path = tmp_path / "cube.vtk"
    write_tetrahedral_vtk(path, nodes, tets)
    text = path.read_text().splitlines()
    assert f"POINTS {len(nodes)} double" in text
    assert f"CELLS {len(tets)} {5 * len(tets)}" in text
    assert text[-1] == "10"


def test_grid_sheet():
    vertices, faces = grid_sheet(0.4, 0.1)
    assert vertices.shape == (25, 3) and faces.shape == (32, 3)
    assert np.allclose(vertices[:, 2], 0) and np.allclose(vertices.mean(axis=0), 0)
