"""VTK for ParaView (meshio): ``<out>/<trajectory>.pvd``, a time series of one ``.vtu`` per frame
(time ``t dt``), the triangles with their object id as cell and point data ``object``."""

from __future__ import annotations

import os
from pathlib import Path
from xml.sax.saxutils import quoteattr

from hrn_pyg.export.animate import ObjectFrames
from hrn_pyg.export.sequence import FRAME_NAME, frame_mesh
from hrn_pyg.utils.files import atomic_path, atomic_write_text

__all__ = ["write_vtk_series"]


def write_vtk_series(folder: str | os.PathLike, name: str, objects: tuple[ObjectFrames, ...], dt: float) -> Path:
    """Write ``folder/name/frame_0000.vtu`` ... and ``folder/name.pvd``; returns the ``.pvd``."""
    import meshio

    folder = Path(folder)
    entries = []
    for t in range(objects[0].vertices.shape[0]):  # one file per frame
        vertices, faces, vertex_object, face_object = frame_mesh(objects, t)
        mesh = meshio.Mesh(vertices, [("triangle", faces)], point_data={"object": vertex_object},
                           cell_data={"object": [face_object]})
        relative = f"{name}/{FRAME_NAME.format(t)}.vtu"
        with atomic_path(folder / relative, suffix=".vtu") as tmp:
            meshio.write(tmp, mesh, file_format="vtu")
        entries.append(f'    <DataSet timestep="{t * float(dt):.9g}" part="0" file={quoteattr(relative)}/>')
    pvd = folder / f"{name}.pvd"
    atomic_write_text(pvd, '<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n  <Collection>\n'
                      + "\n".join(entries) + "\n  </Collection>\n</VTKFile>\n")
    return pvd
