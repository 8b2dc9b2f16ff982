"""Filmstrip previews of mesh sequences (docs, MLflow artifacts, eyeballing synthetic motions).

One row per sequence, one column per chosen frame, drawn with matplotlib's Agg backend as
shaded triangles (Lambert shading, orthographic camera), so it works on headless machines
without an OpenGL stack. Meshes are in metres with z up and the body facing -y; the default
camera looks at the front from 30 degrees to the body's left so that motion towards the camera
(punches, knee raises) still reads. All panels of a row share the same axes limits, so
translation (hops) shows, and a faint line marks the row's lowest point (the ground).
"""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from aniformer.io.files import atomic_path  # noqa: E402

_BASE_COLOUR = np.array([0.62, 0.70, 0.86])
_LIGHT = np.array([-0.3, -1.0, 0.6]) / np.linalg.norm([-0.3, -1.0, 0.6])


def _shaded_colours(triangles: np.ndarray) -> np.ndarray:
    """Per-face RGB from a two-sided Lambert term plus ambient."""
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True) + 1e-12
    diffuse = np.abs(normals @ _LIGHT)
    return np.clip(_BASE_COLOUR * (0.35 + 0.65 * diffuse[:, None]), 0.0, 1.0)


def render_filmstrip(
    rows: list[tuple[str, np.ndarray, np.ndarray]],
    path: str | os.PathLike,
    frames: int | None = 8,
    title: str | None = None,
    panel_px: int = 120,
    view: tuple[float, float] = (10.0, -60.0),
) -> Path:
    """Render ``rows`` of (label, vertices (T, V, 3), faces (F, 3)) to a PNG at ``path``.

    Each row shows up to ``frames`` evenly spaced frames of its sequence (all frames if None).
    ``view`` is matplotlib's (elevation, azimuth) in degrees; (0, -90) is straight from the front.
    The file is written to a temporary name in the same directory and then renamed, so readers
    never see a partial PNG. Returns the path.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    columns = max(len(v) if frames is None else min(frames, len(v)) for _, v, _ in rows)
    inch = panel_px / 100.0
    header = 0.3 if title else 0.0
    fig = plt.figure(figsize=(columns * inch, len(rows) * inch + header), dpi=100)
    if title:
        fig.suptitle(title, fontsize=8)
    top = 1.0 - header / (len(rows) * inch + header)
    for r, (label, vertices, faces) in enumerate(rows):
        vertices = np.asarray(vertices, dtype=np.float64)
        count = len(vertices) if frames is None else min(frames, len(vertices))
        chosen = np.linspace(0, len(vertices) - 1, count).round().astype(int)
        box = _sequence_box(vertices)
        for c, t in enumerate(chosen):
            left, bottom = c / columns, top - (r + 1) * top / len(rows)
            ax = fig.add_axes((left, bottom, 1 / columns, top / len(rows)), projection="3d")
            _frame_axes(ax, box, view, zoom=1.6)
            _add_mesh(ax, vertices[t][faces])
            ax.text2D(0.5, 0.02, f"t={t}", transform=ax.transAxes, ha="center", fontsize=5)
            if c == 0:
                ax.text2D(0.02, 0.92, label, transform=ax.transAxes, fontsize=6)
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format="png", dpi=100)
    finally:
        plt.close(fig)
    return path


def render_animation_gif(
    panels: list[tuple[str, np.ndarray, np.ndarray]],
    path: str | os.PathLike,
    fps: float = 30.0,
    max_frames: int | None = 60,
    panel_px: int = 240,
    view: tuple[float, float] = (10.0, -60.0),
    progress=None,
    max_faces: int = 2_500,
) -> Path:
    """An animated GIF of ``panels`` of (label, vertices (N, V, 3), faces) side by side (e.g. driver | result).

    All panels must have the same number of frames N. At most ``max_frames`` evenly spaced frames
    are drawn (all if None); each GIF frame lasts as long as the frames it stands for at ``fps``, so
    the preview keeps real time. Each panel keeps one set of axes limits over the whole sequence.
    ``progress(1)`` is called after every drawn frame. Meshes with more than ``max_faces`` faces
    are drawn decimated to that many (``preview_mesh``): matplotlib draws ~10^4-10^5 polygons per
    second, and a 240-pixel panel shows no more (a body ~200 pixels tall: a face is a few pixels).
    Written to a temporary name, then renamed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lengths = {len(v) for _, v, _ in panels}
    if len(lengths) != 1:
        raise ValueError(f"panels have different frame counts: {sorted(lengths)}")
    n = lengths.pop()
    panels = [(label, vertices, faces) if len(faces) <= max_faces else (label, *preview_mesh(vertices, faces, max_faces))
              for label, vertices, faces in panels]
    count = n if max_frames is None else max(1, min(max_frames, n))
    chosen = np.linspace(0, n - 1, count).round().astype(int)
    duration_ms = max(20, int(round(1000.0 / fps * n / count)))  # GIF delays are in 10 ms units
    images = _gif_frames(panels, chosen, panel_px, view, progress)
    with atomic_path(path) as tmp:
        images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=duration_ms, loop=0,
                       optimize=False)
    return path


def preview_mesh(frames: np.ndarray, faces: np.ndarray, max_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """``frames (N, V, 3)`` of a mesh as frames of its quadric decimation to ``max_faces`` faces: the decimated
    first frame's vertices ride the closest points of the mesh (barycentric), so every frame decimates alike."""
    import trimesh

    from aniformer.surface import closest_points

    first = np.asarray(frames[0], np.float64)
    whole = trimesh.Trimesh(first, faces, process=False)
    whole.merge_vertices()  # vertices split at seams: decimated apart, their edges were torn open in the preview
    decimated = whole.simplify_quadric_decimation(face_count=max_faces)
    return closest_points(decimated.vertices, first, faces).on(frames, faces), np.asarray(decimated.faces, np.int64)


def _gif_frames(panels: list[tuple[str, np.ndarray, np.ndarray]], chosen: np.ndarray, panel_px: int,
                view: tuple[float, float], progress) -> list:
    """The ``chosen`` frames of ``panels`` drawn side by side, as PIL images; ``progress(1)`` after each."""
    from PIL import Image

    inch = panel_px / 100.0
    fig = plt.figure(figsize=(len(panels) * inch, inch), dpi=100)
    axes = [fig.add_axes((p / len(panels), 0.0, 1 / len(panels), 1.0), projection="3d") for p in range(len(panels))]
    frame_labels, meshes, images = [], [None] * len(panels), []
    for ax, (label, vertices, _) in zip(axes, panels):  # the axes stay: clearing them was a third of the time
        _frame_axes(ax, _sequence_box(vertices), view, zoom=1.5)
        ax.text2D(0.03, 0.93, label, transform=ax.transAxes, fontsize=8)
        frame_labels.append(ax.text2D(0.5, 0.02, "", transform=ax.transAxes, ha="center", fontsize=6))
    try:
        for t in chosen:
            for p, (ax, (_, vertices, faces)) in enumerate(zip(axes, panels)):
                if meshes[p] is not None:
                    meshes[p].remove()
                meshes[p] = _add_mesh(ax, np.asarray(vertices[t], np.float64)[faces])
                frame_labels[p].set_text(f"frame {t}")
            fig.canvas.draw()
            rgba = np.asarray(fig.canvas.buffer_rgba())
            # an octree palette: PIL's default median cut was a fifth of the preview's time (8x slower; mean error
            # 1.2 of 255 levels against 0.1, not visible)
            images.append(Image.fromarray(rgba[..., :3].copy()).quantize(256, method=Image.Quantize.FASTOCTREE,
                                                                          dither=Image.Dither.NONE))
            if progress is not None:
                progress(1)
    finally:
        plt.close(fig)
    return images


def _sequence_box(vertices: np.ndarray) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """(centre, half side, low, high) of the cube around a whole sequence: one axes limit for all its frames."""
    flat = np.asarray(vertices, np.float64).reshape(-1, 3)
    low, high = flat.min(0), flat.max(0)
    return (low + high) / 2, (high - low).max() / 2, low, high


def _add_mesh(ax, triangles: np.ndarray) -> Poly3DCollection:
    """Shaded ``triangles`` drawn on ``ax``: the collection, for removing it."""
    mesh = Poly3DCollection(triangles, facecolors=_shaded_colours(triangles), linewidths=0)
    ax.add_collection3d(mesh)
    return mesh


def _frame_axes(ax, box: tuple, view: tuple[float, float], zoom: float) -> None:
    """Orthographic 3D axes limited to ``box``, a faint line at its lowest point (the ground)."""
    centre, half, low, high = box
    ax.plot([centre[0] - half, centre[0] + half], [high[1], high[1]], [low[2], low[2]], color="0.6", linewidth=0.5)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.set_box_aspect((1, 1, 1), zoom=zoom)
    ax.set_proj_type("ortho")
    ax.view_init(elev=view[0], azim=view[1])
    ax.set_axis_off()
