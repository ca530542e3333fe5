"""The viewer page: ground truth and every sampled future in 3D, in one HTML file.

Built with plotly (its ``plotly.min.js`` written into the page), so it opens from disk in any
browser with WebGL. One trace per trajectory (meshes, or leaves): the truth dark and opaque,
futures lighter and translucent, static objects and the ground grey (a legend click hides one);
a time slider and play / pause (frames at ``dt``, or ``fps``).
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import numpy as np

from hrn_pyg.commands.view import DEFAULT_FPS
from hrn_pyg.data.kinds import STATIC
from hrn_pyg.export.animate import rig
from hrn_pyg.export.gltf import object_rgba
from hrn_pyg.export.scene_meshes import SceneMeshes
from hrn_pyg.export.sequence import frame_mesh
from hrn_pyg.utils.files import atomic_write_text

__all__ = ["viewer_html", "write_viewer", "VIEWER_DIV", "require_plotly"]

#: the id of the page's plot element (the browser test finds it by this)
VIEWER_DIV = "hrn-viewer"
#: camera of the page: where the eye sits, relative to the scene's box
CAMERA_EYE = (1.4, -1.6, 0.9)


def require_plotly():
    """``plotly.graph_objects``, or a ValueError that says how to install it."""
    try:
        import plotly.graph_objects as go
    except ImportError:
        raise ValueError("the viewer needs plotly: pip install 'hrn_pyg[viewer]'") from None
    return go


def _colour(rgba: list[float]) -> str:
    r, g, b = (int(round(255 * c)) for c in rgba[:3])
    return f"rgb({r},{g},{b})"


def _mesh_trace(go, frame: tuple, name: str, truth: bool, objects) -> object:
    """A Mesh3d of one frame (``frame_mesh``'s arrays), coloured per face by its object: the
    face's intensity picks its object's band of a stepwise colour scale (numbers, not a colour
    string per face, keep the page small)."""
    vertices, faces, _, face_object = frame
    vertices = vertices.astype(np.float32)  # a page's size is mostly vertices: float32 halves it
    ordered = sorted(objects, key=lambda o: o.object.index)
    band = np.zeros(ordered[-1].object.index + 1)  # object id -> its band of the colour scale
    scale = []
    for n, o in enumerate(ordered):
        band[o.object.index] = n
        colour = _colour(object_rgba(o.object.index, o.object.material, truth))
        scale += [[n / len(ordered), colour], [(n + 1) / len(ordered), colour]]
    intensity = (band[face_object] + 0.5) / len(ordered)
    return go.Mesh3d(x=vertices[:, 0], y=vertices[:, 1], z=vertices[:, 2], i=faces[:, 0], j=faces[:, 1],
                     k=faces[:, 2], intensity=intensity, intensitymode="cell", colorscale=scale, cmin=0.0, cmax=1.0,
                     showscale=False, name=name, showlegend=True, opacity=1.0 if truth else 0.45, flatshading=True,
                     lighting={"ambient": 0.55, "diffuse": 0.7, "specular": 0.1}, hoverinfo="name")


def _moved(go, frame: tuple) -> object:
    """The part of a frame's trace that changes: the vertices alone."""
    vertices = frame[0]
    vertices = vertices.astype(np.float32)
    return go.Mesh3d(x=vertices[:, 0], y=vertices[:, 1], z=vertices[:, 2])


def _points_trace(go, points: np.ndarray, name: str, truth: bool) -> object:
    return go.Scatter3d(x=points[:, 0], y=points[:, 1], z=points[:, 2], mode="markers", name=name,
                        marker={"size": 3, "color": "rgb(30,30,30)" if truth else "rgb(90,160,220)",
                                "opacity": 1.0 if truth else 0.45}, hoverinfo="name")


def viewer_html(trajectories: Mapping[str, np.ndarray], meshes: SceneMeshes | None = None,
                dt: float | None = None, fps: float | None = None, title: str = "") -> str:
    """The page (a full HTML document with plotly inside) of named leaf trajectories
    ``(T, L, 3)``, the first the ground truth; with ``meshes``, as the scene's meshes."""
    go = require_plotly()
    names = list(trajectories)
    if not names:
        raise ValueError("viewer: no trajectories")
    steps = int(np.asarray(trajectories[names[0]]).shape[0])
    fps = float(fps or DEFAULT_FPS)
    static_traces, moving = [], []
    if meshes is not None:
        scene_rig = rig(meshes)
        animated = {n: scene_rig.animate(trajectories[n]) for n in names}
        first = animated[names[0]]
        still = tuple(o for o in first if o.object.material == STATIC)
        if still:
            static_traces.append(_mesh_trace(go, frame_mesh(still, 0), "static", True, still))
        moving_of = {n: tuple(o for o in animated[n] if o.object.material != STATIC) for n in names}

        def trace(n: str, t: int):
            return _mesh_trace(go, frame_mesh(moving_of[n], t), n, n == names[0], moving_of[n])

        def update(n: str, t: int):
            return _moved(go, frame_mesh(moving_of[n], t))
        extent = np.concatenate([o.vertices.reshape(-1, 3) for o in first])
    else:
        def trace(n: str, t: int):
            return _points_trace(go, np.asarray(trajectories[n][t]), n, n == names[0])

        def update(n: str, t: int):
            points = np.asarray(trajectories[n][t])
            return go.Scatter3d(x=points[:, 0], y=points[:, 1], z=points[:, 2])
        extent = np.asarray(trajectories[names[0]]).reshape(-1, 3)
    low, high = extent.min(axis=0), extent.max(axis=0)
    pad = 0.25 * float((high - low)[:2].max())
    gx, gy = [low[0] - pad, high[0] + pad], [low[1] - pad, high[1] + pad]
    ground = go.Mesh3d(x=[gx[0], gx[1], gx[1], gx[0]], y=[gy[0], gy[0], gy[1], gy[1]], z=[0, 0, 0, 0],
                       i=[0, 0], j=[1, 2], k=[2, 3], color="rgb(225,225,225)", name="ground", showlegend=False,
                       hoverinfo="skip")
    fixed = [ground, *static_traces]
    data = fixed + [trace(n, 0) for n in names]
    animated_ids = list(range(len(fixed), len(data)))
    frames = [go.Frame(name=str(t), data=[update(n, t) for n in names], traces=animated_ids) for t in range(steps)]
    seconds = f" ({dt:g} s a step)" if dt else ""
    play = {"frame": {"duration": 1000.0 / fps, "redraw": True}, "transition": {"duration": 0},
            "fromcurrent": True, "mode": "immediate"}
    layout = go.Layout(
        title={"text": title or "ground truth (dark) and sampled futures (light): click a legend entry to hide it"},
        scene={"aspectmode": "data", "camera": {"eye": dict(zip("xyz", CAMERA_EYE))},
               "xaxis": {"title": "x (m)"}, "yaxis": {"title": "y (m)"}, "zaxis": {"title": "z (m)"}},
        legend={"title": {"text": "trajectories"}, "itemsizing": "constant"},
        margin={"l": 0, "r": 0, "t": 40, "b": 0}, paper_bgcolor="white",
        updatemenus=[{"type": "buttons", "direction": "left", "x": 0.0, "y": 0.0, "xanchor": "left", "yanchor": "top",
                      "buttons": [{"label": "play", "method": "animate", "args": [None, play]},
                                  {"label": "pause", "method": "animate",
                                   "args": [[None], {"frame": {"duration": 0, "redraw": False}, "mode": "immediate"}]}]}],
        sliders=[{"active": 0, "x": 0.16, "len": 0.82, "y": 0.0, "yanchor": "top",
                  "currentvalue": {"prefix": f"step{seconds}: "},
                  "steps": [{"label": str(t), "method": "animate",
                             "args": [[str(t)], {"frame": {"duration": 0, "redraw": True}, "mode": "immediate",
                                                 "transition": {"duration": 0}}]} for t in range(steps)]}],
    )
    figure = go.Figure(data=data, layout=layout, frames=frames)
    return figure.to_html(include_plotlyjs=True, full_html=True, div_id=VIEWER_DIV, auto_play=False,
                          default_width="100%", default_height="96vh",
                          config={"displaylogo": False, "responsive": True})


def write_viewer(path: str | os.PathLike, trajectories: Mapping[str, np.ndarray], meshes: SceneMeshes | None = None,
                 dt: float | None = None, fps: float | None = None, title: str = "") -> None:
    """Write :func:`viewer_html` to ``path`` (one self-contained file), atomically."""
    atomic_write_text(path, viewer_html(trajectories, meshes, dt, fps, title))
